"""Scripted actors (still intervals, presence gaps, seated posture, gestures), the dimmer, and
the people-in-a-room presets hd4 / hd4p: what they contain and that their ground truth is exact."""

from __future__ import annotations

import json

import numpy as np
import pytest

from edgerecon.synth import GroundTruth, Renderer, build_scene, preset_config, write_dataset
from edgerecon.synth.scene import SceneConfig
from edgerecon.synth.scripts import ActorScript, scripted_path

# The frames the hd4 script promises (docs/ARCHITECTURE.md, "Ground truth folder").
HD4_STRETCHES = {
    "still": [{"actor": 1, "start": 30, "stop": 181}],
    "away": [{"actor": 2, "start": 70, "stop": 130}],
    "seated": [{"actor": 3, "start": 0, "stop": 250}],
    "dimming": [{"start": 186, "stop": 245, "min_level": 0.45}],
}


def _pose(actor, t):
    return np.concatenate([np.r_[p.center, p.rotation.ravel(), p.radii] for p in actor.parts(t)])


# ------------------------------------------------------------------------------ scripts
def test_scripted_path_holds_exactly_and_joins_smoothly():
    times = np.array([0.0, 10.0, 30.0, 50.0])
    points = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.0], [2.0, 2.0]])
    path = scripted_path(times, points, [(10.0, 20.0)])
    held = path(np.linspace(10.0, 20.0, 41))
    assert np.array_equal(held, np.repeat([[1.0, 0.5]], 41, axis=0))
    # Through every key, continuous, with zero velocity into and out of the hold.
    np.testing.assert_allclose(path(times), points, atol=1e-12)
    for b in (10.0, 20.0):
        np.testing.assert_allclose(path(b - 1e-9), path(b + 1e-9), atol=1e-8)
        np.testing.assert_allclose(path(b, 1), 0.0, atol=1e-12)
    assert np.linalg.norm(path(25.0, 1)) > 0.01  # it walks on
    # A hold from the first key, and a single key (never moves).
    start = scripted_path(times, points, [(0.0, 5.0)])
    assert np.array_equal(start(2.5), points[0])
    one = scripted_path(times[:1], points[:1], [])
    assert np.array_equal(one(0.0), points[0])


def test_actor_script_validation_names_the_field():
    with pytest.raises(ValueError, match="keys"):
        ActorScript(keys=())
    with pytest.raises(ValueError, match="keys"):
        ActorScript(keys=((0.0, 0, 0), (0.0, 1, 1)))
    with pytest.raises(ValueError, match=r"still\[0\].*needs a key"):
        ActorScript(keys=((0.0, 0, 0), (10.0, 1, 1)), still=((5.0, 8.0),))
    with pytest.raises(ValueError, match="no key may lie inside"):
        ActorScript(keys=((0.0, 0, 0), (10.0, 1, 1)), still=((0.0, 12.0),))
    with pytest.raises(ValueError, match="present"):
        ActorScript(keys=((0.0, 0, 0),), present=((0.0, 5.0), (4.0, 9.0)))
    with pytest.raises(ValueError, match="posture"):
        ActorScript(keys=((0.0, 0, 0), (10.0, 1, 1)), posture="sit")
    with pytest.raises(ValueError, match="gesture"):
        ActorScript(keys=((0.0, 0, 0),), gesture=3.0)
    with pytest.raises(ValueError, match=r"actor_scripts\[0\].keys"):
        SceneConfig(actor_scripts=(ActorScript(keys=((0.0, 3.9, 0.0),)),))
    with pytest.raises(ValueError, match="light_keys"):
        preset_config("demo", light_keys=((10.0, 1.0), (5.0, 0.5)))


# ------------------------------------------------------------------------------ presets
@pytest.mark.parametrize(("name", "size"), [("hd4", (1920, 1080)), ("hd4p", (1080, 1920))])
def test_hd4_presets_are_people_in_a_room(name, size):
    cfg = preset_config(name)
    assert (cfg.rig.width, cfg.rig.height) == size and cfg.rig.num_cameras == 4
    assert cfg.background_frames == 0 and cfg.fps == 25.0 and cfg.num_frames >= 240
    assert SceneConfig.from_dict(cfg.to_dict()) == cfg
    scene = build_scene(preset_config(name, width=size[0] // 8, height=size[1] // 8))
    rig, target = scene.rig, np.array(cfg.rig.target)
    azimuths = np.degrees(np.arctan2(*(rig.centers[:, 1::-1] - target[1::-1]).T))
    np.testing.assert_allclose(np.diff(azimuths % 360), 90.0, atol=5.0)  # ~90 degrees apart
    for cam in rig:
        assert 1.5 < cam.center[2] < 2.5
        axis = cam.R[2]  # optical axis in world coordinates
        assert -0.45 < axis[2] < -0.1  # looking slightly down
    # Every actor is there from frame 0, typically 2-4 m from the cameras.
    assert [a.actor_id for a in scene.actors] == [1, 2, 3]
    assert all(a.present(0) for a in scene.actors)
    for t in (0.0, 100.0, 212.0):
        for actor in scene.actors_at(t):
            d = np.linalg.norm(rig.centers[:, :2] - actor.position(t), axis=1)
            assert 1.8 < d.min() and d.max() < 5.0 and 2.0 < np.median(d) < 4.0, (t, d)
    assert scene.stretches() == HD4_STRETCHES
    # A 40-task run with --frames 0:240:6 has >= 20 tasks in the still stretch, >= 8 dimmed.
    tasks = range(0, 240, 6)
    assert sum(30 <= t < 181 for t in tasks) >= 20 and sum(186 <= t < 245 for t in tasks) >= 8


def test_hd4_actors_follow_their_script(hd4_scene):
    still, leaver, sitter = hd4_scene.actors
    # The still actor: every body part identical over frames 30..180, moving just outside.
    ref = _pose(still, 30.0)
    for t in (31.0, 100.0, 179.5, 180.0):
        assert np.array_equal(_pose(still, t), ref), t
    assert not np.array_equal(_pose(still, 28.0), ref)
    assert not np.array_equal(_pose(still, 182.0), ref)
    # Walking at human speed; no body turns faster than ~180 degrees per second.
    fps = hd4_scene.config.fps
    for actor in (still, leaver):
        ts = [t for t in range(250) if actor.present(t) and actor.present(t + 1)]
        speed = [np.linalg.norm(actor.position(t + 1) - actor.position(t)) * fps for t in ts]
        assert max(speed) < 1.9
        turn = [
            abs((actor.heading(t + 1) - actor.heading(t) + np.pi) % (2 * np.pi) - np.pi) for t in ts
        ]
        assert np.degrees(max(turn)) * fps < 250
    # The leaver walks out near the +x wall and comes back there.
    half_x = hd4_scene.room.half_x
    assert leaver.present(69) and not leaver.present(70) and not leaver.present(129)
    assert leaver.present(130)
    for t in (69.0, 130.0):
        assert half_x - leaver.position(t)[0] < 0.6
    # The seated actor never leaves its chair but its hands and head move (talking).
    assert sitter.seated and sitter.speed(100.0) == 0.0
    hands = [
        np.concatenate([p.center for p in sitter.parts(float(t))[-6:]]) for t in range(0, 60, 5)
    ]
    assert np.ptp(np.array(hands), axis=0).max() > 0.05
    # People keep apart (no interpenetration).
    for a in range(3):
        for b in range(a + 1, 3):
            A, B = hd4_scene.actors[a], hd4_scene.actors[b]
            gaps = [
                np.linalg.norm(A.position(t) - B.position(t))
                for t in range(250)
                if A.present(t) and B.present(t)
            ]
            assert min(gaps) > 0.6


def test_dimmer_levels(hd4_scene):
    levels = [hd4_scene.illumination(t) for t in (0, 185, 197.5, 210, 215, 220, 232.5, 245, 249)]
    np.testing.assert_allclose(levels, [1, 1, 0.725, 0.45, 0.45, 0.45, 0.725, 1, 1])
    drifting = build_scene(preset_config("hd4", width=96, height=54, illumination_change=0.2))
    assert drifting.illumination(210) == pytest.approx(0.45 * (1 - 0.2 * 210 / 249))


# ------------------------------------------------------------------------------ ground truth
# (exactness of depth, masks and clouds: the hd4 cases of test_render.py / test_groundtruth.py)
def test_hd4_masks_over_the_stretches(hd4_renderer, hd4_scene):
    still = [hd4_renderer.render(t) for t in (30, 120, 180)]
    for k in range(4):
        ref = still[0].masks[k]
        m0 = ref == 1
        assert m0.sum() > 200
        for f in still[1:]:
            # Actor 1's silhouette and depth are identical over the whole still stretch, except
            # where another actor passes in front of it.
            m = f.masks[k] == 1
            both = m & m0
            assert np.array_equal(f.depths[k][both], still[0].depths[k][both])
            changed = m != m0
            assert np.all((ref[changed] > 1) | (f.masks[k][changed] > 1))
            assert changed.sum() < 0.2 * m0.sum()
    # Away: actor 2 is in no view during the stretch, back in some view right after it.
    assert not any((m == 2).any() for m in still[1].masks)
    assert any((m == 2).any() for m in hd4_renderer.render(130).masks)
    # The chair is static background: the seated actor's mask sits on it in every frame.
    for k in range(4):
        labels = hd4_renderer.background_labels(k)
        assert labels.max() == len(hd4_scene.furniture)  # the chair boxes are the last items
    seat_top = 2 * hd4_scene.furniture[-2].half[2]
    legs = hd4_scene.actors[2].parts(50.0)[:6]  # thigh, shin, foot of each leg
    thighs = [legs[0], legs[3]]
    for thigh in thighs:  # horizontal, resting on the seat (radii[0]: its thickness)
        assert abs(thigh.center[2] - thigh.radii[0] - seat_top) < 0.02
    feet = [legs[2], legs[5]]
    assert all(abs(f.center[2] - f.radii[0]) < 0.02 for f in feet)  # soles on the floor


def test_dimming_darkens_the_frames(hd4_scene):
    scene = build_scene(preset_config("hd4", width=160, height=90, noise_sigma=0.0))
    r = Renderer(scene)
    full, dim = r.render(100), r.render(212)
    for k in range(4):
        bg = (full.masks[k] == 0) & (dim.masks[k] == 0)
        a = full.images[k][bg].astype(float)
        b = dim.images[k][bg].astype(float)
        ok = (a > 20) & (a < 250)
        ratio = np.median(b[ok] / a[ok])
        assert ratio == pytest.approx(0.45, abs=0.02), (k, ratio)


def test_stretches_recorded_in_scene_json(tmp_path):
    """A short scripted scene: the still / away / dimming stretches land in gt/scene.json and
    the ground-truth reader returns them (benchmarks need no hard-coded frames)."""
    scripts = (
        ActorScript(keys=((0.0, -0.6, 0.3), (2.0, -0.2, 0.3)), still=((2.0, 4.0),)),
        ActorScript(keys=((0.0, 0.6, -0.4), (6.0, 0.4, -0.8)), present=((0.0, 2.0), (4.0, 6.0))),
    )
    cfg = preset_config(
        "hd4",
        width=96,
        height=54,
        num_frames=6,
        num_actors=2,
        actor_scripts=scripts,
        light_keys=((2.0, 1.0), (4.0, 0.5), (5.0, 1.0)),
    )
    summary = write_dataset(cfg, tmp_path / "s")
    want = {
        "still": [{"actor": 1, "start": 2, "stop": 5}],
        "away": [{"actor": 2, "start": 2, "stop": 4}],
        "seated": [],
        "dimming": [{"start": 3, "stop": 5, "min_level": 0.5}],
    }
    assert summary.stretches == want
    gt = GroundTruth.open(tmp_path / "s")
    assert gt.stretches == want
    assert [gt.illumination(t) for t in range(6)] == [1.0, 1.0, 1.0, 0.75, 0.5, 1.0]
    meta = json.loads((tmp_path / "s" / "gt" / "scene.json").read_text())
    assert meta["actors"][1]["presence"] == [[0.0, 2.0], [4.0, 6.0]]
    assert SceneConfig.from_dict(meta["config"]) == cfg
    assert not (gt.object_mask(0, 2) == 2).any() and not (gt.object_mask(0, 3) == 2).any()
    assert not (tmp_path / "s" / "background").exists()
