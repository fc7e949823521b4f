"""The rig-level foreground stage on a synthetic scene with exact masks and depth."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest

from edgerecon.quality.masks import score_mask_set
from edgerecon.scene import (
    ForegroundConfig,
    RigForeground,
    hull_depth_range,
    split_sparse,
)
from edgerecon.types import DataError, FrameSet

FRAMES = range(0, 6)


@pytest.fixture(scope="module")
def scene():  # type: ignore[no-untyped-def]
    """The demo preset at its native 640x480 (5 cameras, 2 actors), rendered in memory."""
    from edgerecon.synth import Renderer, build_scene, preset_config

    sc = build_scene(preset_config("demo", seed=0, num_frames=len(FRAMES), background_frames=8))
    renderer = Renderer(sc)
    background = [renderer.render(t) for t in range(-8, 0)]
    frames = [renderer.render(t) for t in FRAMES]
    return sc, background, frames


@pytest.fixture(scope="module")
def segmented(scene):  # type: ignore[no-untyped-def]
    sc, background, frames = scene
    fg = RigForeground.learn_from_framesets(
        sc.rig, [FrameSet(time_index=f.time_index, images=f.images) for f in background]
    )
    results = [fg.segment(FrameSet(time_index=f.time_index, images=f.images)) for f in frames]
    return fg, results


def test_masks_match_ground_truth(scene, segmented) -> None:  # type: ignore[no-untyped-def]
    _, _, frames = scene
    _, results = segmented
    preds = [m for r in results for m in r.masks]
    gts = [m for f in frames for m in f.masks]
    score = score_mask_set(preds, gts)
    assert score.foreground_iou > 0.9, score
    assert score.precision > 0.93 and score.recall > 0.9
    # The hull consistency step does not cost quality against the model's own masks.
    model = score_mask_set([m for r in results for m in r.model_masks], gts)
    assert score.foreground_iou > model.foreground_iou - 0.01


def test_hull_depth_ranges_bracket_the_true_depth(scene, segmented) -> None:  # type: ignore[no-untyped-def]
    sc, _, frames = scene
    _, results = segmented
    hits = total = 0
    for f, r in zip(frames[-2:], results[-2:], strict=True):
        assert r.hull is not None and r.hull.num_objects >= 1
        for c, cam in enumerate(sc.rig):
            dr = hull_depth_range(r.hull, cam)
            m = f.masks[c] > 0
            d = f.depths[c][m]
            hits += int(((dr.near[m] <= d) & (d <= dr.far[m])).sum())
            total += int(m.sum())
    assert hits / total > 0.9


def test_sparse_split_of_true_surface_points(scene, segmented) -> None:  # type: ignore[no-untyped-def]
    sc, _, frames = scene
    _, results = segmented
    f, r = frames[-1], results[-1]
    rng = np.random.default_rng(0)
    pts, truth, vis = [], [], []
    for c, cam in enumerate(sc.rig):
        ys, xs = np.nonzero(np.ones_like(f.masks[c]))
        pick = rng.choice(len(xs), 300, replace=False)
        uv = np.stack([xs[pick], ys[pick]], axis=1).astype(float)
        p = cam.backproject(uv, f.depths[c][ys[pick], xs[pick]].astype(float))
        pts.append(p)
        truth.append(f.masks[c][ys[pick], xs[pick]] > 0)
        row = np.zeros((len(p), len(sc.rig)), bool)
        row[:, c] = True
        # Other cameras observe the point when their true depth agrees (no occlusion).
        for o, other in enumerate(sc.rig):
            if o == c:
                continue
            ouv, od = other.project(p)
            ok = (od > 0) & other.in_image(ouv)
            ouv = np.where(ok[:, None], ouv, 0.0)
            u = np.clip(np.rint(ouv[:, 0]).astype(int), 0, other.width - 1)
            v = np.clip(np.rint(ouv[:, 1]).astype(int), 0, other.height - 1)
            row[:, o] = ok & (np.abs(f.depths[o][v, u] - od) < 0.03)
        vis.append(row)
    points, is_fg, visibility = np.vstack(pts), np.concatenate(truth), np.vstack(vis)
    split = split_sparse(points, visibility, sc.rig.cameras, r.label_images())
    voted = split.labels >= 0
    accuracy = np.mean((split.labels[voted] > 0) == is_fg[voted])
    assert voted.mean() > 0.99 and accuracy > 0.97, accuracy


def test_states_round_trip(scene, segmented) -> None:  # type: ignore[no-untyped-def]
    sc, _, frames = scene
    fg, _ = segmented
    clone = RigForeground.from_states(sc.rig, pickle.loads(pickle.dumps(fg.states())), fg.config)
    fs = FrameSet(time_index=0, images=frames[0].images)
    a = fg.segment(fs)
    b = clone.segment(fs)
    for ma, mb in zip(a.masks, b.masks, strict=True):
        np.testing.assert_array_equal(ma, mb)


def test_missing_camera_frame_and_bad_input(scene, segmented) -> None:  # type: ignore[no-untyped-def]
    _, _, frames = scene
    fg, _ = segmented
    images = list(frames[0].images)
    images[1] = None
    res = fg.segment(FrameSet(time_index=0, images=tuple(images)))
    assert res.masks[1] is None and res.objects[1] is None and res.areas()[1] is None
    assert res.masks[0] is not None and res.masks[0].any()
    with pytest.raises(DataError, match="2 images for 5 cameras"):
        fg.segment(FrameSet(time_index=0, images=tuple(images[:2])))
    with pytest.raises(DataError, match="occluder"):
        fg.set_occluders([None])
    with pytest.raises(ValueError, match="ForegroundConfig.hull"):
        ForegroundConfig(hull=None)  # type: ignore[arg-type]


def test_reduced_frames_give_the_same_masks(scene, segmented) -> None:  # type: ignore[no-untyped-def]
    """Frames reduced to the working size (what travels between nodes) segment and teach the
    models exactly as the full frames do."""
    sc, _, frames = scene
    fg, _ = segmented
    a = RigForeground.from_states(sc.rig, fg.states(), fg.config)
    b = RigForeground.from_states(sc.rig, fg.states(), fg.config)
    fs = FrameSet(time_index=0, images=frames[0].images)
    small = a.reduce(fs)
    assert all(
        im.shape[1::-1] == m.working_size for im, m in zip(small.images, a.models, strict=True)
    )
    for ma, mb in zip(a.segment(fs).masks, b.segment(small).masks, strict=True):
        np.testing.assert_array_equal(ma, mb)
    a.update(fs)
    b.update(small)
    for sa, sb in zip(a.states(), b.states(), strict=True):
        np.testing.assert_array_equal(sa.mean, sb.mean)


def test_threads_give_the_same_masks(scene, segmented) -> None:  # type: ignore[no-untyped-def]
    """The per-camera steps (background subtraction, photo check, refinement, objects) on two
    threads or one after the other: the same masks, hull and objects."""
    sc, _, frames = scene
    fg, _ = segmented
    one = RigForeground.from_states(
        sc.rig, fg.states(), dataclasses.replace(fg.config, num_threads=1)
    )
    two = RigForeground.from_states(
        sc.rig, fg.states(), dataclasses.replace(fg.config, num_threads=2)
    )
    for f in frames[2:5]:
        fs = FrameSet(time_index=f.time_index, images=f.images)
        a, b = one.segment(fs), two.segment(fs)
        assert "photo_check" in a.timings.to_dict()
        for ma, mb in zip(a.masks, b.masks, strict=True):
            np.testing.assert_array_equal(ma, mb)
        for oa, ob in zip(a.objects, b.objects, strict=True):
            assert oa is not None and ob is not None
            np.testing.assert_array_equal(oa.labels, ob.labels)


def test_hull_fill_adds_only_unsettled_pixels_inside_the_masks_outline(scene) -> None:  # type: ignore[no-untyped-def]
    """Models learned from the stream (the actors walk through the learning frames): the
    fill adds foreground only where the learning frames disagreed, never removes any, and
    does not cost quality against the truth."""
    sc, _, frames = scene
    sets = [FrameSet(time_index=f.time_index, images=f.images) for f in frames]
    # The photo check after the fill judges the pixels of both against their hulls, which
    # differ: it is left out of this comparison of the fill alone (tests/scene/test_ghosts.py).
    cfg = ForegroundConfig(photo_check=False)
    with_fill = RigForeground.learn_from_framesets(sc.rig, sets, cfg)
    without = RigForeground.learn_from_framesets(
        sc.rig, sets, dataclasses.replace(cfg, hull_fill=False)
    )
    assert any(m.unsettled.any() for m in with_fill.models)
    added = 0
    for f, fs in zip(frames, sets, strict=True):
        a, b = with_fill.segment(fs), without.segment(fs)
        assert "hull_fill" in a.timings.seconds and "hull_fill" not in b.timings.seconds
        # The masks as the hull steps leave them (the outline refinement comes after).
        for m_a, m_b, model in zip(a.checked_masks, b.checked_masks, with_fill.models, strict=True):
            assert not (m_b & ~m_a).any()  # never removes
            new = m_a & ~m_b
            assert not (new & ~model.unsettled).any()  # only where the model is unsettled
            added += int(new.sum())
        gts = list(f.masks)
        assert (
            score_mask_set(list(a.masks), gts).foreground_iou
            >= score_mask_set(list(b.masks), gts).foreground_iou - 0.01
        )
    assert added > 0


def test_hull_rescue_only_gives_back_the_models_own_pixels(scene) -> None:  # type: ignore[no-untyped-def]
    """With the rescue (default) the masks hold everything they hold without it, and what
    they gain is foreground of the camera's own model."""
    sc, _, frames = scene
    sets = [FrameSet(time_index=f.time_index, images=f.images) for f in frames]
    # Without the fill and the photo check, which act on the hull after the rescue.
    cfg = ForegroundConfig(hull_fill=False, photo_check=False)
    on = RigForeground.learn_from_framesets(sc.rig, sets, cfg)
    off = RigForeground.learn_from_framesets(
        sc.rig, sets, dataclasses.replace(cfg, hull_rescue=False)
    )
    for fs in sets:
        a, b = on.segment(fs), off.segment(fs)
        assert "hull_rescue" in a.timings.seconds and "hull_rescue" not in b.timings.seconds
        # The masks as the hull steps leave them (the outline refinement comes after).
        for m_a, m_b, model in zip(a.checked_masks, b.checked_masks, a.model_masks, strict=True):
            assert not (m_b & ~m_a).any()
            assert not (m_a & ~m_b & ~model).any()
        assert a.hull is not None and b.hull is not None
        assert a.hull.contains(b.hull.centers).all()


def test_refined_pixels_that_bring_two_objects_together_are_dropped() -> None:
    """Pixels the outline refinement added that make two objects of the masks before it one
    object (closer than the objects' fragment gap, without touching) leave the masks."""
    from edgerecon.scene.foreground import _CheckedObjects, _unglued
    from edgerecon.scene.objects import ObjectConfig, find_objects

    before = np.zeros((120, 160), bool)
    before[30:100, 40:70] = True
    before[30:100, 82:112] = True  # 12 px apart: two objects (the gap is 3 px here)
    cfg = ObjectConfig()
    assert find_objects(before, cfg).num_objects == 2
    after = before.copy()
    after[30:100, 70:80] = True  # grown toward the other, 2 px apart: one object
    after[20:30, 40:70] = True  # and grown elsewhere, away from the other
    assert find_objects(after, cfg).num_objects == 1
    base = _CheckedObjects([before, None], cfg)
    masks, found = _unglued([after, None], [find_objects(after, cfg), None], base, cfg)
    assert masks[1] is None and found[1] is None
    out, seg = masks[0], found[0]
    assert out is not None and seg is not None
    assert seg.num_objects == 2
    # Every pixel the merged object gained goes; the masks before are kept whole.
    np.testing.assert_array_equal(out, before)
    # A refinement that glues nothing keeps its pixels.
    apart = before.copy()
    apart[20:30, 40:70] = True
    masks, found = _unglued([apart, None], [find_objects(apart, cfg), None], base, cfg)
    np.testing.assert_array_equal(masks[0], apart)


@pytest.mark.parametrize(
    "field",
    [
        {"refine_px": -1},
        {"refine_passes": 0},
        {"refine_subsample": 0},
        {"refine_eps": 0.0},
        {"refine_min_push": 0.5},
        {"num_threads": 0},
    ],
)
def test_refinement_settings_are_checked(field: dict[str, float]) -> None:
    with pytest.raises(ValueError, match=next(iter(field))):
        ForegroundConfig(**field)  # type: ignore[arg-type]
