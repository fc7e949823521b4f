"""LAS 1.4 / LAZ export (``io.las``, ``export --to las|laz``): coordinates to the millimetre
in metres (a georeferenced origin included), colours, foreground class and labels, the
inferred points' synthetic flag."""

from __future__ import annotations

import json

import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.io.las import FOREGROUND_CLASS, read_las, write_las
from edgerecon.io.ply import read_ply
from edgerecon.types import DataError, PointCloud


def _cloud(n: int = 500, seed: int = 0) -> PointCloud:
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 4, n).astype(np.int32)
    labels[0] = 300  # beyond user_data's byte
    return PointCloud(
        points3D=rng.uniform(-2000, 2000, (n, 3)),  # millimetres
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        labels=labels,
        attributes={"inferred": (rng.random(n) < 0.2).astype(np.uint8)},
    )


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_round_trip_in_metres_about_a_georeferenced_origin(tmp_path, suffix):
    cloud = _cloud()
    origin = (512_345_678.9, 5_432_109_876.5, 123_456.7)  # UTM-like, in millimetres
    path = write_las(tmp_path / f"c{suffix}", cloud, unit="mm", origin=origin)
    assert path.read_bytes()[:4] == b"LASF"
    got, info = read_las(path)
    assert info["point_format"] == 7 and info["version"] == "1.4"
    assert info["generating_software"] == "edgerecon"
    expected = (cloud.points3D + np.asarray(origin)) / 1000.0
    assert np.abs(got.points3D - expected).max() <= 0.0005 + 1e-9  # a millimetre's quantum
    np.testing.assert_array_equal(got.colors, cloud.colors)
    np.testing.assert_array_equal(got.labels, np.clip(cloud.labels, 0, 255))
    np.testing.assert_array_equal(got.inferred, cloud.inferred)
    fg = np.asarray(info["classification"]) == FOREGROUND_CLASS
    np.testing.assert_array_equal(fg, cloud.labels > 0)
    assert set(np.unique(np.asarray(info["classification"])[~fg])) == {1}


def test_laz_is_compressed_and_bad_files_are_refused(tmp_path):
    cloud = _cloud(5000)
    las = write_las(tmp_path / "c.las", cloud, unit="m")
    laz = write_las(tmp_path / "c.laz", cloud, unit="m")
    assert laz.stat().st_size < 0.8 * las.stat().st_size
    (tmp_path / "bad.las").write_bytes(b"not a las file")
    with pytest.raises(DataError, match="not a readable LAS"):
        read_las(tmp_path / "bad.las")
    with pytest.raises(DataError, match="unit 'furlong'"):
        write_las(tmp_path / "x.las", cloud, unit="furlong")


def test_export_to_las_from_a_reconstruction(tiny_dataset, tmp_path, capsys):
    rec = tmp_path / "rec"
    args = ["reconstruct", "--dataset", str(tiny_dataset), "-t", "3", "-r", "0.5", "-o", str(rec)]
    assert main(args) == 0
    capsys.readouterr()
    cmd = ["export", str(rec), "--to", "laz", "-o", str(tmp_path / "out"), "--max-range", "none"]
    assert main([*cmd, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["laz"].endswith("dense.laz") and report["unit"] == "m"
    dense = read_ply(rec / "dense.ply")
    got, _ = read_las(report["laz"])
    assert len(got) == len(dense) == report["points"]
    assert np.abs(got.points3D - dense.points3D).max() <= 0.0005 + 1e-6


def test_evaluate_against_a_laser_scan_in_metres(tmp_path, capsys):
    """A reference scan as LAS (metres, world coordinates) against a rig's PLY in
    millimetres about an origin: converted, scored in the PLY's unit."""
    from edgerecon.io.ply import write_ply

    cloud = _cloud(2000)
    origin = (1000.0, -2000.0, 500.0)
    write_ply(tmp_path / "pred.ply", cloud, unit="mm", origin=origin)
    write_las(tmp_path / "scan.laz", cloud, unit="mm", origin=origin)
    args = ["evaluate", str(tmp_path / "pred.ply"), str(tmp_path / "scan.laz"), "-d", "2", "--json"]
    assert main(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["unit"] == "mm" and report["ref_converted_from"] == "m"
    assert report["scores"][0]["fscore"] == 1.0
    assert report["scores"][0]["accuracy_mean"] < 0.6  # the LAS millimetre's rounding


def test_evaluate_reprojects_a_scan_in_another_crs(tmp_path, capsys):
    """A scan in the neighbouring UTM zone (its LAS record says so) against a rig's PLY in
    UTM 33N (its comment): REF is moved into PRED's CRS before scoring."""
    import pyproj

    from edgerecon.io.ply import write_ply

    rng = np.random.default_rng(1)
    local = PointCloud(points3D=rng.uniform(-5, 5, (3000, 3)))
    origin = (512_345.0, 4_123_456.0, 250.0)
    write_ply(tmp_path / "pred.ply", local, unit="m", origin=origin, crs="EPSG:32633")
    world = local.points3D + np.asarray(origin)
    move = pyproj.Transformer.from_crs(32633, 32632, always_xy=True)
    x, y, z = move.transform(world[:, 0], world[:, 1], world[:, 2])
    scan = PointCloud(points3D=np.stack([x, y, z], 1))
    assert np.abs(scan.points3D - world).max() > 1e5  # another zone: far apart as numbers
    write_las(tmp_path / "scan.laz", scan, unit="m", crs="EPSG:32632")
    args = ["evaluate", str(tmp_path / "pred.ply"), str(tmp_path / "scan.laz"), "-d", "0.01"]
    assert main([*args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ref_reprojected"] == "WGS 84 / UTM zone 32N -> WGS 84 / UTM zone 33N"
    assert report["scores"][0]["fscore"] == 1.0
    assert report["scores"][0]["accuracy_mean"] < 0.001  # LAS's millimetre
    assert main(args) == 0
    assert "REF reprojected: WGS 84 / UTM zone 32N -> WGS 84 / UTM zone 33N" in (
        capsys.readouterr().out
    )
