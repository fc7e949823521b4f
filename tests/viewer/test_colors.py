import numpy as np
import pytest

from edgerecon.types import PointCloud
from edgerecon.viewer.colors import (
    available_colorings,
    colorize,
    decimate,
    point_spacing,
    unit_to_metres,
    version_colors,
)


def _cloud(labels, **attrs):
    n = len(labels)
    return PointCloud(
        points3D=np.arange(3 * n, dtype=float).reshape(n, 3),
        colors=np.tile([10, 20, 30], (n, 1)),
        labels=np.asarray(labels),
        attributes={k: np.asarray(v) for k, v in attrs.items()},
    )


def test_available_colorings_follow_the_cloud():
    bare = PointCloud(points3D=np.zeros((3, 3)))
    assert available_colorings(bare) == ["rgb"]
    merged = _cloud([0, 1, 2], bg_version=[1, 1, 1])
    assert available_colorings(merged) == ["rgb", "fg_bg", "object", "bg_version"]
    assert "inferred" in available_colorings(_cloud([0, 1], inferred=[0, 1]))
    # Every PLY edgerecon writes has the attribute; all measured: nothing to show.
    assert "inferred" not in available_colorings(_cloud([0, 1], inferred=[0, 0]))


def test_colorings_give_known_colours():
    c = _cloud([0, 1, 2, -1, 11], bg_version=[0, 3, 3, 3, 3], inferred=[0, 1, 0, 1, 0])
    rgb = colorize(c, "rgb")
    assert (rgb == [10, 20, 30]).all()
    fgbg = colorize(c, "fg_bg")
    assert (fgbg[1] == fgbg[2]).all() and not (fgbg[0] == fgbg[1]).all()
    assert not (fgbg[3] == fgbg[0]).all() and not (fgbg[3] == fgbg[1]).all()
    obj = colorize(c, "object")
    assert not (obj[1] == obj[2]).all()  # two objects, two colours
    assert (obj[1] == obj[4]).all()  # palette of 10: object 11 looks like object 1
    inf = colorize(c, "inferred")
    assert (inf[0] == inf[2]).all() and (inf[1] == inf[3]).all() and not (inf[0] == inf[1]).all()


def test_background_version_colours_run_from_oldest_to_newest():
    c = _cloud([0, 0, 0, 1], bg_version=[0, 2, 4, 4])
    col = colorize(c, "bg_version").astype(int)
    assert tuple(col[0]) == (68, 1, 84) and tuple(col[2]) == (253, 231, 37)
    assert col[1].tolist() == version_colors(np.array([2]), 4)[0].tolist()
    assert col[1].tolist() == [33, 145, 140]  # the middle stop
    assert tuple(col[3]) == (70, 70, 70)  # foreground: dark grey


def test_unsupported_coloring_falls_back_to_rgb_and_unknown_raises():
    c = _cloud([0, 1])
    assert (colorize(c, "inferred") == [10, 20, 30]).all()
    with pytest.raises(ValueError, match="coloring"):
        colorize(c, "depth")


def test_decimate_keeps_the_budget_and_favours_the_foreground():
    labels = np.r_[np.ones(1000, np.int32), np.zeros(9000, np.int32)]
    c = _cloud(labels)
    idx = decimate(c, 2000)
    assert len(idx) == 2000 and len(np.unique(idx)) == 2000
    assert (labels[idx] == 1).sum() == 1000  # all of the (small) foreground
    idx = decimate(c, 1000)
    assert (labels[idx] == 1).sum() == 500  # at least half the budget
    assert np.array_equal(decimate(c, 1000), idx)  # deterministic: no flicker
    assert len(decimate(c, 20000)) == 10000
    with pytest.raises(ValueError):
        decimate(c, 0)


def test_point_spacing_and_units():
    grid = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2) * 0.01
    pts = np.column_stack([grid, np.zeros(len(grid))])
    assert point_spacing(pts) == pytest.approx(0.01)
    assert point_spacing(pts[:1]) == 0.0
    assert unit_to_metres("mm") == 0.001 and unit_to_metres("m") == 1.0
