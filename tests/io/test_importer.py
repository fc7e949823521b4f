"""``edgerecon import``: COLMAP binary models with many images per camera, anipose / Pose2Sim
and caliscope TOML, each to a dataset that reconstructs; matching, offsets, checks."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil

import cv2
import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.geometry import Rig
from edgerecon.io import load_rig, open_dataset, read_ply
from edgerecon.io.calib_toml import read_toml_calibration, toml_flavour
from edgerecon.io.calibration import save_rig
from edgerecon.io.colmap import (
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    rig_to_colmap,
    rotation_to_quaternion,
    write_colmap_model,
)
from edgerecon.io.importer import import_dataset, level_horizon_up, parse_up
from edgerecon.quality import evaluate_clouds
from edgerecon.synth import GroundTruth
from edgerecon.types import CalibrationError, DataError
from tests.conftest import ring_rig


def _fmt(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in np.ravel(values)) + "]"


def _matrix(m) -> str:
    return "[" + ", ".join(_fmt(row) for row in np.asarray(m)) + "]"


def anipose_toml(rig: Rig, scale: float = 1.0, pose2sim: bool = False) -> str:
    """An anipose ``calibration.toml`` (Pose2Sim: 4 distortions, float sizes, fisheye)."""
    out = []
    for k, cam in enumerate(rig):
        rvec = cv2.Rodrigues(cam.R)[0].ravel()
        size = f"[{cam.width}.0, {cam.height}.0]" if pose2sim else f"[{cam.width}, {cam.height}]"
        dist = cam.dist[:4] if pose2sim else cam.dist
        out += [
            f"[cam_{k:02d}]" if pose2sim else f"[cam_{k}]",
            f'name = "{cam.name}"',
            f"size = {size}",
            f"matrix = {_matrix(cam.K)}",
            f"distortions = {_fmt(dist)}",
            f"rotation = {_fmt(rvec)}",
            f"translation = {_fmt(cam.t * scale)}",
        ]
        if pose2sim:
            out.append("fisheye = false")
        out.append("")
    out += ["[metadata]", "adjusted = false", "error = 0.0", ""]
    return "\n".join(out)


def caliscope_toml(rig: Rig, ignored: int | None = None) -> str:
    """A caliscope ``camera_array.toml`` (``[cameras.N]``, 3x3 rotations, metres)."""
    out = []
    for k, cam in enumerate(rig):
        out += [
            f"[cameras.{k}]",
            f"cam_id = {k}",
            "rotation_count = 0",
            "error = 0.4",
            f"ignore = {'true' if k == ignored else 'false'}",
            f"size = [{cam.width}, {cam.height}]",
            f"matrix = {_matrix(cam.K)}",
            f"distortions = {_fmt(cam.dist)}",
            f"translation = {_fmt(cam.t)}",
            f"rotation = {_matrix(cam.R)}",
            "",
        ]
    return "\n".join(out)


def _assert_same_rig(got: Rig, want: Rig, scale: float = 1.0, atol: float = 1e-9) -> None:
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a.size == b.size
        np.testing.assert_allclose(a.K, b.K, atol=atol)
        np.testing.assert_allclose(a.R, b.R, atol=atol)
        np.testing.assert_allclose(a.t, b.t * scale, atol=atol * scale)
        np.testing.assert_allclose(a.dist, b.dist, atol=atol)


# ----------------------------------------------------------------------------- readers
def test_toml_readers_known_answers(tmp_path):
    rig = ring_rig(4, dist=(-0.1, 0.02, 0.001, -0.002, 0.005))
    ani = tmp_path / "calibration.toml"
    ani.write_text(anipose_toml(rig, scale=1000.0))
    got = load_rig(ani)
    assert toml_flavour(__import__("tomllib").loads(ani.read_text())) == "anipose"
    assert got.names == rig.names and got.unit == "mm"  # 4 m away: guessed millimetres
    _assert_same_rig(got, rig, scale=1000.0)
    p2s = tmp_path / "Calib.toml"
    p2s.write_text(anipose_toml(rig, pose2sim=True))
    got = read_toml_calibration(p2s)
    assert got.unit == "m"
    np.testing.assert_allclose(got[2].dist, [*rig[2].dist[:4], 0.0])
    np.testing.assert_allclose(got[1].R, rig[1].R, atol=1e-12)
    cal = tmp_path / "camera_array.toml"
    cal.write_text(caliscope_toml(rig, ignored=3))
    got = load_rig(cal)
    assert got.names == ["cam_0", "cam_1", "cam_2"]  # cam_3 is ignored
    _assert_same_rig(got, Rig(cameras=rig.cameras[:3]))


def test_caliscope_reference_file_matches_its_conversion():
    from tests.conftest import shared_data

    root = shared_data("caliscope_charuco")
    got = load_rig(root / "source" / "camera_array.toml")
    ref = load_rig(root / "rig.json")
    _assert_same_rig(got, ref, atol=0)
    # Its up from the level horizons (SOURCE.md: 0.2896, 0.0152, 0.957).
    np.testing.assert_allclose(level_horizon_up(got), ref.up, atol=1e-3)


def test_toml_errors(tmp_path):
    rig = ring_rig(3)
    bad = tmp_path / "Calib.toml"
    bad.write_text(anipose_toml(rig, pose2sim=True).replace("fisheye = false", "fisheye = true", 1))
    with pytest.raises(CalibrationError, match=r"cameras cam0 have fisheye lenses: import"):
        load_rig(bad)
    bad.write_text(anipose_toml(rig).replace("rotation = [", "rotation = [0.0, ", 1))
    with pytest.raises(CalibrationError, match=r"'cam0'.*rotation must be a Rodrigues"):
        load_rig(bad)
    bad.write_text("[cam_0]\nname = 'x'\n")
    with pytest.raises(CalibrationError, match="not an anipose / Pose2Sim / caliscope"):
        load_rig(bad)
    bad.write_text("[cam_0\n")
    with pytest.raises(CalibrationError, match="not valid TOML"):
        load_rig(bad)


def test_parse_up():
    assert parse_up("-Y") == (0.0, -1.0, 0.0)
    assert parse_up("0,0,2") == (0.0, 0.0, 1.0)
    assert parse_up("auto") == "auto"
    with pytest.raises(ValueError, match="--up"):
        parse_up("sideways")


# ----------------------------------------------------------------------------- import
def _colmap_binary_of(rig: Rig, num_frames: int, noise: float = 2e-5) -> ColmapModel:
    """A COLMAP model as SfM leaves it: images ``camK/00000i.png``, one COLMAP camera per
    physical camera, poses of one camera's images slightly different."""
    rng = np.random.default_rng(3)
    base = rig_to_colmap(rig)
    cameras = {
        k: ColmapCamera(
            camera_id=10 + k,
            model=c.model,
            width=c.width,
            height=c.height,
            params=c.params,
        )
        for k, c in base.cameras.items()
    }
    cameras = {c.camera_id: c for c in cameras.values()}
    images = {}
    for f in range(num_frames):
        for k, cam in enumerate(rig):
            dR = cv2.Rodrigues(noise * rng.normal(size=(3, 1)))[0]
            R = dR @ cam.R
            C = cam.center + noise * rng.normal(size=3)
            image_id = 100 + f * len(rig) + k
            images[image_id] = ColmapImage(
                image_id=image_id,
                qvec=rotation_to_quaternion(R),
                tvec=-R @ C,
                camera_id=11 + k,
                name=f"{cam.name}/{f:06d}.png",
            )
    return ColmapModel(cameras=cameras, images=images)


def reconstruct_score(dataset, tmp_path, gt, scale=1.0, t=3, dense=False, to_truth=None):
    """Reconstruct time t of an imported dataset with the CLI; score of its cloud (dense, or
    sparse: cheaper) against the scene's ground truth (in metres) at 3 cm. ``scale``: the
    dataset's units per metre; ``to_truth``: maps its points into the truth's frame (a
    calibration whose world is one camera's)."""
    out = tmp_path / "rec"
    args = ["reconstruct", "--dataset", str(dataset), "--time", str(t), "--out", str(out)]
    assert main(args + ([] if dense else ["--no-dense"])) == 0
    points = read_ply(out / ("dense.ply" if dense else "sparse.ply")).points3D
    points = points if to_truth is None else to_truth(points)
    ref = gt.reference_cloud(t, "all", min_views=2)
    return evaluate_clouds(points / scale, ref, 0.03)[0]


def from_camera0(rig):
    """``to_truth`` for a calibration whose world is camera 0's frame: X = R0^T (X0 - t0)."""
    R0, t0 = rig.cameras[0].R, rig.cameras[0].t
    return lambda points: (points - t0) @ R0


@pytest.fixture(scope="module")
def scene(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    return ds, GroundTruth.open(tiny_dataset)


def test_import_colmap_binary_with_many_images_per_camera(scene, tmp_path, capsys):
    ds, gt = scene
    model_dir = tmp_path / "colmap" / "sparse" / "0"
    write_colmap_model(model_dir, _colmap_binary_of(ds.rig, ds.num_frames), binary=True)
    assert not (model_dir / "cameras.txt").exists()
    out = tmp_path / "imported"
    code = main(
        [
            "import",
            str(tmp_path / "colmap"),
            "--images",
            str(ds.root / "frames"),
            "--out",
            str(out),
            "--json",
        ]
    )
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report["calibration_format"] == "colmap"
    assert [c["name"] for c in report["cameras"]] == ds.rig.names
    assert {c["matched_by"] for c in report["cameras"]} == {"colmap"}
    imported = open_dataset(out)
    assert imported.num_frames == ds.num_frames
    # Poses: the mean of each camera's 8 images, within the SfM noise.
    _assert_same_rig(imported.rig, ds.rig, atol=1e-4)
    # The original rig gives P 0.81 / R 0.43 here (sparse: P 0.93, 287 points).
    score = reconstruct_score(out, tmp_path, gt, 1.0, dense=True)
    assert score.precision > 0.7 and score.recall > 0.35, score


def test_import_anipose_toml_in_millimetres(scene, tmp_path, capsys):
    ds, gt = scene
    calib = tmp_path / "calibration.toml"
    calib.write_text(anipose_toml(ds.rig, scale=1000.0))
    out = tmp_path / "ani"
    # One folder holding the cameras' image folders, matched by name.
    assert main(["import", str(calib), str(ds.root / "frames"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "guessed from the rig's size" in text and "cam3" in text
    imported = open_dataset(out)
    assert imported.rig.unit == "mm"
    _assert_same_rig(imported.rig, ds.rig, scale=1000.0)
    score = reconstruct_score(out, tmp_path, gt, 1000.0)
    assert score.precision > 0.85 and score.num_pred > 150, score


def test_import_caliscope_toml(scene, tmp_path):
    ds, gt = scene
    calib = tmp_path / "camera_array.toml"
    calib.write_text(caliscope_toml(ds.rig))
    # caliscope names its cameras cam_0..; the frame folders are cam0.. (punctuation ignored)
    report = import_dataset(
        tmp_path / "cs",
        calibration=calib,
        frames=[str(ds.root / "frames")],
        background=[str(ds.root / "background")],
    )
    with report.dataset.open_background() as bg:
        assert bg.num_frames == 12  # the scene's empty-room clip
    assert report.dataset.rig.names == [f"cam_{k}" for k in range(5)]
    assert all(c.matched_by == "name" for c in report.cameras)
    assert report.calibration_format == "toml" and "caliscope" in report.unit_note
    assert report.dataset.rig.up == (0.0, 0.0, 1.0)  # the level horizons point at +Z
    score = reconstruct_score(tmp_path / "cs", tmp_path, gt, 1.0)
    assert score.precision > 0.85 and score.num_pred > 150, score


def test_import_offsets_explicit_names_and_checks(scene, tmp_path):
    ds, _ = scene
    calib = tmp_path / "Calib.toml"
    calib.write_text(anipose_toml(ds.rig, pose2sim=True))
    frames = ds.root / "frames"
    items = [f"{n}={frames / n}" for n in ds.rig.names]
    report = import_dataset(
        tmp_path / "d", calibration=calib, frames=items, offsets={"cam1": 2, "cam3": -1}
    )
    # Negative offsets shift the other cameras: cam3 -> 0, cam1 -> 3, the rest -> 1.
    assert {c.name: c.offset for c in report.cameras} == {
        "cam0": 1,
        "cam1": 3,
        "cam2": 1,
        "cam3": 0,
        "cam4": 1,
    }
    assert report.dataset.num_frames == ds.num_frames - 3
    with report.dataset.open_frames() as src, ds.open_frames() as orig:
        got = src.read(2)
        want = [orig.read(t) for t in (3, 5, 3, 2, 3)]
        for k in range(5):
            np.testing.assert_array_equal(got.images[k], want[k].images[k])
    # Frames at another resolution with the calibration's aspect: intrinsics rescaled.
    half = tmp_path / "half"
    for n in ds.rig.names:
        (half / n).mkdir(parents=True)
        for f in sorted((frames / n).glob("*.png"))[:3]:
            im = cv2.imread(str(f))
            cv2.imwrite(str(half / n / f.name), cv2.resize(im, (160, 120)))
    report = import_dataset(tmp_path / "h", calibration=calib, frames=[str(half)])
    assert report.dataset.rig[0].size == (160, 120)
    assert report.cameras[0].rescaled_from == (320, 240)
    np.testing.assert_allclose(report.dataset.rig[0].K[0, 0], ds.rig[0].K[0, 0] / 2)
    # A camera whose frames have another shape is an error naming it.
    shutil.rmtree(half / "cam2")
    (half / "cam2").mkdir()
    cv2.imwrite(str(half / "cam2" / "000000.png"), np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(CalibrationError, match=r"camera 'cam2'.*100x100.*320x240"):
        import_dataset(tmp_path / "h2", calibration=calib, frames=[str(half)])
    with pytest.raises(DataError, match="camera 'cam9'"):
        import_dataset(tmp_path / "x", calibration=calib, frames=[f"cam9={frames / 'cam0'}"])
    with pytest.raises(DataError, match="exists"):
        import_dataset(tmp_path / "d", calibration=calib, frames=items)


# ----------------------------------------------------------------------------- people-capture rigs
def _yaml_matrix(key: str, m) -> list[str]:
    m = np.atleast_2d(np.asarray(m, np.float64))
    data = ", ".join(f"{v:.10f}" for v in m.ravel())
    return [
        f"{key}: !!opencv-matrix",
        f"  rows: {m.shape[0]}",
        f"  cols: {m.shape[1]}",
        "  dt: d",
        f"  data: [{data}]",
    ]


def easymocap_files(rig: Rig, folder, names, sizes: bool = True) -> None:
    """``intri.yml`` + ``extri.yml`` as EasyMocap writes them (its own YAML writer: quoted
    names, ``!!opencv-matrix``, CRLF line ends), with or without ``H_`` / ``W_``."""
    folder.mkdir(parents=True, exist_ok=True)
    head = ["%YAML:1.0", "---", "names:", *[f'  - "{n}"' for n in names]]
    intri, extri = list(head), list(head)
    for name, cam in zip(names, rig, strict=True):
        intri += _yaml_matrix(f"K_{name}", cam.K) + _yaml_matrix(f"dist_{name}", cam.dist[None])
        if sizes:
            intri += [f"H_{name}: {cam.height}", f"W_{name}: {cam.width}"]
        rvec = cv2.Rodrigues(cam.R)[0]
        extri += _yaml_matrix(f"R_{name}", rvec) + _yaml_matrix(f"Rot_{name}", cam.R)
        extri += _yaml_matrix(f"T_{name}", cam.t[:, None])
    (folder / "intri.yml").write_bytes("\r\n".join(intri).encode() + b"\r\n")
    (folder / "extri.yml").write_bytes("\r\n".join(extri).encode() + b"\r\n")


def panoptic_json(rig: Rig, names, extra: int = 0, scale: float = 100.0) -> str:
    """A Panoptic Studio ``calibration_<seq>.json`` (centimetres) of ``rig`` plus ``extra``
    VGA cameras that were not filmed."""
    cams = [
        {
            "name": name,
            "type": "hd",
            "resolution": [cam.width, cam.height],
            "panel": 0,
            "node": k,
            "K": cam.K.tolist(),
            "distCoef": cam.dist.tolist(),
            "R": cam.R.tolist(),
            "t": (cam.t[:, None] * scale).tolist(),
        }
        for k, (name, cam) in enumerate(zip(names, rig, strict=True))
    ]
    for k in range(extra):
        cam = rig[k]
        cams.append(
            {
                "name": f"01_{k + 1:02d}",
                "type": "vga",
                "resolution": [640, 480],
                "panel": 1,
                "node": k + 1,
                "K": cam.K.tolist(),
                "distCoef": [0.0] * 5,
                "R": cam.R.tolist(),
                "t": ((cam.t + 0.1 * (k + 1))[:, None] * scale).tolist(),
            }
        )
    return json.dumps({"calibDataSource": "160422_ultimatum1_calib", "cameras": cams})


def test_easymocap_and_panoptic_readers_known_answers(tmp_path):
    rig = ring_rig(4, dist=(-0.1, 0.02, 0.001, -0.002, 0.005))
    names = ["01", "02", "03", "04"]
    easymocap_files(rig, tmp_path / "em", names)
    for path in (tmp_path / "em", tmp_path / "em" / "intri.yml", tmp_path / "em" / "extri.yml"):
        got = load_rig(path)
        assert got.names == names and got.unit == "m"
        _assert_same_rig(got, rig, atol=1e-8)
    # No image sizes in the file: from image_sizes, else from the frames in EasyMocap's layout.
    easymocap_files(rig, tmp_path / "ns", names, sizes=False)
    with pytest.raises(CalibrationError, match=r"camera '01' has no image size.*images/01/"):
        load_rig(tmp_path / "ns")
    assert (
        load_rig(tmp_path / "ns", image_sizes=(rig[0].width, rig[0].height))[3].size == rig[3].size
    )
    for name in names:
        (tmp_path / "ns" / "images" / name).mkdir(parents=True)
        cv2.imwrite(
            str(tmp_path / "ns" / "images" / name / "000000.jpg"), np.zeros((240, 320, 3), np.uint8)
        )
    assert [c.size for c in load_rig(tmp_path / "ns")] == [(320, 240)] * 4
    (tmp_path / "half").mkdir()
    shutil.copy(tmp_path / "em" / "intri.yml", tmp_path / "half" / "intri.yml")
    with pytest.raises(CalibrationError, match="extri.yml is missing"):
        load_rig(tmp_path / "half" / "intri.yml")

    pan = tmp_path / "calibration_160422_ultimatum1.json"
    pan.write_text(panoptic_json(rig, ["00_00", "00_01", "00_02", "00_03"], extra=2))
    got = load_rig(pan)
    assert got.names == ["00_00", "00_01", "00_02", "00_03", "01_01", "01_02"]
    assert got.unit == "cm" and got.up == (0.0, -1.0, 0.0) and got[4].size == (640, 480)
    _assert_same_rig(Rig(cameras=got.cameras[:4]), rig, scale=100.0, atol=1e-8)
    assert load_rig(tmp_path).names == got.names  # the folder holding one calibration_*.json
    bad = json.loads(pan.read_text())
    bad["cameras"][2]["t"] = [1.0, 2.0]
    pan.write_text(json.dumps(bad))
    with pytest.raises(CalibrationError, match=r"camera '00_02': t must have 3 values"):
        load_rig(pan)


def test_import_easymocap_layout(scene, tmp_path, capsys):
    ds, gt = scene
    # EasyMocap's layout: intri.yml, extri.yml and images/<name>/ (here, names 1..5).
    root = tmp_path / "zju"
    names = [str(k + 1) for k in range(len(ds.rig))]
    easymocap_files(ds.rig, root, names, sizes=False)
    for name, cam in zip(names, ds.rig.names, strict=True):
        (root / "images").mkdir(exist_ok=True)
        (root / "images" / name).symlink_to(ds.root / "frames" / cam)
    out = tmp_path / "em"
    assert main(["import", str(root), str(root / "images"), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["calibration_format"] == "easymocap"
    assert [c["matched_by"] for c in report["cameras"]] == ["name"] * 5
    imported = open_dataset(out)
    assert imported.rig.names == names and imported.rig.up == (0.0, 0.0, 1.0)
    _assert_same_rig(imported.rig, ds.rig, atol=1e-8)
    score = reconstruct_score(out, tmp_path, gt, 1.0)
    assert score.precision > 0.85 and score.num_pred > 150, score


def test_import_panoptic_keeps_the_filmed_cameras(scene, tmp_path):
    ds, gt = scene
    names = [f"00_{k:02d}" for k in range(len(ds.rig))]
    calib = tmp_path / "calibration_seq.json"
    calib.write_text(panoptic_json(ds.rig, names, extra=3))
    # Panoptic names its HD frames hd_00_03 (videos hdVideos/hd_00_03.mp4): four of the five
    # HD cameras were filmed here, none of the VGA ones.
    frames = tmp_path / "hdImgs"
    frames.mkdir()
    for name, cam in list(zip(names, ds.rig.names, strict=True))[:4]:
        (frames / f"hd_{name}").symlink_to(ds.root / "frames" / cam)
    report = import_dataset(tmp_path / "pan", calibration=calib, frames=[str(frames)])
    assert report.calibration_format == "panoptic" and report.unit_note.startswith("cm")
    assert report.dataset.rig.names == names[:4]
    assert any("4 of the calibration's 8 cameras have no frames" in n for n in report.notes)
    assert "00_04, 01_01, 01_02, 01_03" in " ".join(report.notes)
    _assert_same_rig(report.dataset.rig, Rig(cameras=ds.rig.cameras[:4]), scale=100.0, atol=1e-8)
    # The reader says -y (Panoptic's world); the cameras' level horizons here say +z.
    assert load_rig(calib).up == (0.0, -1.0, 0.0)
    auto = import_dataset(tmp_path / "p2", calibration=calib, frames=[str(frames)])
    assert auto.dataset.rig.up == (0.0, 0.0, 1.0) and "level horizons" in auto.up_note
    # The format written in metres by another tool: the rig's size tells.
    metres = tmp_path / "m" / "calibration_m.json"
    metres.parent.mkdir()
    metres.write_text(panoptic_json(ds.rig, names, scale=1.0))
    assert load_rig(metres).unit == "m"
    report_m = import_dataset(tmp_path / "p4", calibration=metres, frames=[str(frames)])
    assert report_m.dataset.rig.unit == "m" and "guessed from the rig's size" in report_m.unit_note
    score = reconstruct_score(tmp_path / "pan", tmp_path, gt, 100.0)
    assert score.precision > 0.85 and score.num_pred > 100, score
    # Fewer than three filmed cameras, or frames that names do not tell: errors, as before.
    for extra in sorted(frames.iterdir())[2:]:
        extra.unlink()
    with pytest.raises(DataError, match=r"only 2 of the calibration's cameras .*00_00, 00_01"):
        import_dataset(tmp_path / "p3", calibration=calib, frames=[str(frames)])


def poses_bounds(rig: Rig) -> np.ndarray:
    """LLFF's ``poses_bounds.npy`` of ``rig``: camera-to-world with axes (down, right,
    backwards), the centre, (height, width, focal), then near / far bounds."""
    rows = []
    for cam in rig:
        c2w = cam.R.T  # columns: right, down, forward
        pose = np.column_stack(
            [c2w[:, 1], c2w[:, 0], -c2w[:, 2], cam.center, [cam.height, cam.width, cam.K[0, 0]]]
        )
        rows.append(np.concatenate([pose.ravel(), [0.5, 20.0]]))
    return np.asarray(rows)


def test_import_llff_poses_bounds(scene, tmp_path, capsys):
    ds, gt = scene
    # Neural 3D Video's layout: poses_bounds.npy next to one folder (here) or video per
    # camera, its rows in the sources' sorted order; the principal point is the centre.
    centred = Rig(
        cameras=tuple(
            dataclasses.replace(
                c,
                K=np.array([[c.K[0, 0], 0, c.width / 2], [0, c.K[1, 1], c.height / 2], [0, 0, 1]]),
            )
            for c in ds.rig
        )
    )
    root = tmp_path / "n3dv"
    root.mkdir()
    np.save(root / "poses_bounds.npy", poses_bounds(centred).astype(np.float32))
    for k, cam in enumerate(ds.rig.names):
        (root / f"cam{k:02d}").symlink_to(ds.root / "frames" / cam)
    got = load_rig(root)
    assert got.names == [f"cam{k:02d}" for k in range(5)]
    _assert_same_rig(got, centred, atol=2e-4)  # stored as float32
    out = tmp_path / "ll"
    assert (
        main(["import", str(root / "poses_bounds.npy"), str(root), "--out", str(out), "--json"])
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["calibration_format"] == "llff"
    assert [c["matched_by"] for c in report["cameras"]] == ["order"] * 5
    assert "SfM scales are arbitrary" in report["unit_note"]
    assert open_dataset(out).rig.up == (0.0, 0.0, 1.0)  # the cameras' horizons
    score = reconstruct_score(out, tmp_path, gt, 1.0)
    assert score.precision > 0.85 and score.num_pred > 150, score
    with pytest.raises(CalibrationError, match="5 cameras .rows. but 4"):
        import_dataset(
            tmp_path / "l4", calibration=root, frames=[str(root / f"cam0{k}") for k in range(4)]
        )
    np.save(root / "poses_bounds.npy", np.zeros((3, 12)))
    with pytest.raises(CalibrationError, match=r"\(N, 17\) array, got shape \(3, 12\)"):
        load_rig(root)


def test_relative_paths_are_kept_from_where_import_ran(scene, tmp_path, monkeypatch):
    # `edgerecon import calib videos/ --out data/session1`, as the README shows it: the
    # dataset is opened from its own folder later, wherever the reader runs.
    ds, _ = scene
    work = tmp_path / "work"
    work.mkdir()
    (work / "frames").symlink_to(ds.root / "frames")
    save_rig(work / "rig.json", ds.rig)
    monkeypatch.chdir(work)
    assert main(["import", "rig.json", "frames", "--out", "data/session1", "-q"]) == 0
    monkeypatch.chdir(tmp_path)
    with open_dataset(work / "data" / "session1").open_frames() as src:
        assert src.num_frames == ds.num_frames
        assert src.read(2).images[0] is not None


def test_sources_named_after_no_camera_are_left_out_and_said(scene, tmp_path, capsys):
    # Ego-Exo4D's frame_aligned_videos/ holds the worn camera's streams beside the GoPros'.
    ds, _ = scene
    folder = tmp_path / "videos"
    folder.mkdir()
    for cam in ds.rig.names:
        (folder / cam).symlink_to(ds.root / "frames" / cam)
    (folder / "aria01_214-1").symlink_to(ds.root / "frames" / ds.rig.names[0])
    save_rig(tmp_path / "rig.json", ds.rig)
    out = tmp_path / "ds"
    assert main(["import", str(tmp_path / "rig.json"), str(folder), "-o", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert [c["matched_by"] for c in report["cameras"]] == ["name"] * len(ds.rig)
    assert any("left out: aria01_214-1" in n for n in report["notes"]), report["notes"]


def test_import_of_a_calibration_a_camera_moved_since_says_what_calib_would_do(
    scene, tmp_path, capsys
):
    from tests.quality.test_calibration import turned

    ds, _ = scene
    calib = tmp_path / "rig.json"
    save_rig(calib, turned(ds.rig, 1, 2.0, (1.0, 0.0, 0.0)))
    out = tmp_path / "knocked"
    assert main(["import", str(calib), str(ds.root / "frames"), "--out", str(out)]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "cam1 moved since it was calibrated" in text and "calib --dataset" in text
    said = re.search(r"from these frames: cam1 re-aimed by ([0-9.]+) degrees", text)
    assert said is not None and float(said[1]) == pytest.approx(2.0, abs=0.1)
