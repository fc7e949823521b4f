"""Kalibr's ``camchain.yaml``: written as Kalibr writes it, read back to the rig (in camera
0's frame), imported with frames and reconstructed; refused models."""

from __future__ import annotations

import json

import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.geometry import Rig
from edgerecon.io import load_rig, open_dataset
from edgerecon.io.calib_kalibr import read_kalibr
from edgerecon.io.calibration import detect_calibration_format
from edgerecon.synth import GroundTruth
from edgerecon.types import CalibrationError
from tests.io.test_importer import from_camera0, reconstruct_score


@pytest.fixture(scope="module")
def scene(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    return ds, GroundTruth.open(tiny_dataset)


def _row(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _camchain(
    rig: Rig, distortion: str = "radtan", model: str = "pinhole", imu: bool = False
) -> str:
    """A camchain.yaml as Kalibr's yaml.dump lays it out: T_cn_cnm1 maps camera n-1's frame
    into camera n's."""
    lines = []
    for n, cam in enumerate(rig):
        lines.append(f"cam{n}:")
        if imu:  # camchain-imucam.yaml: the IMU's frame -> the camera's
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = cam.R, cam.t
            lines.append("  T_cam_imu:")
            lines += [f"  - {_row(r)}" for r in T]
        elif n > 0:
            prev = rig.cameras[n - 1]
            T_prev, T_cur = np.eye(4), np.eye(4)
            T_prev[:3, :3], T_prev[:3, 3] = prev.R, prev.t
            T_cur[:3, :3], T_cur[:3, 3] = cam.R, cam.t
            T = T_cur @ np.linalg.inv(T_prev)
            lines.append("  T_cn_cnm1:")
            lines += [f"  - {_row(r)}" for r in T]
        k1, k2, p1, p2 = np.ravel(cam.dist)[:4]
        lines += [
            f"  cam_overlaps: [{', '.join(str(k) for k in range(len(rig)) if k != n)}]",
            f"  camera_model: {model}",
            f"  distortion_coeffs: {_row([k1, k2, p1, p2])}",
            f"  distortion_model: {distortion}",
            f"  intrinsics: {_row([cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]])}",
            f"  resolution: [{cam.width}, {cam.height}]",
            f"  rostopic: /cam{n}/image_raw",
        ]
    return "\n".join(lines) + "\n"


def _in_camera0(rig: Rig) -> Rig:
    """The rig with camera 0's frame as the world's (what a camera chain records)."""
    R0, t0 = rig.cameras[0].R, rig.cameras[0].t
    cams = tuple(
        type(c)(name=f"cam{n}", width=c.width, height=c.height, K=c.K, R=c.R @ R0.T,
                t=c.t - c.R @ R0.T @ t0, dist=c.dist)
        for n, c in enumerate(rig)
    )  # fmt: skip
    return Rig(cameras=cams, unit=rig.unit)


def test_camchain_reads_as_the_rig_in_camera0s_frame(scene, tmp_path):
    ds, _ = scene
    path = tmp_path / "camchain-kalibr.yaml"
    path.write_text(_camchain(ds.rig))
    assert detect_calibration_format(path) == "kalibr"
    assert detect_calibration_format(tmp_path) == "kalibr"
    got = load_rig(tmp_path)
    want = _in_camera0(ds.rig)
    assert got.names == want.names and got.unit == "m"
    for a, b in zip(got, want, strict=True):
        assert a.size == b.size
        np.testing.assert_allclose(a.K, b.K, atol=1e-12)
        np.testing.assert_allclose(a.R, b.R, atol=1e-9)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)
    np.testing.assert_allclose(got.cameras[0].R, np.eye(3), atol=1e-12)


def test_refused_models_and_bad_chains(scene, tmp_path):
    ds, _ = scene
    path = tmp_path / "camchain.yaml"
    for text, match in (
        (_camchain(ds.rig, distortion="fov"), "distortion_model 'fov'"),
        (_camchain(ds.rig, distortion="equidistant"), "have fisheye lenses: import"),
        (_camchain(ds.rig, model="omni"), "camera_model 'omni'"),
        (_camchain(ds.rig).replace("  T_cn_cnm1:", "  T_other:", 1), "cam1 without T_cn_cnm1"),
        (_camchain(ds.rig).replace("resolution: [320, 240]", "resolution: [320]", 1),
         "resolution must hold 2"),
    ):  # fmt: skip
        path.write_text(text)
        with pytest.raises(CalibrationError, match=match):
            read_kalibr(path)
    bad = _camchain(ds.rig).replace("- [", "- [3.0, ", 1)  # a 5-wide first row
    path.write_text(bad)
    with pytest.raises(CalibrationError, match="cam1: T_cn_cnm1 is not a list of numbers"):
        read_kalibr(path)


def test_import_camchain_and_reconstruct(scene, tmp_path, capsys):
    ds, gt = scene
    (tmp_path / "camchain.yaml").write_text(_camchain(ds.rig))
    frames = [f"cam{n}={ds.root / 'frames' / name}" for n, name in enumerate(ds.rig.names)]
    out = tmp_path / "ds"
    assert (
        main(["import", str(tmp_path / "camchain.yaml"), *frames, "--out", str(out), "--json"]) == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["calibration_format"] == "kalibr"
    assert report["unit_note"].startswith("m (Kalibr")
    score = reconstruct_score(out, tmp_path, gt, to_truth=from_camera0(ds.rig))
    assert score.precision > 0.85 and score.num_pred > 150, score


def test_imu_camera_chain_puts_the_imu_at_the_origin(scene, tmp_path):
    # camchain-imucam.yaml: every camera's T_cam_imu (IMU frame -> camera), no chain.
    ds, _ = scene
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(_camchain(ds.rig, imu=True))
    got = read_kalibr(path)
    for a, b in zip(got, ds.rig, strict=True):
        np.testing.assert_allclose(a.R, b.R, atol=1e-9)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)
