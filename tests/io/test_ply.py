import numpy as np
import pytest

from edgerecon.io.ply import read_ply, write_ply
from edgerecon.types import DataError, PointCloud


def test_ply_roundtrip_all_attributes(tmp_path):
    rng = np.random.default_rng(0)
    n = 57
    cloud = PointCloud(
        points3D=rng.normal(size=(n, 3)),
        colors=rng.integers(0, 256, (n, 3)),
        normals=rng.normal(size=(n, 3)),
        labels=rng.integers(-1, 4, n),
        confidence=rng.random(n),
        attributes={
            "bg_version": rng.integers(0, 9, n).astype(np.int32),
            "num_views": rng.integers(2, 7, n).astype(np.uint8),
        },
    )
    path = write_ply(tmp_path / "c.ply", cloud, double=True)
    back = read_ply(path)
    np.testing.assert_array_equal(back.points3D, cloud.points3D)
    np.testing.assert_array_equal(back.colors, cloud.colors)
    np.testing.assert_array_equal(back.normals, cloud.normals)
    np.testing.assert_array_equal(back.labels, cloud.labels)
    np.testing.assert_array_equal(back.confidence, cloud.confidence)
    np.testing.assert_array_equal(back.attributes["bg_version"], cloud.attributes["bg_version"])
    np.testing.assert_array_equal(back.attributes["num_views"], cloud.attributes["num_views"])
    assert not list(tmp_path.glob(".*tmp"))  # atomic write leaves no temporary file


def test_ply_float32_and_empty(tmp_path):
    write_ply(tmp_path / "e.ply", PointCloud.empty())
    assert len(read_ply(tmp_path / "e.ply")) == 0
    pts = np.array([[1.5, 2.25, -3.0]])
    write_ply(tmp_path / "f.ply", PointCloud(points3D=pts))
    np.testing.assert_array_equal(read_ply(tmp_path / "f.ply").points3D, pts)


def test_ascii_ply_and_errors(tmp_path):
    p = tmp_path / "a.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        "end_header\n0 0 0 255 0 0\n1 2 3 0 255 0\n"
    )
    c = read_ply(p)
    np.testing.assert_array_equal(c.points3D[1], [1, 2, 3])
    np.testing.assert_array_equal(c.colors[0], [255, 0, 0])
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    with pytest.raises(DataError, match="not a PLY"):
        read_ply(tmp_path / "bad.ply")
    with pytest.raises(DataError, match="not found"):
        read_ply(tmp_path / "missing.ply")
    trunc = tmp_path / "t.ply"
    write_ply(trunc, PointCloud(points3D=np.ones((10, 3))))
    trunc.write_bytes(trunc.read_bytes()[:-5])
    with pytest.raises(DataError, match="truncated"):
        read_ply(trunc)
