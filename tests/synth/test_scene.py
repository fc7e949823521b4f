"""Scene configs, presets, rigs and deterministic building."""

import dataclasses

import numpy as np
import pytest

from edgerecon.synth import SceneConfig, build_scene, make_rig, preset_config
from edgerecon.synth.scene import PRESETS, RealismConfig, RigSpec, _TextureBank


def test_presets_match_their_description():
    demo = preset_config("demo")
    assert (demo.rig.num_cameras, demo.rig.width, demo.rig.height) == (5, 640, 480)
    assert (demo.num_frames, demo.num_actors) == (40, 2)
    arc = preset_config("arc7")
    assert (arc.rig.num_cameras, arc.rig.width, arc.rig.height) == (7, 1920, 1080)
    assert arc.rig.focal_px == pytest.approx(1720, abs=5)
    assert any(arc.rig.distortion)
    assert set(PRESETS) >= {"ring", "arc7", "demo"}


def test_arc7_rig_geometry():
    cfg = preset_config("arc7")
    rig = make_rig(cfg.rig, seed=0)
    target = np.array(cfg.rig.target)
    dirs = rig.centers - target
    dirs[:, 2] = 0
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    angles = np.degrees(np.arccos(np.clip(np.sum(dirs[1:] * dirs[:-1], axis=1), -1, 1)))
    np.testing.assert_allclose(angles, 15.0, atol=3.0)
    for cam in rig:
        # Every camera looks at (near) the target: it projects near the image centre.
        uv, depth = cam.project(target[None])
        assert depth[0] > 2.5
        assert abs(uv[0, 0] - cam.width / 2) < 0.15 * cam.width
        assert abs(uv[0, 1] - cam.height / 2) < 0.15 * cam.height


def test_resolution_override_keeps_field_of_view():
    small = preset_config("arc7", width=480, height=270)
    assert small.rig.focal_px == pytest.approx(1720 / 4)
    assert small.rig.principal_offset_px[0] == pytest.approx(-21.7 / 4)


def test_build_is_deterministic_and_seed_dependent():
    cfg = preset_config("demo", width=160, height=120, num_frames=10)
    a, b = build_scene(cfg), build_scene(cfg)
    c = build_scene(dataclasses.replace(cfg, seed=1))
    assert a.rig.to_dict() == b.rig.to_dict()
    assert a.describe() == b.describe()
    for ta, tb in zip(a.textures, b.textures, strict=True):
        assert np.array_equal(ta.levels[0], tb.levels[0])
    pa = [a.actors[0].position(t) for t in range(10)]
    pb = [b.actors[0].position(t) for t in range(10)]
    pc = [c.actors[0].position(t) for t in range(10)]
    assert np.array_equal(pa, pb)
    assert not np.allclose(pa, pc)
    assert a.describe()["furniture"] != c.describe()["furniture"]


def test_scene_layout_is_sane():
    scene = build_scene(preset_config("ring", num_frames=60))
    assert len(scene.rig) == 8
    half = scene.room.half_x
    for cam in scene.rig:
        assert scene.room.contains(cam.center, margin=0.1)
    for item in scene.furniture:
        corners = item.corners()
        assert np.all(np.abs(corners[:, :2]) <= half + 1e-9)
    # Rich textures and at least one weakly textured surface, as in real rooms.
    assert "paint" in scene.texture_kinds
    assert {"posters", "bricks", "stone"} <= set(scene.texture_kinds)
    # Actors: ids 1..K, person-sized, walking at human speed, staying in the room.
    assert [a.actor_id for a in scene.actors] == [1, 2, 3]
    for actor in scene.actors:
        assert 1.55 < actor.height_m < 1.95
        ts = np.arange(np.ceil(actor.enter_frame), actor.leave_frame)
        pos = np.array([actor.position(t) for t in ts])
        assert np.all(np.abs(pos) < half - 0.2)
        speed = np.linalg.norm(np.diff(pos, axis=0), axis=1) * scene.config.fps
        assert 0.3 < np.median(speed) < 2.5
        parts = actor.parts(float(ts[len(ts) // 2]))
        assert len(parts) >= 14
        tops = [p.center[2] + p.radii.max() for p in parts]
        bottoms = [p.center[2] - p.radii.max() for p in parts]
        assert actor.height_m * 0.9 < max(tops) < actor.height_m * 1.1
        assert min(bottoms) > -0.1
    # Someone enters or leaves, and the second actor passes close to the first.
    assert any(a.enter_frame > 0 or a.leave_frame < 60 for a in scene.actors)
    a1, a2 = scene.actors[:2]
    common = [t for t in range(60) if a1.present(t) and a2.present(t)]
    closest = min(np.linalg.norm(a1.position(t) - a2.position(t)) for t in common)
    assert closest < 1.2


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match="num_cameras"):
        RigSpec(num_cameras=2)
    with pytest.raises(ValueError, match="noise_sigma"):
        RealismConfig(noise_sigma=-1)
    with pytest.raises(ValueError, match="radius_m"):
        SceneConfig(rig=RigSpec(radius_m=6.0))
    with pytest.raises(ValueError, match="unknown preset"):
        preset_config("cathedral")
    with pytest.raises(ValueError, match="unknown scene option"):
        preset_config("demo", num_cameraz=4)


def test_config_round_trips_through_dict():
    cfg = preset_config("arc7", seed=4, noise_sigma=1.0)
    assert SceneConfig.from_dict(cfg.to_dict()) == cfg


def test_texture_sides_are_capped():
    bank = _TextureBank(seed=0, texel_m=0.001)
    i = bank.add("paint", (10.0, 3.0))
    h, w = bank.textures[i].shape
    assert w == 2048 and h % 64 == 0
    assert bank.textures[i].texel_m == pytest.approx(10.0 / 2048, rel=1e-3)


def test_illumination_change_dims_over_time():
    cfg = preset_config("demo", width=160, height=120, illumination_change=0.2)
    scene = build_scene(cfg)
    first = scene.illumination(-cfg.background_frames)
    last = scene.illumination(cfg.num_frames - 1)
    assert first == pytest.approx(1.0) and last == pytest.approx(0.8)
    assert build_scene(preset_config("demo", width=160, height=120)).illumination(30) == 1.0
