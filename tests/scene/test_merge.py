"""Merging the foreground with the background cloud."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from edgerecon.io.ply import read_ply
from edgerecon.scene.hull import HullConfig, visual_hull
from edgerecon.scene.merge import BG_VERSION, MergeConfig, merge_clouds, split_merged, write_merged
from edgerecon.types import PointCloud
from tests.scene._scenes import box_silhouette, box_surface_points, ring_with_top


def _clouds() -> tuple[PointCloud, PointCloud]:
    rng = np.random.default_rng(0)
    fg = PointCloud(
        points3D=rng.uniform([-0.2, -0.2, 0.5], [0.2, 0.2, 1.5], (300, 3)),
        colors=np.full((300, 3), 200, np.uint8),
        labels=np.r_[np.full(200, 1), np.full(100, 2)].astype(np.int32),
    )
    floor = np.column_stack([rng.uniform(-2, 2, (1000, 2)), np.zeros(1000)])
    ghost = rng.uniform([-0.1, -0.1, 0.8], [0.1, 0.1, 1.2], (50, 3))  # an old actor's points
    bg = PointCloud(
        points3D=np.vstack([floor, ghost]),
        colors=np.full((1050, 3), 50, np.uint8),
        attributes={BG_VERSION: np.r_[np.full(1000, 3), np.full(50, 2)].astype(np.int32)},
    )
    return fg, bg


def test_merge_labels_versions_and_override() -> None:
    fg, bg = _clouds()
    # FG points are ~8 cm apart: a 12 cm radius covers the space they occupy.
    merged = merge_clouds(fg, bg, bg_version=3, config=MergeConfig(clear_radius=0.12))
    assert merged.labels is not None
    fg_part, bg_part = split_merged(merged)
    assert len(fg_part) == 300
    np.testing.assert_array_equal(np.unique(fg_part.labels), [1, 2])
    np.testing.assert_array_equal(fg_part.attributes[BG_VERSION], 3)
    # The ghost (inside the foreground's neighbourhood) is gone, the floor stays.
    assert not (bg_part.points3D[:, 2] > 0.5).any()
    assert len(bg_part) == 1000
    np.testing.assert_array_equal(bg_part.labels, 0)
    np.testing.assert_array_equal(bg_part.attributes[BG_VERSION], 3)


def test_merge_without_radius_keeps_everything_and_defaults_versions() -> None:
    fg, bg = _clouds()
    bg = PointCloud(points3D=bg.points3D, colors=bg.colors)  # no version attribute
    unlabelled = PointCloud(points3D=fg.points3D)
    merged = merge_clouds(unlabelled, bg, bg_version=7)
    assert len(merged) == 1350
    np.testing.assert_array_equal(merged.attributes[BG_VERSION], 7)
    np.testing.assert_array_equal(merged.labels[:300], 1)


def test_merge_removes_background_inside_the_hull() -> None:
    rig = ring_with_top(6)
    lo, hi = np.array([-0.3, -0.3, 0.5]), np.array([0.3, 0.3, 1.5])
    hull = visual_hull(
        rig.cameras, [box_silhouette(c, lo, hi) for c in rig], HullConfig(voxel_size=0.04)
    )
    fg = PointCloud(points3D=box_surface_points(lo, hi, 5), labels=np.ones(150, np.int32))
    inside = np.array([[0.0, 0.0, 1.0], [0.1, -0.1, 0.7]])
    outside = np.array([[1.5, 0.0, 1.0]])
    bg = PointCloud(points3D=np.vstack([inside, outside]))
    merged = merge_clouds(fg, bg, bg_version=1, hull=hull)
    _, bg_part = split_merged(merged)
    np.testing.assert_allclose(bg_part.points3D, outside)


def test_merge_overrides_exactly_the_points_near_the_foreground_or_in_the_hull() -> None:
    """Only points in the foreground's or the hull's box are searched: the result is that of
    testing every background point."""
    rig = ring_with_top(6)
    lo, hi = np.array([-0.3, -0.3, 0.5]), np.array([0.3, 0.3, 1.5])
    hull = visual_hull(
        rig.cameras, [box_silhouette(c, lo, hi) for c in rig], HullConfig(voxel_size=0.04)
    )
    rng = np.random.default_rng(3)
    fg = PointCloud(points3D=rng.uniform([0.2, 0.2, 0.4], [0.8, 0.5, 1.0], (400, 3)))
    bg = PointCloud(points3D=rng.uniform(-1.0, 1.6, (20000, 3)))
    radius = 0.05
    merged = merge_clouds(fg, bg, bg_version=1, config=MergeConfig(clear_radius=radius), hull=hull)
    d = np.linalg.norm(bg.points3D[:, None, :] - fg.points3D[None, :, :], axis=2).min(axis=1)
    expected = (d >= radius) & ~hull.contains(bg.points3D)
    assert 0.5 < expected.mean() < 0.999
    np.testing.assert_array_equal(split_merged(merged)[1].points3D, bg.points3D[expected])


def test_merge_scene_scale_sets_radius() -> None:
    fg, bg = _clouds()
    merged = merge_clouds(fg, bg, bg_version=1, scene_scale=5.0)  # radius 0.05
    assert len(split_merged(merged)[1]) < 1050


def test_write_merged(tmp_path: Path) -> None:
    fg, bg = _clouds()
    merged = merge_clouds(fg, bg, bg_version=4, config=MergeConfig(clear_radius=0.05))
    paths = write_merged(tmp_path / "out", merged)
    assert set(paths) == {"merged", "fg", "bg"}
    back = read_ply(paths["merged"])
    assert len(back) == len(merged)
    np.testing.assert_array_equal(back.labels, merged.labels)
    np.testing.assert_array_equal(back.attributes[BG_VERSION], merged.attributes[BG_VERSION])
    assert len(read_ply(paths["fg"])) == 300
    assert len(read_ply(paths["bg"])) == len(merged) - 300


def test_merge_keeps_which_points_are_inferred(tmp_path: Path) -> None:
    fg, bg = _clouds()
    # The background's completed floor (every other floor point) is inferred; the
    # foreground carries no flag (all measured).
    flag = np.r_[np.arange(1000) % 2 == 0, np.zeros(50, bool)]
    merged = merge_clouds(fg, bg.with_inferred(flag), bg_version=4)
    assert merged.num_inferred == 500
    assert not merged.inferred[merged.labels >= 1].any()
    paths = write_merged(tmp_path / "out", merged)
    np.testing.assert_array_equal(read_ply(paths["merged"]).inferred, merged.inferred)
    assert read_ply(paths["bg"]).num_inferred == 500 and read_ply(paths["fg"]).num_inferred == 0
