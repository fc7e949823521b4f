"""A camera whose view moved (``quality.frames.MovedCameras``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgerecon.geometry.camera import Camera
from edgerecon.quality.frames import FrameCheckConfig, MovedCameras
from edgerecon.types import FrameSet

H, W = 360, 480
K = np.array([[400.0, 0.0, W / 2], [0.0, 400.0, H / 2], [0.0, 0.0, 1.0]])


def _camera(width: int = W, height: int = H, K: np.ndarray = K) -> Camera:
    """The calibration the stabiliser is given (a pinhole at the origin)."""
    return Camera(name="cam", width=width, height=height, K=K, R=np.eye(3), t=np.zeros(3))


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A room's worth of texture: blobs and edges at several sizes."""
    out = np.zeros((h, w), np.float32)
    for size in (3, 9, 27):
        out += cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), size) * size
    out = (out - out.min()) / (out.max() - out.min()) * 200 + 25
    return cv2.cvtColor(out.astype(np.uint8), cv2.COLOR_GRAY2BGR)


def _turned(image: np.ndarray, degrees: float, axis: tuple[float, float, float]) -> np.ndarray:
    """``image`` as the camera sees it turned by ``degrees`` about its own ``axis``."""
    dR = cv2.Rodrigues(np.radians(degrees) * np.asarray(axis, float))[0]
    H_ = K @ dR @ np.linalg.inv(K)
    return cv2.warpPerspective(image, H_, (W, H), borderMode=cv2.BORDER_REPLICATE)


def test_a_turned_camera_is_a_move_people_light_and_a_shake_are_not():
    rng = np.random.default_rng(3)
    rooms = [_texture(rng, H, W) for _ in range(5)]
    person = _texture(rng, 300, 200)
    watch = MovedCameras()
    events = []
    for t in range(30):
        noise = [rng.normal(0, 2, (H, W, 3)) for _ in range(5)]
        # cam0: a person 200 px wide (40 % of the frame) walks across it.
        cam0 = rooms[0].copy()
        x = 10 * t
        cam0[40:340, x : x + 200] = person[:, : min(200, W - x)]
        # cam1: turned 1 degree (tilted) at time 10, and stays so.
        cam1 = _turned(rooms[1], 1.0, (1.0, 0.0, 0.0)) if t >= 10 else rooms[1]
        # cam2: the lights dim to half over 20 frames; cam3: shaken at time 5 only.
        cam2 = (rooms[2] * (1.0 - 0.5 * min(t, 20) / 20)).astype(np.uint8)
        cam3 = _turned(rooms[3], 1.0, (0.0, 1.0, 0.0)) if t == 5 else rooms[3]
        # cam4: the left third of its view (a door, a shelf) moved 15 px at time 15.
        cam4 = rooms[4].copy()
        if t >= 15:
            cam4[:, 15:160] = rooms[4][:, :145]
        images = [
            np.clip(im + n, 0, 255).astype(np.uint8)
            for im, n in zip([cam0, cam1, cam2, cam3, cam4], noise, strict=True)
        ]
        events.append(watch.update(FrameSet(time_index=t, images=tuple(images))))
    moves = [(t, m) for t, ms in enumerate(events) for m in ms]
    assert len(moves) == 1
    t, move = moves[0]
    # Seen at its third frame (``moved_after_frames``), dated at its first.
    assert (t, move.camera, move.time_index) == (12, 1, 10)
    # Tilted 1 degree: the image centre went f tan(1 degree) = 7.0 px up.
    assert move.shift_px[0] == pytest.approx(0.0, abs=0.5)
    assert move.shift_px[1] == pytest.approx(-400 * np.tan(np.radians(1.0)), abs=0.7)
    assert abs(move.roll_deg) < 0.2


def test_a_rolled_camera_is_a_move_and_the_check_can_be_off():
    rng = np.random.default_rng(4)
    room = _texture(rng, H, W)
    frames = [room if t < 4 else _turned(room, 2.0, (0.0, 0.0, 1.0)) for t in range(8)]
    on, off = MovedCameras(), MovedCameras(FrameCheckConfig(moved_min_shift=0.0))
    seen, none = [], []
    for t, image in enumerate(frames):
        noisy = np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)
        seen += on.update(FrameSet(time_index=t, images=(noisy,)))
        none += off.update(FrameSet(time_index=t, images=(noisy,)))
    (move,) = seen
    assert move.time_index == 4 and move.roll_deg == pytest.approx(2.0, abs=0.3)
    assert none == []
    with pytest.raises(ValueError, match="moved_min_shift"):
        FrameCheckConfig(moved_min_shift=0.5)
    with pytest.raises(ValueError, match="moved_after_frames"):
        FrameCheckConfig(moved_after_frames=0)


def test_a_camera_turned_while_the_run_was_stopped_is_a_move_against_its_saved_view():
    """The references go over a stop (``references`` / ``restore``): a camera turned
    between the last frame before it and the first after is a move dated at that first
    frame (``across_stop``); the other camera, unmoved, is none. A detector that starts from
    the frames after the stop sees nothing (its first frame is its reference)."""
    rng = np.random.default_rng(5)
    rooms = [_texture(rng, H, W) for _ in range(2)]

    def noisy(image: np.ndarray) -> np.ndarray:
        return np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)

    before = MovedCameras()
    for t in range(6):
        assert before.update(FrameSet(time_index=t, images=tuple(noisy(r) for r in rooms))) == []
    saved = before.references()
    assert sorted(saved) == [0, 1] and all(v.dtype == np.uint8 for v in saved.values())
    resumed, fresh = MovedCameras(), MovedCameras()
    resumed.restore(saved)
    turned = _turned(rooms[1], 1.0, (0.0, 1.0, 0.0))  # panned 1 degree while stopped
    seen, none = [], []
    for t in range(9, 14):
        frames = FrameSet(time_index=t, images=(noisy(rooms[0]), noisy(turned)))
        seen += resumed.update(frames)
        none += fresh.update(frames)
    (move,) = seen
    assert (move.camera, move.time_index, move.across_stop) == (1, 9, True)
    assert move.shift_px[0] == pytest.approx(400 * np.tan(np.radians(1.0)), rel=0.15)
    assert none == []
    # A move during the run is not one across the stop.
    for t in range(14, 18):
        frames = FrameSet(time_index=t, images=(noisy(rooms[0]), noisy(rooms[1])))
        seen += resumed.update(frames)
    assert [(m.camera, m.time_index, m.across_stop) for m in seen[1:]] == [(1, 14, False)]


def test_a_swaying_camera_is_turned_back_onto_its_view():
    """``Stabiliser``: tilts, pans, rolls and a mix of them are taken off the frame (the
    warped frame matches the reference to the noise), the turn measured within 0.1 degree;
    a still frame is left alone; a frame half covered by someone close still gives the
    turn of the rest (the tiles they cover do not follow it)."""
    from edgerecon.quality.frames import Stabiliser, thumbnail

    rng = np.random.default_rng(1)
    room = _texture(rng, H, W)
    steady = Stabiliser()
    steady.start(0, thumbnail(room), _camera())
    assert steady.cameras == {0}
    inner = (slice(30, H - 30), slice(30, W - 30))
    for axis, degrees, person in [
        ((1, 0, 0), 1.0, False),
        ((0, 1, 0), 0.7, False),
        ((0, 0, 1), 0.6, False),
        ((1, 1, 0.3), 1.5, False),
        ((1, 0.4, 0), 1.0, True),
        ((1, 0, 0), 0.0, False),
    ]:
        turned = _turned(room, degrees, tuple(np.asarray(axis) / np.linalg.norm(axis)))
        if person:  # someone close covers the left 40 % of the frame
            turned[:, : int(0.4 * W)] = _texture(rng, H, int(0.4 * W))
        image = np.clip(turned + rng.normal(0, 2, turned.shape), 0, 255).astype(np.uint8)
        out, taken = steady.apply(FrameSet(time_index=0, images=(image, None)))
        assert taken[0] == pytest.approx(degrees, abs=0.1)
        back = np.abs(out.images[0][inner].astype(float) - room[inner])
        if person:
            back = back[:, int(0.45 * W) :]
        assert back.mean() < 2.0, (axis, degrees)
    # Only the cameras started are touched.
    assert steady.apply(FrameSet(time_index=0, images=(None, room)))[1] == {}


def test_a_real_camera_with_lens_distortion_swaying_is_turned_back():
    """caliscope_charuco's cam_1 (a webcam with lens distortion, people and a board moving
    before it) swaying 1 degree (its distortion taken off, the view turned, put back on):
    every 16th frame's turn measured within 0.15 degree, and the frame turned back to
    within a few grey levels of the frame as it came."""
    from edgerecon.io.dataset import open_dataset
    from edgerecon.quality.frames import Stabiliser, thumbnail
    from tests.conftest import shared_data
    from tests.quality.test_calibration import knocked_frames

    ds = open_dataset(shared_data("caliscope_charuco"))
    cam = ds.rig[1]
    steady = Stabiliser()
    before, after = [], []
    with ds.open_frames() as source:
        steady.start(1, thumbnail(source.read(0).images[1]), cam)
        for t in range(3, source.num_frames, 16):
            frames = source.read(t)
            degrees = float(np.sin(2 * np.pi * t / 12 + 0.5))
            swayed = knocked_frames(frames, ds.rig, 1, degrees, (0.92, 0.39, 0.0))
            out, taken = steady.apply(swayed)
            assert taken[1] == pytest.approx(abs(degrees), abs=0.15), t
            h, w = cam.height, cam.width
            middle = (slice(h // 6, 5 * h // 6), slice(w // 6, 5 * w // 6))
            truth = frames.images[1][middle].astype(float)
            before.append(np.abs(swayed.images[1][middle] - truth).mean())
            after.append(np.abs(out.images[1][middle] - truth).mean())
    assert np.mean(before) > 5.0 and np.mean(after) < 0.3 * np.mean(before), (before, after)


def test_the_turn_of_a_camera_that_holds_still_is_its_new_aim_not_a_sway_s():
    """``Stabiliser.steady_turn``: a camera turned 1.2 degrees and left so (a knock) gives
    that turn, as a rotation (its frames' rays ``R r``), once 3 frames are measured; one
    that sways gives none; ``forget`` starts the count again."""
    from edgerecon.quality.frames import Stabiliser, thumbnail

    rng = np.random.default_rng(4)
    room = _texture(rng, H, W)
    axis = np.array([0.8, 0.6, 0.0])
    dR = cv2.Rodrigues(np.radians(1.2) * axis)[0]
    steady = Stabiliser()
    steady.start(0, thumbnail(room), _camera())
    knocked = _turned(room, 1.2, tuple(axis))
    for k in range(4):
        assert (steady.steady_turn(0) is None) == (k < 3)
        image = np.clip(knocked + rng.normal(0, 2, knocked.shape), 0, 255).astype(np.uint8)
        steady.apply(FrameSet(time_index=k, images=(image,)))
    R = steady.steady_turn(0)
    assert R is not None and np.allclose(R @ R.T, np.eye(3), atol=1e-9)
    angle = np.degrees(np.arccos(np.clip((np.trace(R @ dR.T) - 1) / 2, -1, 1)))
    assert angle < 0.08
    steady.forget(0)
    for k, degrees in enumerate([1.0, -1.0, 1.0, -1.0]):
        image = _turned(room, degrees, (1.0, 0.0, 0.0))
        steady.apply(FrameSet(time_index=k, images=(image,)))
    assert steady.steady_turn(0) is None


def test_the_stabiliser_scales_the_calibration_s_intrinsics_to_the_frames():
    """Intrinsics given at the calibration's width (twice the frames'): the turn of the
    frames is measured as with intrinsics at their own size."""
    from edgerecon.quality.frames import Stabiliser, thumbnail

    rng = np.random.default_rng(5)
    room = _texture(rng, H, W)
    steady = Stabiliser()
    steady.start(0, thumbnail(room), _camera().resized(2 * W, 2 * H))
    image = _turned(room, 1.0, (0.0, 1.0, 0.0))
    _, taken = steady.apply(FrameSet(time_index=0, images=(image,)))
    assert taken[0] == pytest.approx(1.0, abs=0.1)
