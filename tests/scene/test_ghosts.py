"""Ghosts told from the static scene that other cameras see uncovered."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgerecon.geometry import Camera, Rig
from edgerecon.scene.ghosts import (
    PhotoCheckConfig,
    StaticCheckConfig,
    photo_consistent_masks,
    static_consistent_masks,
)
from edgerecon.types import DataError
from tests.scene._scenes import box_silhouette, box_surface_points, ring_with_top

LO = np.array([-0.3, -0.2, 0.5])
HI = np.array([0.3, 0.2, 1.4])
BOX_BGR = np.array([230.0, 25.0, 235.0])  # unlike any floor colour


def _floor_bgr(points: np.ndarray) -> np.ndarray:
    """A smooth colour field on the floor (z = 0), the same from every camera."""
    x, y = points[:, 0], points[:, 1]
    return np.stack(
        [120 + 70 * np.sin(2.0 * x), 120 + 70 * np.cos(1.5 * y), 90 + 40 * np.sin(x + y)], axis=1
    )


def _view(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, static depth, box silhouette) of a floor and a floating box."""
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    px = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    dirs = cam.pixel_rays(px) @ cam.R  # world directions, parametrised by depth
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = -cam.center[2] / dirs[:, 2]
    hit = np.isfinite(depth) & (depth > 0)
    image = np.full((len(px), 3), 50.0)
    image[hit] = _floor_bgr(cam.center + dirs[hit] * depth[hit, None])
    static = np.where(hit, depth, np.nan).reshape(cam.height, cam.width).astype(np.float32)
    box = box_silhouette(cam, LO, HI)
    image = image.reshape(cam.height, cam.width, 3)
    image[box] = BOX_BGR
    return image.astype(np.float32), static, box


@pytest.fixture(scope="module")
def rig() -> Rig:
    return ring_with_top(6)


def test_a_ghost_on_the_floor_goes_and_the_actor_stays(rig: Rig) -> None:
    views = [_view(c) for c in rig]
    images = [v[0] for v in views]
    static = [v[1] for v in views]
    masks = [v[2].copy() for v in views]
    # Camera 0's model learned an actor where it stood: a patch of floor is foreground there.
    free = np.isfinite(static[0]) & ~masks[0]
    inner = cv2.erode(free.view(np.uint8), np.ones((17, 17), np.uint8)) > 0
    ys, xs = np.nonzero(inner)
    by, bx = np.argwhere(masks[0]).mean(axis=0)
    k = int(np.argmin((ys - by) ** 2 + (xs - bx) ** 2))  # floor beside the actor
    ghost = np.zeros_like(masks[0])
    ghost[ys[k] - 8 : ys[k] + 8, xs[k] - 8 : xs[k] + 8] = True
    assert ghost.sum() == 256 and not (ghost & ~free).any()
    masks[0] |= ghost

    out, removed = static_consistent_masks(masks, images, rig.cameras, static)
    assert out[0][ghost].mean() < 0.1  # the ghost is gone
    assert removed[0] >= 0.9 * ghost.sum()
    for c, (m, v) in enumerate(zip(out, views, strict=True)):
        assert m is not None
        assert m[v[2]].mean() > 0.97, f"camera {c} lost the actor"

    # Unknown static depth: nothing is removed (and nothing vouches).
    unknown = [np.full_like(s, np.nan) for s in static]
    kept, none = static_consistent_masks(masks, images, rig.cameras, unknown)
    assert none == [0] * len(rig)
    assert all(np.array_equal(k, m) for k, m in zip(kept, masks, strict=True))
    # Where the other cameras see something else at the ghost's floor point, it stays.
    recoloured = [im.copy() for im in images]
    for c in range(1, len(rig)):
        recoloured[c][~views[c][2]] = 255.0 - recoloured[c][~views[c][2]]
    stays, _ = static_consistent_masks(masks, recoloured, rig.cameras, static)
    assert stays[0][ghost].mean() > 0.9
    # A camera whose own model explains the pixel as well (a white board before a white
    # wall) keeps it: the model learned the actor there, not the floor, for the ghost only.
    learned = [im.copy() for im in images]
    learned[0][ghost] = BOX_BGR  # the model holds the actor at the ghost
    gone, _ = static_consistent_masks(masks, images, rig.cameras, static, backgrounds=learned)
    assert gone[0][ghost].mean() < 0.1
    explained, n = static_consistent_masks(masks, images, rig.cameras, static, backgrounds=images)
    assert n == [0] * len(rig) and explained[0][ghost].all()
    # A checked board before a floor of its mean colour: the colours agree, the local
    # contrasts do not (caliscope_charuco's white board before a white wall), so it stays;
    # by the colours alone it would go.
    checked = [im.copy() for im in images]
    yy, xx = np.nonzero(ghost)
    checked[0][yy, xx] += np.where((yy + xx) % 2 == 0, 60.0, -60.0)[:, None]
    board, _ = static_consistent_masks(masks, checked, rig.cameras, static)
    assert board[0][ghost].mean() > 0.9
    flat, _ = static_consistent_masks(
        masks, checked, rig.cameras, static, StaticCheckConfig(texture_px=0)
    )
    assert flat[0][ghost].mean() < 0.1
    with pytest.raises(DataError, match="backgrounds"):
        static_consistent_masks(masks, images, rig.cameras, static, backgrounds=images[:2])


def _box_samples(step: float = 0.02) -> np.ndarray:
    """Points through the box's volume and on its faces (a hull that fits it)."""
    axes = [np.arange(lo + step / 2, hi, step) for lo, hi in zip(LO, HI, strict=True)]
    inner = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return np.concatenate([inner, box_surface_points(LO, HI, 60)])


def _photo_scene(rig: Rig) -> tuple[list, list, list, np.ndarray, np.ndarray, np.ndarray]:
    """Images and box masks; camera 0's mask with a ghost of floor beside the box; the hull's
    points: the box, and where the ghost's rays pass in front of the box as other cameras
    see it (what two opposite cameras' ghosts add to a hull); their labels (1 / 2)."""
    views = [_view(c) for c in rig]
    images = [v[0] for v in views]
    masks = [v[2].copy() for v in views]
    cam0 = rig[0]
    ys, xs = np.nonzero(masks[0])
    x1 = xs.max()
    ghost = np.zeros_like(masks[0])
    rows = slice(int(np.percentile(ys, 30)), int(np.percentile(ys, 70)))
    ghost[rows, x1 + 1 : x1 + 13] = True  # floor beside the box in camera 0
    masks[0] |= ghost
    gy, gx = np.nonzero(ghost)
    pix = np.stack([gx, gy], axis=1).astype(np.float64)
    _, d0 = cam0.project(0.5 * (LO + HI)[None])
    extra = []
    for depth in np.linspace(d0[0] - 0.4, d0[0] + 0.4, 41):
        pts = cam0.backproject(pix, np.full(len(pix), depth))
        for cam, mask in zip(rig.cameras[1:], masks[1:], strict=True):
            uv, d = cam.project(pts)
            ok = (d > 0) & cam.in_image(uv)
            u = np.clip(np.rint(uv[:, 0]).astype(int), 0, cam.width - 1)
            v = np.clip(np.rint(uv[:, 1]).astype(int), 0, cam.height - 1)
            ok &= mask[v, u]
            extra.append(pts[ok])
    inflated = np.concatenate(extra)
    points = np.concatenate([_box_samples(), inflated])
    labels = np.concatenate([np.ones(len(points) - len(inflated)), np.full(len(inflated), 2)])
    return images, masks, [v[2] for v in views], ghost, points, labels.astype(np.int32)


def test_the_photo_check_drops_a_ghost_that_the_hull_explains(rig: Rig) -> None:
    images, masks, boxes, ghost, points, labels = _photo_scene(rig)
    assert (labels == 2).sum() > 100  # the ghost's rays do pass in front of the box
    everywhere = [np.ones_like(m) for m in masks]  # candidates: every pixel
    # The box's pixels are not candidates anywhere: they tell how well colours agree here.
    candidates = [e & ~b for e, b in zip(everywhere, boxes, strict=True)]
    out, removed = photo_consistent_masks(points, 0.01, rig.cameras, masks, images, candidates)
    assert out[0] is not None and out[0][ghost].mean() < 0.1  # the ghost is gone
    assert removed[0] >= 0.9 * ghost.sum() and removed[1:] == [0] * (len(rig) - 1)
    # One pass: the second (the default) only ever removes more.
    once = PhotoCheckConfig(passes=1)
    one, _ = photo_consistent_masks(points, 0.01, rig.cameras, masks, images, candidates, once)
    for a, b in zip(out, one, strict=True):
        assert a is not None and b is not None and not (a & ~b).any()
    for c, (m, box) in enumerate(zip(out, boxes, strict=True)):
        assert m is not None and m[box].all(), f"camera {c} lost the box"
    # The box itself as a candidate: its colour agrees in every view, it stays. No pixel
    # outside the candidates tells how well this rig's colours agree; the median of all
    # judged pixels does (the box's agree, the ghost's do not), and the ghost goes.
    out, _ = photo_consistent_masks(points, 0.01, rig.cameras, masks, images, everywhere)
    assert all(m is not None and m[b].mean() > 0.97 for m, b in zip(out, boxes, strict=True))
    assert out[0] is not None and out[0][ghost].mean() < 0.1
    # Without that fallback, nothing is judged then.
    strict = PhotoCheckConfig(fallback_scale=0)
    out, n = photo_consistent_masks(points, 0.01, rig.cameras, masks, images, everywhere, strict)
    assert n == [0] * len(rig) and out[0] is not None and out[0][ghost].all()

    # The ghost's points as a second object: the judging cameras may see the box in front of
    # them, so they do not judge, and the ghost stays.
    kept, none = photo_consistent_masks(
        points, 0.01, rig.cameras, masks, images, candidates, labels=labels
    )
    assert kept[0] is not None and kept[0][ghost].mean() > 0.9 and none[0] < 0.1 * ghost.sum()
    # Where the other cameras show the ghost's colours on the box, it stays.
    painted = [im.copy() for im in images]
    floor = images[0][ghost].mean(axis=0)
    for im, box in zip(painted[1:], boxes[1:], strict=True):
        im[box] = floor
    stays, _ = photo_consistent_masks(points, 0.01, rig.cameras, masks, painted, candidates)
    assert stays[0] is not None and stays[0][ghost].mean() > 0.9
    # Too few reference pixels: no check.
    few = PhotoCheckConfig(min_reference_px=10**7)
    same, n = photo_consistent_masks(points, 0.01, rig.cameras, masks, images, candidates, few)
    assert n == [0] * len(rig) and all(
        np.array_equal(a, b) for a, b in zip(same, masks, strict=True)
    )


def test_the_limit_is_none_when_too_many_true_pixels_agree_nowhere() -> None:
    from edgerecon.scene.ghosts import _limit

    config = PhotoCheckConfig()
    shape = (50, 50)
    judged = [np.ones(shape, bool)]
    settled = [np.zeros(shape, bool)]  # no pixel is a candidate: all are the reference
    best = np.linspace(0, 40, shape[0] * shape[1], dtype=np.float32).reshape(shape)
    assert _limit([best], judged, settled, config) == pytest.approx(38.0, abs=0.1)
    some = best.copy()
    some.flat[:50] = np.inf  # 2 % agree with no other camera: still a limit
    limit = _limit([some], judged, settled, config)
    assert limit is not None and np.isfinite(limit)
    many = best.copy()
    many.flat[::16] = np.inf  # 6 %: the 95th percentile is not finite
    assert _limit([many], judged, settled, config) is None


def test_photo_check_bad_input(rig: Rig) -> None:
    n = len(rig)
    pts = np.zeros((4, 3))
    with pytest.raises(DataError, match="images"):
        photo_consistent_masks(pts, 0.01, rig.cameras, [None] * n, [None] * (n - 1), [None] * n)
    with pytest.raises(DataError, match="labels"):
        photo_consistent_masks(
            pts, 0.01, rig.cameras, [None] * n, [None] * n, [None] * n, labels=np.ones(3)
        )
    for bad in (
        {"blur_px": 0},
        {"max_ratio": 1.0},
        {"reference_quantile": 1.5},
        {"footprint": 0},
        {"fallback_scale": -1.0},
        {"passes": 0},
    ):
        with pytest.raises(ValueError):
            PhotoCheckConfig(**bad)  # type: ignore[arg-type]
    out, removed = photo_consistent_masks(
        np.zeros((0, 3)), 0.01, rig.cameras, [None] * n, [None] * n, [None] * n
    )
    assert out == [None] * n and removed == [0] * n


def test_bad_input(rig: Rig) -> None:
    n = len(rig)
    with pytest.raises(DataError):
        static_consistent_masks([None] * n, [None] * (n - 1), rig.cameras, [None] * n)
    for bad in ({"blur_px": 0}, {"max_ratio": 1.0}, {"depth_tol_rel": 0.0}, {"min_agree": 0}):
        with pytest.raises(ValueError):
            StaticCheckConfig(**bad)  # type: ignore[arg-type]
    StaticCheckConfig(max_chroma=0.0)  # bounds that are allowed
    out, removed = static_consistent_masks([None] * n, [None] * n, rig.cameras, [None] * n)
    assert out == [None] * n and removed == [0] * n


def test_the_static_depth_of_several_clouds_fills_each_ones_gaps(rig: Rig) -> None:
    """``set_static_clouds``: the newest cloud where it has a point, an older one where the
    newest has none (where an actor stood then)."""
    from edgerecon.scene.foreground import RigForeground

    blank = [[np.full((c.height, c.width, 3), 90, np.uint8)] for c in rig]
    fg = RigForeground.learn(rig, blank)
    g = np.linspace(-0.6, 0.6, 121)
    floor = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
    left, right = floor[floor[:, 0] < 0], floor[floor[:, 0] >= 0]
    raised = right + [0.0, 0.0, 0.05]  # the older cloud has the right half higher
    fg.set_static_clouds([np.concatenate([left, raised]), right])
    assert len(fg.static_clouds) == 2
    newest = RigForeground.learn(rig, blank)
    newest.set_static_clouds([right])
    oldest = RigForeground.learn(rig, blank)
    oldest.set_static_clouds([np.concatenate([left, raised])])
    assert fg.static_depth is not None
    assert newest.static_depth is not None and oldest.static_depth is not None
    for both, new, old in zip(
        fg.static_depth, newest.static_depth, oldest.static_depth, strict=True
    ):
        assert both is not None and new is not None and old is not None
        has_new = np.isfinite(new)
        np.testing.assert_array_equal(both[has_new], new[has_new])  # the newest wins
        only_old = ~has_new & np.isfinite(old)
        np.testing.assert_array_equal(both[only_old], old[only_old])
        assert np.isfinite(both).sum() > has_new.sum()  # the older one filled its gaps
    fg.set_static_clouds([])
    assert fg.static_depth is None and fg.static_clouds == ()


def test_the_floor_plane_fills_what_no_static_cloud_covers(rig: Rig) -> None:
    from edgerecon.dense.planes import Plane, plane_depth
    from edgerecon.scene.foreground import ForegroundConfig, RigForeground

    blank = [[np.full((c.height, c.width, 3), 90, np.uint8)] for c in rig]
    g = np.linspace(0.0, 0.6, 61)
    patch = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
    floor = Plane(normal=(0.0, 0.0, 1.0), offset=0.0, support=100, rms=0.0)
    on = RigForeground.learn(rig, blank)
    on.set_static_clouds([patch], [floor])
    off = RigForeground.learn(rig, blank, ForegroundConfig(static=StaticCheckConfig(floor=False)))
    off.set_static_clouds([patch], [floor])
    assert on.static_depth is not None and off.static_depth is not None
    for cam, d_on, d_off in zip(on.working_cameras, on.static_depth, off.static_depth, strict=True):
        assert d_on is not None and d_off is not None
        plane = plane_depth(cam, floor)
        gap = ~np.isfinite(d_off) & (plane > 0)
        assert gap.any()
        np.testing.assert_allclose(d_on[gap], plane[gap], rtol=1e-6)  # the plane filled it
        has = np.isfinite(d_off)
        np.testing.assert_array_equal(d_on[has], d_off[has])  # the cloud's own depth stays
        assert not np.isfinite(d_on[(plane <= 0) & ~has]).any()  # above the horizon: none
    with pytest.raises(DataError, match="floor planes"):
        on.set_static_clouds([patch], [floor, floor])


def test_the_floor_depth_follows_a_distorted_cameras_rays(rig: Rig) -> None:
    import dataclasses

    from edgerecon.dense.planes import Plane, plane_depth

    cam = dataclasses.replace(rig[0], dist=np.array([-0.25, 0.08, 0.001, -0.001, 0.0]))
    assert cam.has_distortion
    floor = Plane(normal=(0.0, 0.0, 1.0), offset=0.0, support=100, rms=0.0)
    depth = plane_depth(cam, floor)
    ys, xs = np.nonzero(depth > 0)
    assert len(ys) > 100
    pick = np.linspace(0, len(ys) - 1, 200).astype(int)
    px = np.stack([xs[pick], ys[pick]], axis=1).astype(np.float64)
    points = cam.backproject(px, depth[ys[pick], xs[pick]].astype(np.float64))
    np.testing.assert_allclose(points[:, 2], 0.0, atol=1e-4 * cam.center[2] + 1e-5)


def _judge_reference(c, idx, colours, contrasts, inside, alone, valid, ratios, has_ratio, cfg):
    """The photo check's per-point judgement written with NumPy arrays (what the kernel
    fuses): float32 throughout, as the check's NumPy version computed it."""
    n = len(valid)
    a = colours[c][:, idx]
    sa = a[0] + a[1] + a[2] + 1.0
    dist = np.full(len(idx), np.inf, np.float32)
    vouch = np.zeros(len(idx), bool)
    tinted = np.zeros(len(idx), bool)
    for o in range(n):
        if o == c or not valid[o]:
            continue
        both = inside[o][idx]
        b = colours[o][:, idx]
        if has_ratio[c, o]:
            b = b * ratios[c, o][:, None]
        sb = b[0] + b[1] + b[2] + 1.0
        ia, ib = 1.0 / sa, 1.0 / sb
        chroma = np.abs(a[0] * ia - b[0] * ib) + np.abs(a[1] * ia - b[1] * ib)
        chroma = chroma + np.abs(a[2] * ia - b[2] * ib)
        ratio = sa * ib
        alike = (chroma < cfg.max_chroma) & (ratio < cfg.max_ratio) & (ratio * cfg.max_ratio > 1)
        d = np.maximum(np.maximum(np.abs(a[0] - b[0]), np.abs(a[1] - b[1])), np.abs(a[2] - b[2]))
        if len(contrasts):
            x, y = contrasts[c][idx], contrasts[o][idx]
            unlike = ~(np.abs(x - y) <= np.maximum(cfg.texture_tol, 2 / 3 * np.maximum(x, y)))
            d[unlike] = np.inf
            alike &= ~unlike
        tinted |= both & alike
        vouch |= alone[o][idx]
        np.minimum(dist, np.where(both, d, np.inf), out=dist)
    return dist, vouch, tinted


@pytest.mark.parametrize("with_contrast", [True, False])
def test_the_photo_check_kernel_is_the_numpy_judgement_bit_for_bit(with_contrast: bool) -> None:
    from edgerecon.scene._kernels import judge_points
    from edgerecon.scene.ghosts import PhotoCheckConfig

    rng = np.random.default_rng(3)
    n, num = 5, 4000
    cfg = PhotoCheckConfig()
    # Colours near each other (some alike, some not), one camera without a view.
    base = rng.uniform(0, 255, (1, 3, num)).astype(np.float32)
    colours = (base * rng.uniform(0.8, 1.25, (n, 1, 1)) + rng.normal(0, 6, (n, 3, num))).astype(
        np.float32
    )
    contrasts = rng.uniform(0, 30, (n if with_contrast else 0, num)).astype(np.float32)
    inside = rng.random((n, num)) < 0.8
    alone = inside & (rng.random((n, num)) < 0.9)
    valid = np.array([True, True, False, True, True])
    ratios = rng.uniform(0.8, 1.25, (n, n, 3)).astype(np.float32)
    has_ratio = rng.random((n, n)) < 0.7
    for c in (0, 3):
        idx = np.flatnonzero(inside[c]).astype(np.intp)
        dist = np.full(len(idx), np.inf, np.float32)
        vouch = np.zeros(len(idx), bool)
        tinted = np.zeros(len(idx), bool)
        judge_points(
            c, idx, colours, contrasts, with_contrast, inside, alone, valid, ratios, has_ratio,
            np.float32(cfg.max_chroma), np.float32(cfg.max_ratio), np.float32(cfg.texture_tol),
            dist, vouch, tinted,
        )  # fmt: skip
        ref = _judge_reference(
            c, idx, colours, contrasts, inside, alone, valid, ratios, has_ratio, cfg
        )
        np.testing.assert_array_equal(dist, ref[0])
        np.testing.assert_array_equal(vouch, ref[1])
        np.testing.assert_array_equal(tinted, ref[2])
        # Every outcome occurs (the test is not vacuous).
        assert np.isinf(dist).any() and np.isfinite(dist).any()
        assert tinted.any() and not tinted.all() and vouch.any() and not vouch.all()


def test_the_splat_kernels_draw_opencv_s_discs_pixel_for_pixel() -> None:
    """``splat_discs`` / ``splat_min_discs`` (one pass over the points) give what one
    ``cv2.dilate`` / ``cv2.erode`` per radius with the elliptic element gives, points at the
    image's edges and in a box included."""
    import cv2

    from edgerecon.scene._kernels import (
        MAX_KERNEL_DISC,
        disc_half_widths,
        splat_discs,
        splat_min_discs,
    )

    rng = np.random.default_rng(11)
    h, w, num = 90, 130, 600
    u = rng.integers(0, w, num).astype(np.int64)
    v = rng.integers(0, h, num).astype(np.int64)
    u[:20], v[20:40] = 0, h - 1  # on the edges
    r = rng.integers(0, MAX_KERNEL_DISC + 1, num).astype(np.int64)
    values = rng.uniform(0, 100, num).astype(np.float32)
    table = disc_half_widths()
    got = np.zeros((h, w), np.uint8)
    box = (17, 9, 101, 77)
    splat_discs(got, u, v, r, table, *box)
    got_min = np.full((h, w), np.inf, np.float32)
    splat_min_discs(got_min, u, v, r, values, table)
    want = np.zeros((h, w), np.uint8)
    want_min = np.full((h, w), np.inf, np.float32)
    for rr in np.unique(r):
        sel = r == rr
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(rr) + 1,) * 2)
        layer = np.zeros((h, w), np.uint8)
        layer[v[sel], u[sel]] = 1
        want |= cv2.dilate(layer, disc)
        layer_min = np.full((h, w), 1e30, np.float32)
        np.minimum.at(layer_min, (v[sel], u[sel]), values[sel])
        np.minimum(want_min, cv2.erode(layer_min, disc), out=want_min)
    want_min[want_min >= 1e30] = np.inf
    x0, y0, x1, y1 = box
    inside = np.zeros((h, w), bool)
    inside[y0:y1, x0:x1] = True
    np.testing.assert_array_equal(got.view(bool), want.view(bool) & inside)
    np.testing.assert_array_equal(got_min, want_min)
    assert 0.2 < inside[want > 0].mean() < 1  # the box cut some discs
