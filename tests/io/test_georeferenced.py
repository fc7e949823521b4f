"""A rig far from its world's origin (UTM-like coordinates): the pipeline works in a local
frame (``Rig.localised``) and every output is in world coordinates as float64, so a
georeferenced rig reconstructs as precisely as the same rig near zero."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.geometry import Rig
from edgerecon.io import open_dataset
from edgerecon.io.calibration import save_rig
from edgerecon.io.colmap import read_colmap_model
from edgerecon.io.ply import read_ply_meta, read_ply_with_meta, write_ply
from edgerecon.quality import evaluate_clouds
from edgerecon.types import PointCloud
from tests.conftest import ring_rig

#: A UTM-like world: float32 spacing is 0.25-0.5 m there.
OFFSET = np.array([512345.0, 4123456.0, 250.0])


def _moved(rig: Rig, offset: np.ndarray) -> Rig:
    """``rig`` in a world whose coordinates are the old ones plus ``offset``."""
    cams = tuple(dataclasses.replace(c, t=c.t - c.R @ offset) for c in rig)
    return dataclasses.replace(rig, cameras=cams)


def test_a_far_rig_works_in_a_local_frame():
    near = ring_rig(4)
    assert near.localised() is near  # near its origin: unchanged
    far = _moved(near, OFFSET)
    local = far.localised()
    assert local.localised() is local
    origin = np.asarray(local.origin)
    assert np.all(np.abs(origin - OFFSET) < 10)  # the cameras' mean, rounded
    np.testing.assert_allclose(local.centers + origin, far.centers, atol=1e-8)
    assert float(np.abs(local.centers).max()) < 20
    # The same pixels for the same world points.
    world = OFFSET + np.random.default_rng(0).uniform(-1, 1, (50, 3))
    for a, b in zip(far, local, strict=True):
        np.testing.assert_allclose(a.project(world)[0], b.project(world - origin)[0], atol=1e-5)
    back = Rig.from_dict(json.loads(json.dumps(local.to_dict())))
    assert back.origin == local.origin
    for a, b in zip(back, local, strict=True):
        np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_allclose(local.in_world().centers, far.centers, atol=1e-8)
    assert "origin" not in near.to_dict()


def test_ply_with_an_origin_is_world_float64(tmp_path):
    pts = np.random.default_rng(1).uniform(-2, 2, (100, 3))
    cloud = PointCloud(points3D=pts)
    path = write_ply(tmp_path / "c.ply", cloud, unit="m", origin=tuple(OFFSET))
    meta = read_ply_meta(path)
    assert meta.origin == tuple(OFFSET) and meta.vertex_properties[:3] == ("x", "y", "z")
    assert b"property double x" in path.read_bytes()[:400]
    raw = np.frombuffer(path.read_bytes().split(b"end_header\n", 1)[1], dtype="<f8", count=3)
    np.testing.assert_allclose(raw, pts[0] + OFFSET, rtol=0, atol=1e-9)  # world, as stored
    got, meta = read_ply_with_meta(path)
    np.testing.assert_allclose(got.points3D, pts, rtol=0, atol=1e-9)  # local, as read
    plain = write_ply(tmp_path / "p.ply", cloud)
    assert read_ply_meta(plain).origin is None and b"property float x" in plain.read_bytes()[:300]


@pytest.fixture(scope="module")
def far_dataset(tiny_dataset, tmp_path_factory):
    """The tiny scene with its rig moved into a UTM-like world (same frames)."""
    root = tmp_path_factory.mktemp("far") / "scene"
    root.mkdir()
    ds = open_dataset(tiny_dataset)
    save_rig(root / "rig.json", _moved(ds.rig, OFFSET))
    desc = json.loads((tiny_dataset / "dataset.json").read_text())
    desc.pop("ground_truth", None)
    for section in ("frames", "background"):
        if section in desc:
            desc[section]["cameras"] = {
                n: str(tiny_dataset / p) for n, p in desc[section]["cameras"].items()
            }
    (root / "dataset.json").write_text(json.dumps(desc))
    return root


def test_a_georeferenced_rig_reconstructs_as_precisely(tiny_dataset, far_dataset, tmp_path, capsys):
    from edgerecon.config import ReconstructionConfig
    from edgerecon.pipeline import reconstruct

    far_rig = open_dataset(far_dataset).rig
    assert any(far_rig.origin)
    out = tmp_path / "far"
    assert (
        main(["reconstruct", "--dataset", str(far_dataset), "--time", "3", "--out", str(out)]) == 0
    )
    far, meta = read_ply_with_meta(out / "dense.ply")
    assert meta.origin == far_rig.origin and len(far) > 1000
    assert b"property double x" in (out / "dense.ply").read_bytes()[:400]
    # The near rig in the frame the far one works in (the origin is the cameras' rounded
    # mean, not OFFSET): the same arithmetic, the same cloud. (Without the local frame the
    # far rig's depth maps and fusion ran at 4e6 in float32: F at 1 cm 0.05 on hd4.)
    ds = open_dataset(tiny_dataset)
    delta = np.asarray(far_rig.origin) - OFFSET
    with ds.open_frames() as src:
        frames = src.read(3)
    near = reconstruct(frames, _moved(ds.rig, -delta), ReconstructionConfig()).dense.cloud
    # (Poses moved in float64 differ in the last bits: a few voxel ties fall the other way.)
    [score] = evaluate_clouds(far.points3D, near.points3D, 1e-3)
    assert score.fscore > 0.97 and score.accuracy_median < 1e-8, score
    # `evaluate` against the near cloud in world coordinates, as another tool would write it
    # (float64, no origin comment): PRED is moved into REF's frame.
    ref = tmp_path / "ref.ply"
    world = near.points3D + np.asarray(far_rig.origin)
    write_ply(ref, dataclasses.replace(near, points3D=world), double=True)
    capsys.readouterr()
    assert main(["evaluate", str(out / "dense.ply"), str(ref), "-d", "0.001", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["scores"][0]["fscore"] > 0.97
    # The COLMAP export: poses and points in world coordinates.
    ws = tmp_path / "ws"
    args = ["export", str(out), "--dataset", str(far_dataset), "--out", str(ws)]
    assert main([*args, "--no-images"]) == 0
    model = read_colmap_model(ws / "sparse")
    centres = [img.center for img in model.images.values()]
    want = {c.name: c.center for c in _moved(open_dataset(tiny_dataset).rig, OFFSET)}
    for img, centre in zip(model.images.values(), centres, strict=True):
        np.testing.assert_allclose(centre, want[img.name.rsplit(".", 1)[0]], atol=1e-6)
    xyz = model.points3D.xyz
    assert len(xyz) and float(np.abs(xyz - OFFSET).max()) < 50


def test_a_georeferenced_run_writes_world_clouds_and_reads_them_back(far_dataset, tmp_path):
    from edgerecon.viewer.rundir import RunFolder

    out = tmp_path / "run"
    args = ["run", "--dataset", str(far_dataset), "--out", str(out), "--deadline", "20"]
    assert main([*args, "--frames", "2:4", "--fixed", "0.6"]) == 0
    folder = RunFolder(out)
    rig = folder.rig()
    assert rig is not None and any(rig.origin)
    tasks = folder.poll()
    assert [m.status for m in tasks] == ["ok", "ok"]
    cloud = folder.cloud(3)
    assert cloud is not None and len(cloud) > 100
    assert float(np.abs(cloud.points3D).max()) < 50  # local, as the rig
    stored, meta = read_ply_with_meta(out / "tasks" / "000003" / "fg.ply")
    assert meta.origin == rig.origin
    assert float(np.abs(stored.points3D + np.asarray(meta.origin) - OFFSET).max()) < 50


def test_a_coordinate_reference_system_reaches_the_las_files(far_dataset, tmp_path, capsys):
    """`import --crs` records the rig's CRS; a run's clouds and their LAS / PLY exports carry
    it (QGIS places them), `export --crs` overrides it, bad ones are refused."""
    import laspy

    from edgerecon.io.las import read_las

    geo = tmp_path / "geo"
    frames = json.loads((far_dataset / "dataset.json").read_text())["frames"]["cameras"]
    sources = [f"{n}={p}" for n, p in frames.items()]
    calib = far_dataset / "rig.json"
    assert main(["import", str(calib), *sources, "-o", str(geo), "--crs", "EPSG:32633"]) == 0
    assert "UTM zone 33N" in capsys.readouterr().out
    assert json.loads((geo / "rig.json").read_text())["crs"] == "EPSG:32633"
    assert open_dataset(geo).rig.crs == "EPSG:32633"
    assert main(["info", "--dataset", str(geo)]) == 0
    assert "coordinate reference system: WGS 84 / UTM zone 33N" in capsys.readouterr().out
    run = tmp_path / "run"
    args = ["run", "--dataset", str(geo), "--out", str(run), "--deadline", "20", "-q"]
    assert main([*args, "--frames", "2:4", "--fixed", "0.6"]) == 0
    assert read_ply_meta(run / "tasks" / "000003" / "fg.ply").crs == "EPSG:32633"
    capsys.readouterr()
    assert main(["export", str(run), "--to", "laz", "-o", str(tmp_path / "seq"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["crs"] == "WGS 84 / UTM zone 33N" and len(report["clouds"]) == 2
    path = report["clouds"][1]["laz"]
    assert laspy.read(path).header.parse_crs().to_epsg() == 32633
    cloud, info = read_las(path)
    assert info["crs"] == "WGS 84 / UTM zone 33N"
    assert float(np.abs(cloud.points3D - OFFSET).max()) < 50  # metres in the UTM zone
    # A PLY keeps it as a comment; a LAS made from that PLY alone (no dataset) has it too.
    ply = tmp_path / "t3.ply"
    assert main(["export", str(run), "--to", "ply", "-t", "3", "-o", str(tmp_path / "p")]) == 0
    (tmp_path / "p" / "000003.ply").rename(ply)
    assert read_ply_meta(ply).crs == "EPSG:32633"
    assert main(["export", str(ply), "--to", "las", "-o", str(tmp_path / "t3.las")]) == 0
    assert read_las(tmp_path / "t3.las")[1]["crs"] == "WGS 84 / UTM zone 33N"
    # --crs overrides the rig's (the same zone in ETRS89); bad ones: the reason, exit 2.
    over = tmp_path / "over.las"
    assert main(["export", str(ply), "--to", "las", "-o", str(over), "--crs", "25833"]) == 0
    assert laspy.read(over).header.parse_crs().to_epsg() == 25833
    capsys.readouterr()
    for crs, why in (
        ("EPSG:4326", "geographic"),
        ("EPSG:2263", "US survey foot"),
        ("no such crs", "not a coordinate reference system"),
    ):
        assert main(["export", str(ply), "--to", "las", "-o", str(over), "--crs", crs]) == 2
        assert why in capsys.readouterr().err
        assert main(["import", str(calib), *sources, "-o", str(tmp_path / "x"), "--crs", crs]) == 2
        assert why in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert main(["export", str(run / "tasks" / "000003"), "--to", "colmap", "--crs", "25833",
                 "-o", str(tmp_path / "c")]) == 2  # fmt: skip
    assert "--crs is for ply / las / laz" in capsys.readouterr().err


def test_a_turned_world_leaves_the_rig_crs_out(tmp_path, capsys):
    """--z-up-metres turns a rig whose up is not +Z: its CRS no longer applies."""
    from edgerecon.io.las import read_las

    cloud = PointCloud(points3D=np.random.default_rng(0).uniform(-1, 1, (50, 3)))
    src = write_ply(tmp_path / "c.ply", cloud, unit="m", up=(0, -1, 0), crs="EPSG:32633")
    out = tmp_path / "c.las"
    assert main(["export", str(src), "--to", "las", "-o", str(out), "--z-up-metres"]) == 0
    assert "reference system left out" in capsys.readouterr().out
    assert read_las(out)[1]["crs"] is None
    args = ["export", str(src), "--to", "las", "-o", str(out), "--z-up-metres"]
    assert main([*args, "--crs", "EPSG:32633"]) == 2
    assert "turns this rig's world frame" in capsys.readouterr().err
    up = write_ply(tmp_path / "u.ply", cloud, unit="mm", up=(0, 0, 1), crs="EPSG:32633")
    assert main(["export", str(up), "--to", "las", "-o", str(out), "--z-up-metres"]) == 0
    assert read_las(out)[1]["crs"] == "WGS 84 / UTM zone 33N"  # millimetres to metres: kept


def test_evaluate_against_the_truth_in_world_coordinates(tiny_dataset, tmp_path, capsys):
    """A PLY with an origin is scored against a synthetic scene's truth in world coordinates."""
    from edgerecon.synth import GroundTruth

    ref = GroundTruth.open(tiny_dataset).reference_cloud(3, "all", min_views=1)
    origin = (1000.0, 2000.0, 0.0)
    local = dataclasses.replace(ref, points3D=ref.points3D - np.asarray(origin))
    pred = write_ply(tmp_path / "pred.ply", local, origin=origin)
    args = ["evaluate", str(pred), "--gt", str(tiny_dataset), "--time", "3", "--part", "all"]
    assert main([*args, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["scores"][0]["fscore"] > 0.99
