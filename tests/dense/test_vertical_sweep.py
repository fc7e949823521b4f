"""The "vertical" plane families of the coarse sweep: upright planes turned about the up
direction, and what they change on an upright surface that two cameras see at 45 degrees."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edgerecon.dense import DenseConfig, reconstruct_dense
from edgerecon.dense.depth import _families, _rays
from edgerecon.geometry import Camera, look_at
from edgerecon.pipeline import SplitPipelineConfig, foreground_dense_config
from edgerecon.views import View
from tests.conftest import ring_rig
from tests.dense.scene import Rect, noise_texture, render

UP = np.array([0.0, 0.0, 1.0])


def _camera(center: tuple[float, float, float], target: tuple[float, float, float]) -> Camera:
    R, t = look_at(center, target)
    K = np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]])
    return Camera(name="c", width=160, height=120, K=K, R=R, t=t)


def test_vertical_families_hold_the_up_direction_at_the_configured_turns():
    cam = _camera((3.0, 1.0, 1.6), (0.0, 0.0, 1.0))
    config = DenseConfig(sweep_families=("fronto", "vertical"), vertical_sweep_deg=(20.0, 40.0))
    fams = _families(cam, _rays(cam), UP, config)
    assert [f.name for f in fams] == [
        "fronto",
        "vertical+20",
        "vertical-20",
        "vertical+40",
        "vertical-40",
    ]
    up_cam = cam.R @ UP
    # The image plane's normal with its up component removed: the turn's zero.
    front = np.array([0.0, 0.0, 1.0]) - up_cam[2] * up_cam
    front /= np.linalg.norm(front)
    for fam, deg in zip(fams[1:], (20, 20, 40, 40), strict=True):
        n = fam.normal
        assert abs(np.linalg.norm(n) - 1.0) < 1e-9
        assert abs(n @ up_cam) < 1e-9  # the plane holds the up direction
        assert math.degrees(math.acos(np.clip(n @ front, -1, 1))) == pytest.approx(deg)
        # Planes in front of the camera: n . ray > 0 wherever the family may explain a pixel.
        assert fam.usable.mean() > 0.9
        assert (fam.nray[fam.usable] > 0).all()
    # The two turns of one angle are mirror images about the image plane's normal.
    assert fams[1].normal @ front == pytest.approx(fams[2].normal @ front)
    assert not np.allclose(fams[1].normal, fams[2].normal)


def test_no_vertical_planes_without_an_up_direction():
    config = DenseConfig(sweep_families=("fronto", "vertical"))
    cam = _camera((3.0, 1.0, 1.6), (0.0, 0.0, 1.0))
    assert [f.name for f in _families(cam, _rays(cam), None, config)] == ["fronto"]


def test_a_camera_looking_down_sees_upright_planes_edge_on_in_most_pixels():
    config = DenseConfig(sweep_families=("vertical",))
    down = _camera((0.0, 0.0, 4.0), (0.0, 0.3, 0.0))
    for fam in _families(down, _rays(down), UP, config):
        # Rays within 10 degrees of the planes get no hypotheses from them.
        assert fam.usable.mean() < 0.5, fam.name


@pytest.mark.parametrize("value", [(), (0.0,), (80.0,), (20.0, -5.0)])
def test_vertical_sweep_deg_validation(value):
    with pytest.raises(ValueError, match="vertical_sweep_deg"):
        DenseConfig(vertical_sweep_deg=value)


def test_the_foreground_sweeps_vertical_planes_unless_told_not_to():
    base = DenseConfig()
    assert base.sweep_families == ("fronto", "ground")
    # Upright planes in the place of floor-parallel ones (the foreground is never floor).
    on = foreground_dense_config(base, SplitPipelineConfig())
    assert on.sweep_families == ("fronto", "vertical")
    off = foreground_dense_config(base, SplitPipelineConfig(fg_vertical_sweep=False))
    assert off.sweep_families == base.sweep_families
    # Already there: not twice; a ground-only configuration keeps a fronto family.
    with_v = DenseConfig(sweep_families=("vertical", "fronto"))
    assert foreground_dense_config(with_v).sweep_families == ("fronto", "vertical")
    ground = DenseConfig(sweep_families=("ground",))
    assert foreground_dense_config(ground).sweep_families == ("fronto", "vertical")


def test_an_upright_wall_seen_at_45_degrees_is_measured_more_precisely():
    # Cameras 0 and 2 stand 90 degrees apart and see the wall at 45 degrees; camera 1 faces
    # it. A coarse, low-frequency texture: fronto-parallel windows of cameras 0 and 2 are
    # sheared across the sweep, the wall's own orientation is not.
    rig = ring_rig(8, radius=3.0, height=1.2, width=320, height_px=240, focal_px=400.0)
    n = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0])
    side = np.array([-n[1], n[0], 0.0])
    wall = Rect(
        -0.7 * side + np.array([0.0, 0.0, 0.3]),
        1.4 * side,
        np.array([0.0, 0.0, 1.4]),
        noise_texture(512, 5, (24, 64)),
    )
    ids = (0, 1, 2)
    views, depths = [], {}
    for i in ids:
        image, depth = render(rig[i], [wall])
        views.append(View(camera_id=i, camera=rig[i], image=image, mask=depth > 0))
        depths[i] = depth
    # Bounds as a visual hull would give them (+-8 % around the surface).
    ranges = {
        i: (
            np.where(d > 0, 0.92 * d, 0).astype(np.float32),
            np.where(d > 0, 1.08 * d, 0).astype(np.float32),
        )
        for i, d in depths.items()
    }

    def precise_share(families: tuple[str, ...]) -> dict[int, float]:
        config = DenseConfig(resolution_level=0, num_threads=1, sweep_families=families)
        res = reconstruct_dense(views, config, up=(0, 0, 1), depth_ranges=ranges)
        out = {}
        for i in ids:
            d, gt = res.depth_maps[i], depths[i]
            ok = (d > 0) & (gt > 0)
            assert ok.sum() > 0.8 * (gt > 0).sum(), i
            out[i] = float(np.mean(np.abs(d[ok] - gt[ok]) / gt[ok] < 0.003))
        return out

    fronto = precise_share(("fronto", "ground"))
    vertical = precise_share(("fronto", "ground", "vertical"))
    for i in (0, 2):  # the slanted views
        assert vertical[i] >= fronto[i] + 0.02, (i, fronto, vertical)
        assert vertical[i] > 0.95, (i, vertical)
    assert vertical[1] >= fronto[1] - 0.01  # the facing view loses nothing
