"""multical's ``calibration.json``: written as multical exports it (poses absolute, or
relative to a master camera), read back, imported with frames and reconstructed."""

from __future__ import annotations

import json

import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.io import load_rig, open_dataset
from edgerecon.io.calib_multical import multical_calibration
from edgerecon.io.calibration import detect_calibration_format
from edgerecon.synth import GroundTruth
from edgerecon.types import CalibrationError
from tests.io.test_importer import from_camera0, reconstruct_score


@pytest.fixture(scope="module")
def scene(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    return ds, GroundTruth.open(tiny_dataset)


def _T(cam) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cam.R, cam.t
    return T


def _multical(rig, master: str | None = None, fisheye: str | None = None) -> dict:
    """multical's export_json: cameras, and camera_poses absolute or ``k_to_master``."""
    cameras = {
        c.name: {
            "model": "standard",
            "image_size": [c.width, c.height],
            "K": c.K.tolist(),
            "dist": [([0.03, -0.01, 0.004, -0.001] if c.name == fisheye else list(c.dist))],
        }
        for c in rig
    }
    poses = {}
    base = None if master is None else _T(rig.cameras[rig.index(master)])
    for c in rig:
        T = _T(c) if base is None else _T(c) @ np.linalg.inv(base)
        key = c.name if master is None or c.name == master else f"{c.name}_to_{master}"
        poses[key] = {"R": T[:3, :3].tolist(), "T": T[:3, 3].tolist()}
    return {"cameras": cameras, "camera_poses": poses, "image_sets": {"rgb": []}}


def test_absolute_and_master_relative_poses(scene, tmp_path):
    ds, _ = scene
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(_multical(ds.rig)))
    assert detect_calibration_format(path) == "multical"
    assert detect_calibration_format(tmp_path) == "multical"
    got = load_rig(tmp_path)
    for a, b in zip(got, ds.rig, strict=True):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)
        np.testing.assert_allclose(a.K, b.K)
    # Relative to cam2 (the master's frame is the world).
    path.write_text(json.dumps(_multical(ds.rig, master="cam2")))
    got = load_rig(path)
    base = _T(ds.rig.cameras[2])
    for a, b in zip(got, ds.rig, strict=True):
        want = _T(b) @ np.linalg.inv(base)
        np.testing.assert_allclose(a.R, want[:3, :3], atol=1e-9)
        np.testing.assert_allclose(a.t, want[:3, 3], atol=1e-9)
    np.testing.assert_allclose(got.cameras[2].R, np.eye(3), atol=1e-12)
    # A fisheye camera (4 coefficients) comes with its lens.
    path.write_text(json.dumps(_multical(ds.rig, fisheye="cam1")))
    cal = multical_calibration(path)
    assert list(cal.lenses) == ["cam1"] and not cal.rig.cameras[1].has_distortion
    data = _multical(ds.rig, master="cam0")
    del data["camera_poses"]["cam3_to_cam0"]
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match="no pose for cameras cam3"):
        load_rig(path)


def test_import_multical_and_reconstruct(scene, tmp_path, capsys):
    ds, gt = scene
    (tmp_path / "calibration.json").write_text(json.dumps(_multical(ds.rig, master="cam0")))
    frames = [f"{n}={ds.root / 'frames' / n}" for n in ds.rig.names]
    out = tmp_path / "ds"
    assert (
        main(["import", str(tmp_path / "calibration.json"), *frames, "-o", str(out), "--json"]) == 0
    )
    assert json.loads(capsys.readouterr().out)["calibration_format"] == "multical"
    score = reconstruct_score(out, tmp_path, gt, to_truth=from_camera0(ds.rig))
    assert score.precision > 0.85 and score.num_pred > 150, score


def test_malformed_values_are_calibration_errors(scene, tmp_path):
    # Found by mutating valid files: every malformed value is a CalibrationError naming it.
    ds, _ = scene
    path = tmp_path / "calibration.json"
    for change, match in (
        (lambda d: d["cameras"]["cam1"].update(dist="x"), "cam1.*dist is not a list of numbers"),
        (lambda d: d["cameras"]["cam1"].update(dist=[[{}]]), "dist is not a list of numbers"),
        (lambda d: d["cameras"]["cam2"].update(K=[[1, 2]]), "cam2.*K must hold 9"),
        (lambda d: d["camera_poses"]["cam0"].update(R="x"), "R is not an array of numbers"),
    ):
        data = _multical(ds.rig)
        change(data)
        path.write_text(json.dumps(data))
        with pytest.raises(CalibrationError, match=match):
            load_rig(path)
