"""Background model: known-answer tests on small synthetic image sequences."""

from __future__ import annotations

import pickle

import cv2
import numpy as np
import pytest

from edgerecon.quality.masks import at_resolution, mask_iou
from edgerecon.scene.background import BackgroundConfig, BackgroundModel, working_size
from edgerecon.types import DataError
from tests.scene._scenes import noisy, paint, square_mask, textured_background

H, W = 120, 160


@pytest.fixture
def background() -> np.ndarray:
    return textured_background(H, W)


def _learn(background: np.ndarray, rng: np.random.Generator, **kw: object) -> BackgroundModel:
    clip = [noisy(background, 3.0, rng) for _ in range(20)]
    return BackgroundModel.learn(clip, BackgroundConfig(**kw), camera="test")  # type: ignore[arg-type]


def test_moving_square_is_segmented_with_high_iou(background: np.ndarray) -> None:
    rng = np.random.default_rng(0)
    model = _learn(background, rng)
    ious = []
    for t in range(20):
        truth = square_mask(H, W, 10 + 5 * t, 30, 40)
        frame = noisy(paint(background, truth, (30, 200, 60)), 3.0, rng)
        mask = model.apply(frame)
        ious.append(mask_iou(mask, truth))
    assert min(ious) > 0.9, ious
    # Pixels far from the square never light up: background noise is suppressed.
    assert np.mean(ious) > 0.95


def test_no_motion_gives_empty_foreground(background: np.ndarray) -> None:
    rng = np.random.default_rng(1)
    model = _learn(background, rng)
    for _ in range(10):
        mask = model.apply(noisy(background, 3.0, rng))
    assert mask.dtype == bool and mask.shape == (H, W)
    assert not mask.any()


def test_global_illumination_ramp_is_not_foreground(background: np.ndarray) -> None:
    rng = np.random.default_rng(2)
    model = _learn(background, rng)
    areas = []
    for t in range(30):
        gain = 1.0 - 0.012 * t  # 35 % darker at the end, per-channel slightly different
        lit = np.clip(background * np.array([gain, gain * 0.98, gain * 1.01]), 0, 255)
        seg = model.segment(noisy(lit.astype(np.uint8), 3.0, rng))
        areas.append(seg.foreground.mean())
    assert max(areas) < 0.002, max(areas)
    # The model measured the gain it compensated.
    assert abs(seg.gain[0] - (1.0 - 0.012 * 29)) < 0.03


def test_without_gain_compensation_the_ramp_would_be_flagged(background: np.ndarray) -> None:
    # Guards the test above: the ramp is strong enough to matter.
    lit = np.clip(background * 0.65, 0, 255).astype(np.uint8)
    diff = np.linalg.norm(lit.astype(float) - background, axis=2)
    assert np.mean(diff > 12.0) > 0.5


def test_shadow_is_not_foreground(background: np.ndarray) -> None:
    rng = np.random.default_rng(3)
    model = _learn(background, rng)
    shadow = square_mask(H, W, 40, 40, 50)
    darker = background.astype(np.float64)
    darker[shadow] *= 0.6
    seg = model.segment(noisy(darker.astype(np.uint8), 3.0, rng))
    assert seg.foreground[shadow].mean() < 0.02
    assert seg.shadow.mean() > 0.5 * shadow.mean()
    # A dark *object* with a different colour in the same place is foreground.
    obj = paint(background, shadow, (20, 20, 90))
    assert model.apply(noisy(obj, 3.0, rng))[shadow].mean() > 0.95


def test_still_actor_is_not_absorbed(background: np.ndarray) -> None:
    rng = np.random.default_rng(4)
    model = _learn(background, rng, learning_rate=0.05)
    truth = square_mask(H, W, 50, 30, 40)
    frame_with_actor = paint(background, truth, (200, 60, 60))
    # 100 updates = 50 s at the default update interval of an actor who does not move: held.
    for _ in range(100):
        mask = model.apply(noisy(frame_with_actor, 3.0, rng))
    assert mask_iou(mask, truth) > 0.95


def test_mog2_absorbs_the_same_still_actor(background: np.ndarray) -> None:
    # The reason for the selective update: OpenCV's MOG2 absorbs a still actor.
    rng = np.random.default_rng(4)
    mog = cv2.createBackgroundSubtractorMOG2(history=200, detectShadows=False)
    for _ in range(20):
        mog.apply(noisy(background, 3.0, rng))
    truth = square_mask(H, W, 50, 30, 40)
    frame_with_actor = paint(background, truth, (200, 60, 60))
    for _ in range(300):
        fg = mog.apply(noisy(frame_with_actor, 3.0, rng))
    assert mask_iou(fg > 0, truth) < 0.5


def test_static_change_is_absorbed_after_absorb_after_frames(background: np.ndarray) -> None:
    rng = np.random.default_rng(5)
    model = _learn(background, rng, learning_rate=0.2, absorb_after_frames=20)
    change = square_mask(H, W, 50, 30, 40)
    moved = paint(background, change, (60, 60, 200))
    areas = [model.apply(noisy(moved, 3.0, rng))[change].mean() for _ in range(80)]
    assert areas[10] > 0.95  # still foreground before absorb_after_frames
    assert areas[-1] < 0.05  # learned afterwards


def test_learning_from_stream_with_moving_actor_recovers_background(background: np.ndarray) -> None:
    rng = np.random.default_rng(6)
    frames = []
    for t in range(15):
        truth = square_mask(H, W, 10 * t, 40, 30)  # crosses the image
        frames.append(noisy(paint(background, truth, (0, 255, 0)), 3.0, rng))
    model = BackgroundModel.learn(frames, camera="stream")
    err = np.abs(model.background_image().astype(int) - background.astype(int))
    assert np.percentile(err, 99) < 12


def test_state_round_trip_and_pickle(background: np.ndarray) -> None:
    rng = np.random.default_rng(7)
    model = _learn(background, rng)
    frames = [
        noisy(paint(background, square_mask(H, W, 20 + 6 * t, 50, 30), (250, 250, 0)), 3.0, rng)
        for t in range(6)
    ]
    for f in frames[:3]:
        model.apply(f)
    clone = BackgroundModel.from_state(pickle.loads(pickle.dumps(model.state)), model.config)
    assert clone.num_frames == model.num_frames == 3
    for f in frames[3:]:
        np.testing.assert_array_equal(model.apply(f), clone.apply(f))
    np.testing.assert_array_equal(model.state.mean, clone.state.mean)


def test_working_resolution_bounds_the_pixels() -> None:
    bg = textured_background(240, 640)
    rng = np.random.default_rng(8)
    model = BackgroundModel.learn(
        [noisy(bg, 2.0, rng) for _ in range(5)], BackgroundConfig(working_pixels=40_000)
    )
    # 640x240 = 153,600 px -> 40,000 allows 0.51: the exact half (38,400 px) is close enough.
    assert model.working_size == (320, 120) == working_size((640, 240), 40_000)
    assert working_size((640, 240), 60_000) == (400, 150)  # no integer factor close enough
    assert working_size((640, 240), 200_000) == (640, 240)
    truth = square_mask(240, 640, 200, 60, 100)
    mask = model.apply(noisy(paint(bg, truth, (255, 0, 255)), 2.0, rng))
    assert mask.shape == (120, 320)  # masks stay at the working resolution
    assert mask_iou(at_resolution(mask, truth.shape), truth) > 0.93


def test_segment_never_changes_the_model(background: np.ndarray) -> None:
    rng = np.random.default_rng(9)
    model = _learn(background, rng)
    before = model.state
    frame = noisy(paint(background, square_mask(H, W, 40, 40, 30), (0, 0, 255)), 3.0, rng)
    for _ in range(3):
        model.segment(frame)
    after = model.state
    np.testing.assert_array_equal(before.mean, after.mean)
    np.testing.assert_array_equal(before.var, after.var)
    assert after.num_frames == before.num_frames == 0
    model.update(frame)
    assert model.num_frames == 1


def test_ghost_of_a_departed_actor_is_repaired_but_a_stopped_one_is_held(
    background: np.ndarray,
) -> None:
    """An actor present while the model is bootstrapped leaves: the uncovered background is
    a ghost (its outline is in the model, not in the frame) and is learned at the first update;
    a second actor who walked in and stopped is held."""
    rng = np.random.default_rng(10)
    sitter = square_mask(H, W, 20, 30, 35)
    with_sitter = paint(background, sitter, (40, 200, 230))
    model = BackgroundModel.learn(
        [noisy(with_sitter, 3.0, rng) for _ in range(10)], BackgroundConfig(), camera="c"
    )
    # The sitter is background for the model: nothing is foreground.
    assert model.segment(noisy(with_sitter, 3.0, rng)).foreground.mean() < 0.01
    walker = square_mask(H, W, 100, 40, 30)
    left = noisy(paint(background, walker, (200, 60, 60)), 3.0, rng)
    seg = model.segment(left)
    assert seg.foreground[sitter].mean() > 0.9  # the ghost, before repair
    stats = model.update(left, seg)
    assert stats.ghosts == 1 and stats.ghost_px >= 0.9 * sitter.sum()
    after = model.segment(noisy(paint(background, walker, (200, 60, 60)), 3.0, rng))
    assert after.foreground[sitter].mean() < 0.05  # repaired at once
    assert mask_iou(after.foreground, walker) > 0.9  # the stopped walker is held
    for _ in range(20):
        model.apply(noisy(paint(background, walker, (200, 60, 60)), 3.0, rng))
    assert (
        mask_iou(
            model.segment(noisy(paint(background, walker, (200, 60, 60)), 3.0, rng)).foreground,
            walker,
        )
        > 0.9
    )


def test_bad_input_raises_data_error(background: np.ndarray) -> None:
    with pytest.raises(DataError, match="no frames"):
        BackgroundModel.learn([], camera="cam9")
    with pytest.raises(DataError, match="differ in size"):
        BackgroundModel.learn([background, background[:-1]], camera="cam9")
    model = BackgroundModel.learn([background], camera="cam9")
    with pytest.raises(DataError, match="cam9.*159x120"):
        model.apply(background[:, :-1])


@pytest.mark.parametrize(
    "field, value",
    [
        ("threshold_sigma", 0.0),
        ("learning_rate", 1.5),
        ("shadow_min_brightness", 0.0),
        ("min_gain", 1.5),
        ("working_pixels", 4),
        ("min_free_frames", 0),
    ],
)
def test_config_validation_names_the_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        BackgroundConfig(**{field: value})  # type: ignore[arg-type]


def test_unsettled_marks_where_something_moved_while_learning(background: np.ndarray) -> None:
    rng = np.random.default_rng(7)
    # An empty-scene clip: nothing is unsettled (the hull fill never touches such a camera).
    assert not _learn(background, rng).unsettled.any()
    frames = []
    crossed = np.zeros((H, W), bool)
    for t in range(8):
        truth = square_mask(H, W, 10 * t, 40, 30)
        crossed |= truth
        frames.append(noisy(paint(background, truth, (0, 255, 0)), 3.0, rng))
    model = BackgroundModel.learn(frames, camera="stream")
    unsettled = at_resolution(model.unsettled, (H, W))
    assert unsettled[crossed].mean() > 0.95
    far = ~(cv2.dilate(crossed.view(np.uint8), np.ones((15, 15), np.uint8)) > 0)
    assert not unsettled[far].any()
    # Stored with the model (never recomputed), and the same after a round trip.
    assert model.unsettled is model.unsettled
    again = BackgroundModel.from_state(model.state)
    assert np.array_equal(again.unsettled, model.unsettled)


def test_learning_from_stream_leaves_out_the_frames_a_person_covers(background: np.ndarray) -> None:
    """An actor who walks along a camera's line of sight covers the same pixels in most of
    the learning frames: the plain median learns the actor there; with the person model's
    masks the median is over the frames that show the pixel free of people, where at least
    ``min_free_frames`` do (elsewhere, over all of them)."""
    rng = np.random.default_rng(8)
    frames, people = [], []
    for t in range(8):
        # Covered in 5 of 8 frames (t = 0..4), then gone.
        truth = square_mask(H, W, 60 + t, 40, 30) if t < 5 else np.zeros((H, W), bool)
        frames.append(noisy(paint(background, truth, (0, 255, 0)), 3.0, rng))
        people.append(truth)
    core = square_mask(H, W, 65, 44, 20)  # covered in every one of the five
    plain = BackgroundModel.learn(frames, camera="stream")
    err = np.abs(plain.background_image().astype(int) - background.astype(int)).max(axis=2)
    assert np.median(err[core]) > 100  # the actor's green
    model = BackgroundModel.learn(frames, camera="stream", people=people)
    err = np.abs(model.background_image().astype(int) - background.astype(int)).max(axis=2)
    assert np.percentile(err[core], 99) < 15
    assert np.percentile(err[~core], 99) < 15
    # A person over a pixel in all but two frames: too few free frames, the plain median.
    seated = [square_mask(H, W, 60, 40, 30) if t < 6 else np.zeros((H, W), bool) for t in range(8)]
    frames = [noisy(paint(background, m, (0, 255, 0)), 3.0, rng) for m in seated]
    model = BackgroundModel.learn(frames, camera="stream", people=seated)
    err = np.abs(model.background_image().astype(int) - background.astype(int)).max(axis=2)
    assert np.median(err[square_mask(H, W, 66, 44, 20)]) > 100
    with pytest.raises(ValueError, match="person masks"):
        BackgroundModel.learn(frames, camera="stream", people=seated[:3])


def test_a_person_back_where_they_stood_while_the_model_learned_is_no_ghost(
    background: np.ndarray,
) -> None:
    """The ghost test learns at once a still foreground pixel whose colour the learning
    frames showed: with the person model's masks, the frames that showed a person there do
    not count (they showed no background), so a person who comes back to where they stood
    then stays foreground."""
    import dataclasses

    rng = np.random.default_rng(9)
    place = square_mask(H, W, 60, 40, 30)
    people = [place if t < 5 else np.zeros((H, W), bool) for t in range(8)]
    learning = [noisy(paint(background, m, (0, 255, 0)), 3.0, rng) for m in people]
    back = paint(background, place, (0, 255, 0))

    def after_standing(model: BackgroundModel) -> float:
        for _ in range(3):  # a still person: foreground at the last update too
            model.update(noisy(back, 3.0, rng))
        fg = model.segment(noisy(back, 3.0, rng)).foreground
        return float(at_resolution(fg, (H, W))[place].mean())

    model = BackgroundModel.learn(learning, camera="stream", people=people)
    assert model.state.seen_people is not None
    assert after_standing(model) > 0.9
    # The same model without the people's masks in its learning frames: learned as a ghost.
    blind = BackgroundModel.from_state(dataclasses.replace(model.state, seen_people=None))
    assert after_standing(blind) < 0.1
