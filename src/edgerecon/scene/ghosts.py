"""Ghosts told from the static scene that other cameras see uncovered.

Without an empty-scene clip a background model learns an actor who stood in its view while it
learned. Once the actor has moved on, the camera shows the floor or wall that the model never
saw, and calls it foreground: a *ghost*. Two opposite cameras see such a ghost where the two
others see the actor along the same lines, so the visual hull cannot carve it (hd4 preset:
the false foreground left after the hull, moving-actor precision 0.77).

A ghost pixel shows the static scene; a pixel of an actor does not. With a depth map of the
static scene per camera (a background cloud rendered into each working camera,
``RigForeground.set_static_clouds``; :mod:`edgerecon.scene.stream` builds one from the stream
every ``StaticCheckConfig.every_s``), each foreground pixel's static point is projected into
the other cameras. Where another camera sees that point itself (its own static depth agrees)
and has no foreground there now, its colour there is what the point looks like; the pixel is
called background when more such cameras agree with its colour than disagree. An actor's
pixel is only called background where the actor has the colour of what stands behind it in
several views.

hd4 (t = 60 and 120, the back-end's background of that time): 37-41 % of the ghost pixels of
the two opposite cameras are found, 1-2 % of the actors' pixels (docs/BENCHMARKS.md).

A second test needs no static scene, only the frames of the moment and the visual hull
(``photo_consistent_masks``, on by default). A ghost pixel's ray meets the hull only where
the hull is inflated by the ghosts themselves; the surface that pixel shows (a wall, the
floor) lies behind the hull. So no point of the hull on its ray looks, in another camera
that has that point inside its mask, like what the pixel shows: that camera sees the actor
in front of or behind the inflated part. An actor's pixel shows a point of the actor, inside
the hull, which some other camera sees in its colour. Points spread through the hull's
voxels are compared across the cameras whose masks hold them; a candidate pixel (one that
moved while its model learned) whose points other cameras judge, none of them in its
colour, is a ghost. How close "in its colour" is comes from the rig itself: the colour
distance that 95 % of the surely-true foreground pixels (outside the candidates) reach, at
least ``max_diff``. Synthetic cameras agree to a few grey levels, real webcams with their own
white balance and gamma to 20-50 (caliscope_charuco), and the test loosens with them.

The check runs twice (``passes``): the points that land on pixels the first pass removed
are carved before the second, as the hull of the new masks would carve them. Where no pixel
outside the candidates tells the rig's colour agreement (the first second of a stream, when
every actor still stands where the models learned), the limit comes from all judged pixels
(``fallback_scale``).

hd4 (20 tasks): moving-actor IoU 0.727 -> 0.814, precision 0.769 -> 0.869, recall of the
two moving actors 0.938 / 0.944 -> 0.930 / 0.938; hd4p 0.695 -> 0.761 (docs/BENCHMARKS.md).
What it cannot remove: ghost pixels whose ray meets, by chance, a hull point that another
camera sees in a colour within the limit (about half of what is left on hd4 at t = 228),
and ghosts that no camera judges (no other camera's mask holds their hull points).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera
from edgerecon.quality.frames import local_contrast
from edgerecon.scene._kernels import (
    DISC_HALF_WIDTHS,
    MAX_KERNEL_DISC,
    disc_centres,
    gather_channels,
    judge_points,
    splat_discs,
    splat_min_discs,
)
from edgerecon.scene.masks import disk
from edgerecon.threads import thread_map
from edgerecon.types import DataError, DepthMap, Mask, Points3D


@dataclass(frozen=True, kw_only=True)
class StaticCheckConfig:
    """Parameters of ``static_consistent_masks``."""

    depth_tol_rel: float = 0.02
    """Another camera sees the static point itself when its own static depth there is within
    this share of the point's depth."""
    max_diff: float = 15.0
    """Two colours agree when their channels differ by less than this (grey levels) ..."""
    max_chroma: float = 0.08
    """... or their chromaticities (B, G, R over their sum) differ by less than this (L1) ..."""
    max_ratio: float = 1.6
    """... with brightnesses within this ratio (the cameras' exposures differ)."""
    blur_px: int = 3
    """Colours are compared as box means of this size (pixels of the working images)."""
    min_agree: int = 1
    """Cameras that must agree (and outnumber those that disagree) to call a pixel background."""
    texture_px: int = 5
    """Two cameras also agree only where their local contrast (grey standard deviation in a
    window of this size) is alike: a checked board before a white wall has the wall's mean
    colour, not its flatness (caliscope_charuco t = 100, one camera's removed pixels, most of
    them the person and the board: 6,879 -> 2,042; hd4 moving IoU 0.786 -> 0.770). 0 = colours
    alone."""
    texture_tol: float = 10.0
    """Local contrasts are alike when they differ by at most this (grey levels) or by a factor
    of at most 3."""
    every_s: float = 2.0
    """Stream time between two static scenes (``scene.stream``): the frame set on the models'
    update schedule every this many seconds, outside its model masks, reconstructed at the
    working resolution (0.5-0.8 s on hd4's 4 x 480x270)."""
    keep: int = 3
    """How many of the latest static scenes make the static depth (the newest where it has a
    point, else the next): more cover what an actor hid in one of them."""
    floor: bool = True
    """Where no static cloud has a point, the ground plane the latest static scene found
    (``dense.planes``), where the pixel's ray meets it: the floor under a ghost that no
    camera saw uncovered while a cloud was built (hd4: moving IoU 0.774 -> 0.80)."""

    def __post_init__(self) -> None:
        # (name, smallest allowed value, whether the bound itself is allowed)
        for name, low, inclusive in (
            ("depth_tol_rel", 0.0, False),
            ("max_diff", 0.0, False),
            ("max_chroma", 0.0, True),
            ("max_ratio", 1.0, False),
            ("blur_px", 1, True),
            ("min_agree", 1, True),
            ("texture_px", 0, True),
            ("texture_tol", 0.0, True),
            ("every_s", 0.0, False),
            ("keep", 1, True),
        ):
            value = getattr(self, name)
            if not (value >= low if inclusive else value > low):
                sign = ">=" if inclusive else ">"
                raise ValueError(f"StaticCheckConfig.{name} must be {sign} {low}, got {value}")


@dataclass(frozen=True, kw_only=True)
class PhotoCheckConfig:
    """Parameters of ``photo_consistent_masks``."""

    max_diff: float = 10.0
    """The smallest colour tolerance: two colours agree when their channels differ by at
    most the rig's limit (``reference_quantile``), never less than this (grey levels) ..."""
    max_chroma: float = 0.03
    """... or when their chromaticities (B, G, R over their sum) differ by less than this
    (L1) ..."""
    max_ratio: float = 1.6
    """... with brightnesses within this ratio (one surface at two exposures)."""
    blur_px: int = 3
    """Colours are compared as box means of this size (pixels of the working images)."""
    texture_px: int = 5
    """Local contrasts (grey standard deviation in a window of this size) must be alike too,
    as in ``StaticCheckConfig.texture_px``; 0 = colours alone."""
    texture_tol: float = 10.0
    """Local contrasts are alike within this (grey levels) or a factor of 3."""
    calibrate: bool = True
    """Before comparing two cameras, bring the second's colours to the first's: per channel,
    the median ratio over the points both see with channels within ``calibration_diff``
    (the cameras' exposure and white balance differ; hd4, 4 tasks: moving IoU 0.775 ->
    0.783)."""
    calibration_diff: float = 30.0
    """Largest channel difference of the point pairs that estimate the ratio."""
    min_calibration_points: int = 50
    """Fewer such pairs: no calibration between those two cameras."""
    footprint: float = 0.7
    """A point vouches for the pixels within this share of its voxel's projected edge."""
    reference_quantile: float = 0.95
    """The colour distance that true foreground reaches on this rig: this quantile of the
    best distances of the mask pixels outside the candidates (the models saw the background
    there), over all cameras. A candidate pixel is a ghost when its best distance exceeds
    it (and ``max_diff``): cameras whose colours agree less (real webcams with their own
    white balance and gamma) get a looser test."""
    min_reference_px: int = 500
    """Fewer such pixels (the first second of a stream without an empty clip, when every
    actor stands where the models learned: all their pixels are candidates): the limit is
    ``fallback_scale`` times the median best distance of all judged pixels instead."""
    passes: int = 2
    """Checks in a row: before each after the first, the points that project onto pixels
    the last one removed are carved (as the hull of the new masks would), so the phantom
    volume that two cameras' ghosts leave in the hull vouches no more (hd4 / hd4p, 20
    tasks: moving IoU 0.809 / 0.754 with one, 0.814 / 0.761 with two; hd4 0.816 with
    three)."""
    fallback_scale: float = 4.0
    """That multiple: the 95th percentile of the true foreground's best distance is 3-6
    times its median on hd4, caliscope_charuco and utrecht4cam, and the median of all judged
    pixels, ghosts included, is at least the true foreground's where ghosts are fewer than
    half of them (hd4, t = 0 / 12 / 24: moving IoU 0.750 / 0.716 / 0.709 -> 0.790 / 0.732 /
    0.765). 0 = no check then."""
    max_points: int = 150_000
    """The hull's samples: four points per voxel of the tolerant hull while that keeps
    within this many, else each voxel's centre alone (a hull 2 m from the cameras that
    holds a whole seated person, caliscope_charuco with the person model: 116,000 voxels,
    464,000 points, 0.39 s of the check per task on this machine; the presets' hulls hold a
    few thousand)."""

    def __post_init__(self) -> None:
        for name, low, inclusive in (
            ("max_diff", 0.0, False),
            ("max_chroma", 0.0, True),
            ("max_ratio", 1.0, False),
            ("blur_px", 1, True),
            ("texture_px", 0, True),
            ("texture_tol", 0.0, True),
            ("calibration_diff", 0.0, False),
            ("min_calibration_points", 1, True),
            ("footprint", 0.0, False),
            ("reference_quantile", 0.0, True),
            ("min_reference_px", 1, True),
            ("fallback_scale", 0.0, True),
            ("passes", 1, True),
            ("max_points", 1, True),
        ):
            value = getattr(self, name)
            if not (value >= low if inclusive else value > low):
                sign = ">=" if inclusive else ">"
                raise ValueError(f"PhotoCheckConfig.{name} must be {sign} {low}, got {value}")
        if self.reference_quantile > 1.0:
            raise ValueError(
                f"PhotoCheckConfig.reference_quantile must be <= 1, got {self.reference_quantile}"
            )


def photo_consistent_masks(
    points: Points3D,
    sizes: NDArray[np.floating] | float,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    images: Sequence[NDArray[np.floating] | NDArray[np.uint8] | None],
    candidates: Sequence[Mask | None],
    config: PhotoCheckConfig | None = None,
    *,
    labels: NDArray[np.integer] | None = None,
    num_threads: int = 1,
) -> tuple[list[Mask | None], list[int]]:
    """The masks without their candidate pixels that no point of the hull explains, and per
    camera how many pixels were removed (see the module docstring). The cameras' work runs
    on ``num_threads`` threads (the same masks).

    ``points`` (N, 3) are samples of the hull and ``sizes`` (N,) their spacing (or one
    number for all). A point is compared between two cameras when it lies in both images
    and inside both masks (after a per-pair colour ratio, ``calibrate``); a pixel's best
    distance is the smallest colour difference over the points within its footprint and
    the other cameras. The limit is the ``reference_quantile`` of the best distances of the
    mask pixels outside ``candidates`` (at least ``max_diff``); with fewer than
    ``min_reference_px`` such pixels, ``fallback_scale`` times the median over all judged
    pixels (nothing is removed when fewer than that many are judged). A pixel of
    ``candidates[c]`` (the models' unsettled pixels: where a model may hold a ghost) inside
    ``masks[c]`` is removed when points were compared within its footprint, its best distance
    exceeds the limit and no point there has its tint at another brightness. Pixels that no
    compared point covers are kept (nothing vouches against them). All images are per camera
    at the masks' resolution (``cameras``), BGR at each model's exposure; a camera without a
    mask or an image neither loses pixels nor vouches for others.

    With ``passes`` > 1 the check runs again: the points that land on removed pixels are
    carved, the colour ratios are estimated anew from the points left, and the first pass's
    limit judges again the candidates still in the masks that a carved point covered.

    ``labels`` (N,): the 3D object of each point. A camera then only judges a point where no
    other object's points project within a pixel: there it may see the other object in
    front of it (an actor passing behind another in one view lost half its pixels without
    this, hd4p t = 132).
    """
    config = config or PhotoCheckConfig()
    n = len(cameras)
    for name, seq in (("masks", masks), ("images", images), ("candidates", candidates)):
        if len(seq) != n:
            raise DataError(f"photo check: {len(seq)} {name} for {n} cameras")
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    size = np.broadcast_to(np.asarray(sizes, np.float64), (len(pts),))
    if labels is not None and len(labels) != len(pts):
        raise DataError(f"photo check: {len(labels)} labels for {len(pts)} points")
    out = [None if m is None else np.asarray(m, bool) for m in masks]
    removed = [0] * n
    if len(pts) == 0:
        return out, removed
    # What does not change between passes: where each point lands and its colour there.
    k = config.blur_px

    def sees(c: int) -> _Seen | None:
        cam, mask, im = cameras[c], out[c], images[c]
        if mask is None or im is None:
            return None
        colour = np.asarray(cv2.blur(np.asarray(im, np.float32), (k, k)), np.float32)
        uv, depth, u, v, inside = cam.nearest_pixels(pts)
        contrast = local_contrast(im, config.texture_px)[v, u] if config.texture_px else None
        # Channel-first: the per-point tests are sums over three rows, not reductions over a
        # trailing axis of 3 (10x faster).
        colours = gather_channels(colour, u, v)
        return _Seen(uv, depth, u, v, inside, colours, contrast)

    seen = thread_map(sees, list(range(n)), num_threads)
    stack = _Stack.of(seen, len(pts))
    limit: float | None = None
    keep = np.ones(len(pts), bool)
    previous = out
    carved: NDArray[np.bool_] | None = None
    for step in range(config.passes):
        if step:
            # Carve the points that land on a pixel the last pass removed: the hull of the
            # new masks has no point there, and such points (the phantom volume that two
            # cameras' ghosts leave in the hull) vouch no more for the pixels left.
            before_keep = keep.copy()
            for sc, before, after in zip(seen, previous, out, strict=True):
                if sc is not None and before is not None and after is not None:
                    keep &= ~(sc.inside & before[sc.v, sc.u] & ~after[sc.v, sc.u])
            carved = before_keep & ~keep
            if not carved.any():
                break
        previous = list(out)
        out, gone, limit = _photo_pass(
            seen,
            stack,
            keep,
            size,
            labels,
            cameras,
            out,
            candidates,
            config,
            limit,
            carved,
            num_threads,
        )
        removed = [a + b for a, b in zip(removed, gone, strict=True)]
        if limit is None or not any(gone):
            break
    return out, removed


#: One camera's pass of the photo check: best colour distance per pixel, the pixels judged,
#: those with a point of the same tint and (later passes) those judged again.
_Judgement = tuple[NDArray[np.float32] | None, Mask | None, Mask | None, Mask | None]


def _photo_pass(
    seen: list[_Seen | None],
    stack: _Stack,
    keep: NDArray[np.bool_],
    size: NDArray[np.float64],
    labels: NDArray[np.integer] | None,
    cameras: Sequence[Camera],
    masks: list[Mask | None],
    candidates: Sequence[Mask | None],
    config: PhotoCheckConfig,
    limit: float | None,
    carved: NDArray[np.bool_] | None = None,
    num_threads: int = 1,
) -> tuple[list[Mask | None], list[int], float | None]:
    """One pass of ``photo_consistent_masks`` over the ``keep`` points: the masks, the
    pixels removed per camera and the colour limit (None: too few pixels to set it,
    nothing removed). The later passes (``carved``: the points carved since the last one)
    take the first one's ``limit`` and judge again only the candidates still in the masks
    that a carved point covered (the others' points did not change); the colour ratios are
    estimated again from the points left (the carved ones skewed them: hd4, 20 tasks,
    moving IoU 0.811 with the first pass's ratios, 0.815 with new ones). The cameras run on
    ``num_threads`` threads; the ratios of every pair come first, each from the lower
    camera's side, so that the masks do not depend on the threads' order."""
    ratios: dict[tuple[int, int], NDArray[np.float32] | None] = {}
    n = len(cameras)
    out = list(masks)
    removed = [0] * n
    first = limit is None
    views: list[_View | None] = []
    for sc, mask in zip(seen, out, strict=True):
        if sc is None or mask is None:
            views.append(None)
            continue
        inside = sc.inside & keep & mask[sc.v, sc.u]
        alone = (
            inside if labels is None else inside & _alone(labels, inside, sc.u, sc.v, mask.shape)
        )
        views.append(_View(sc, inside, alone))
    # Per camera: the best colour distance to another camera over the points within each
    # pixel's footprint (inf: none), and the pixels some camera judges.
    best: list[NDArray[np.float32] | None] = [None] * n
    judged: list[Mask | None] = [None] * n
    tint: list[Mask | None] = [None] * n  # a point in the same tint (another exposure)
    opened: list[Mask | None] = [None] * n  # later passes: the pixels judged again
    if config.calibrate:
        for c in range(n):
            for o in range(c + 1, n):
                here, there = views[c], views[o]
                if here is not None and there is not None:
                    ratio = _colour_ratio(here, there, config)
                    ratios[c, o] = ratio
                    ratios[o, c] = None if ratio is None else 1.0 / ratio

    # The kernel's inputs: every camera's views stacked (a camera without one: not valid).
    valid = np.array([v is not None for v in views], bool)
    inside_all = np.zeros((n, len(keep)), bool)
    alone_all = np.zeros((n, len(keep)), bool)
    ratio_all = np.ones((n, n, 3), np.float32)
    has_ratio = np.zeros((n, n), bool)
    for c, view in enumerate(views):
        if view is not None:
            inside_all[c] = view.inside
            alone_all[c] = view.alone
    for (c, o), ratio in ratios.items():
        if ratio is not None:
            ratio_all[c, o] = ratio
            has_ratio[c, o] = True

    def judge(c: int) -> _Judgement:
        cam = cameras[c]
        here, mask, cand = views[c], out[c], candidates[c]
        if here is None or mask is None or not mask.any():
            return None, None, None, None
        opened_c: Mask | None = None
        (idx,) = np.nonzero(here.inside)
        radius = config.footprint * size[idx] * cam.focal_px / np.maximum(here.at.depth[idx], 1e-9)
        if not first and len(idx):
            # Only the candidates left can go, and only where a carved point vouched: the
            # points whose footprint reaches such a pixel.
            sc = seen[c]
            assert sc is not None and carved is not None
            (gone_idx,) = np.nonzero(sc.inside & carved)
            if cand is None or len(gone_idx) == 0:
                return None, None, None, None
            gone_r = config.footprint * size[gone_idx] * cam.focal_px
            gone_r = gone_r / np.maximum(sc.depth[gone_idx], 1e-9)
            open_ = mask & np.asarray(cand, bool) & _splat(mask.shape, sc.uv[gone_idx], gone_r)
            if not open_.any():
                return None, None, None, None
            opened_c = open_
            reach = int(np.clip(np.ceil(radius.max()), 0, _MAX_FOOTPRINT_PX))
            near = cv2.dilate(open_.view(np.uint8), disk(reach)).view(bool)
            on = near[sc.v[idx], sc.u[idx]]
            idx, radius = idx[on], radius[on]
        if len(idx) == 0:
            return None, None, None, opened_c
        # Per point, against every other camera that holds it (its colours brought to this
        # camera's by the pair's ratio, from every point both hold): the smallest largest-
        # channel difference (inf where the local contrasts differ), whether one holds it
        # in this tint at another brightness, and whether one vouches for it (any camera
        # may; one that may see another object in front of it does not judge it).
        vouch = np.zeros(len(idx), bool)
        dist = np.full(len(idx), np.inf, np.float32)
        tinted = np.zeros(len(idx), bool)
        judge_points(
            c,
            idx,
            stack.colours,
            stack.contrasts,
            stack.contrasts.shape[0] > 0,
            inside_all,
            alone_all,
            valid,
            ratio_all,
            has_ratio,
            np.float32(config.max_chroma),
            np.float32(config.max_ratio),
            np.float32(config.texture_tol),
            dist,
            vouch,
            tinted,
        )
        if not vouch.any():
            return None, None, None, opened_c
        uv = here.at.uv[idx]
        return (
            _splat_min(mask.shape, uv, radius, dist),
            _splat(mask.shape, uv[vouch], radius[vouch]) & mask,
            _splat(mask.shape, uv[tinted], radius[tinted]),
            opened_c,
        )

    for c, judgement in enumerate(thread_map(judge, list(range(n)), num_threads)):
        best[c], judged[c], tint[c], opened[c] = judgement
    if limit is None:
        limit = _limit(best, judged, candidates, config)
        if limit is None:
            return out, removed, None
    for c in range(n):
        mask, bc, jc, tc, cand = out[c], best[c], judged[c], tint[c], candidates[c]
        if mask is None or bc is None or jc is None or tc is None or cand is None:
            continue
        ghost = mask & np.asarray(cand, bool) & jc & (bc > limit) & ~tc
        if not first:
            ghost &= opened[c] if opened[c] is not None else False
        if ghost.any():
            out[c] = mask & ~ghost
            removed[c] = int(np.count_nonzero(ghost))
    return out, removed, limit


def _limit(
    best: list[NDArray[np.float32] | None],
    judged: list[Mask | None],
    candidates: Sequence[Mask | None],
    config: PhotoCheckConfig,
) -> float | None:
    """The colour distance beyond which a candidate is a ghost (``reference_quantile``,
    ``fallback_scale``); None when too few pixels were judged to tell."""
    # How well true foreground agrees on this rig: the pixels outside the candidates (the
    # models saw the background there, so they are foreground), pooled over the cameras.
    reference = [
        bc[jc & ~np.asarray(cand, bool)]
        for bc, jc, cand in zip(best, judged, candidates, strict=True)
        if bc is not None and jc is not None and cand is not None
    ]
    pooled = np.concatenate(reference) if reference else np.zeros(0, np.float32)
    if len(pooled) >= config.min_reference_px:
        with np.errstate(invalid="ignore"):  # inf - inf between two infinite samples
            q = float(np.quantile(pooled, config.reference_quantile))
        if not np.isfinite(q):
            # More of the surely-true pixels than the quantile leaves out agree with no
            # other camera at all (inf: every comparison unlike in texture): these colours
            # cannot tell a ghost from an actor (caliscope_charuco t = 48: 5.3 %; the limit
            # had fallen to max_diff there, through a NaN).
            return None
        return max(config.max_diff, q)
    # Too few surely-true pixels: a robust scale of all judged pixels' distances.
    every = [
        bc[jc] for bc, jc in zip(best, judged, strict=True) if bc is not None and jc is not None
    ]
    pooled = np.concatenate(every) if every else np.zeros(0, np.float32)
    pooled = pooled[np.isfinite(pooled)]
    if config.fallback_scale <= 0 or len(pooled) < config.min_reference_px:
        return None
    return max(config.max_diff, config.fallback_scale * float(np.median(pooled)))


#: At most about this many points (evenly spaced) estimate a colour ratio.
_CALIBRATION_SAMPLES = 20_000


def _colour_ratio(
    here: _View, there: _View, config: PhotoCheckConfig
) -> NDArray[np.float32] | None:
    """Per channel, the median ratio of ``here``'s colours to ``there``'s over the points
    both hold with channels within ``calibration_diff``; None with too few such points."""
    (both,) = np.nonzero(here.inside & there.inside)
    both = both[:: max(1, len(both) // _CALIBRATION_SAMPLES)]
    # Channel-first (3, k): the largest channel difference and the medians per row, not
    # reductions over a trailing axis of 3 (the same numbers, 4x faster).
    a, b = here.at.colour[:, both], there.at.colour[:, both]
    diff = np.abs(a - b)
    pair = np.maximum(np.maximum(diff[0], diff[1]), diff[2]) < config.calibration_diff
    if np.count_nonzero(pair) < config.min_calibration_points:
        return None
    return np.median((a[:, pair] + 1.0) / (b[:, pair] + 1.0), axis=1).astype(np.float32)


@dataclass(frozen=True, eq=False)
class _Seen:
    """The hull's points in one camera: projections, nearest pixels, colours there."""

    uv: NDArray[np.float64]
    depth: NDArray[np.float64]
    u: NDArray[np.intp]
    v: NDArray[np.intp]
    inside: NDArray[np.bool_]
    """In the image, in front of the camera."""
    colour: NDArray[np.float32]
    """(3, N) BGR."""
    contrast: NDArray[np.float32] | None


@dataclass(frozen=True, eq=False)
class _Stack:
    """Every camera's ``_Seen`` colours and contrasts stacked for the kernel (zeros for a
    camera without a view)."""

    colours: NDArray[np.float32]
    """(n, 3, N) BGR."""
    contrasts: NDArray[np.float32]
    """(n, N) local contrasts; (0, N) without the contrast test."""

    @classmethod
    def of(cls, seen: list[_Seen | None], num_points: int) -> _Stack:
        n = len(seen)
        colours = np.zeros((n, 3, num_points), np.float32)
        with_contrast = any(sc is not None and sc.contrast is not None for sc in seen)
        contrasts = np.zeros((n if with_contrast else 0, num_points), np.float32)
        for c, sc in enumerate(seen):
            if sc is not None:
                colours[c] = sc.colour
                if with_contrast and sc.contrast is not None:
                    contrasts[c] = sc.contrast
        return cls(colours, contrasts)


@dataclass(frozen=True, eq=False)
class _View:
    """The hull's points as one camera sees them in one pass."""

    at: _Seen
    inside: NDArray[np.bool_]
    """In the image and inside the camera's mask (points carved by an earlier pass: out)."""
    alone: NDArray[np.bool_]
    """Inside, and no other object's point within a pixel."""


def _alone(
    labels: NDArray[np.integer],
    inside: NDArray[np.bool_],
    u: NDArray[np.intp],
    v: NDArray[np.intp],
    shape: tuple[int, ...],
) -> NDArray[np.bool_]:
    """Points whose pixel (u, v), give or take one, holds no other object's point."""
    ids = np.unique(labels[inside])
    if len(ids) < 2:
        return np.ones(len(labels), bool)
    count = np.zeros(shape[:2], np.uint8)
    k3 = np.ones((3, 3), np.uint8)
    for k in ids:
        sel = inside & (labels == k)
        layer = np.zeros(shape[:2], np.uint8)
        layer[v[sel], u[sel]] = 1
        count += np.asarray(cv2.dilate(layer, k3), np.uint8)
    return np.asarray(count[v, u] <= 1)


#: A point's footprint never reaches farther than this (pixels).
_MAX_FOOTPRINT_PX = MAX_KERNEL_DISC


def _splat_min(
    shape: tuple[int, ...],
    uv: NDArray[np.float64],
    radius: NDArray[np.float64],
    values: NDArray[np.float32],
) -> NDArray[np.float32]:
    """(H, W) smallest of ``values`` over the points within ``radius`` (rounded up) of each
    pixel; inf where none."""
    h, w = shape[:2]
    out = np.full((h, w), np.inf, np.float32)
    if len(uv) == 0:
        return out
    u, v, r = disc_centres(uv, radius, w, h, _MAX_FOOTPRINT_PX)
    vals = np.minimum(np.asarray(values, np.float32), np.float32(_BIG))
    splat_min_discs(out, u, v, r, vals, DISC_HALF_WIDTHS)
    out[out >= _BIG] = np.inf
    return out


#: Stands for "no point" in the min filters (OpenCV's filters do not keep infinities).
_BIG = 1e30


def _splat(shape: tuple[int, ...], uv: NDArray[np.float64], radius: NDArray[np.float64]) -> Mask:
    """(H, W) pixels within ``radius`` (rounded up, per point) of the points ``uv``."""
    h, w = shape[:2]
    out = np.zeros((h, w), np.uint8)
    if len(uv) == 0:
        return out.astype(bool)
    u, v, r = disc_centres(uv, radius, w, h, _MAX_FOOTPRINT_PX)
    splat_discs(out, u, v, r, DISC_HALF_WIDTHS, 0, 0, w, h)
    return out.view(bool)


def static_consistent_masks(
    masks: Sequence[Mask | None],
    images: Sequence[NDArray[np.floating] | NDArray[np.uint8] | None],
    cameras: Sequence[Camera],
    static_depth: Sequence[DepthMap | None],
    config: StaticCheckConfig | None = None,
    backgrounds: Sequence[NDArray[np.floating] | NDArray[np.uint8] | None] | None = None,
) -> tuple[list[Mask | None], list[int]]:
    """The masks without the pixels that show the static scene, and per camera how many
    pixels were removed.

    ``backgrounds`` (the models' background images at this resolution): a pixel whose colour
    agrees with its own model's background is never removed. A ghost is where the model is
    wrong (it disagrees with the pixel); where the model agrees too, the pixel is foreground by
    a weaker cue (texture, the hull's fill) and other cameras' agreement tells nothing (a
    white board before a white wall, caliscope_charuco).

    All inputs are per camera at one resolution (``cameras``): ``images`` BGR (any dtype),
    ``static_depth`` the static scene's depth along the optical axis (NaN or <= 0 where it
    is unknown: such pixels are never removed). A camera without an image, a mask or a
    static depth neither loses pixels nor vouches for others.
    """
    config = config or StaticCheckConfig()
    n = len(cameras)
    named = [("masks", masks), ("images", images), ("static depths", static_depth)]
    if backgrounds is not None:
        named.append(("backgrounds", backgrounds))
    for name, seq in named:
        if len(seq) != n:
            raise DataError(f"static check: {len(seq)} {name} for {n} cameras")
    out = [None if m is None else np.asarray(m, bool) for m in masks]
    removed = [0] * n
    k = config.blur_px
    means: list[NDArray[np.float32] | None] = [
        None if im is None else np.asarray(cv2.blur(np.asarray(im, np.float32), (k, k)), np.float32)
        for im in images
    ]
    contrasts = [
        None if im is None or not config.texture_px else local_contrast(im, config.texture_px)
        for im in images
    ]
    depths = [
        None
        if d is None
        else np.where(np.isfinite(d) & (np.asarray(d) > 0), d, np.nan).astype(np.float32)
        for d in static_depth
    ]
    for c, cam in enumerate(cameras):
        mask, colour, depth = out[c], means[c], depths[c]
        if mask is None or colour is None or depth is None:
            continue
        ys, xs = np.nonzero(mask & np.isfinite(depth))
        if len(ys) == 0:
            continue
        points = cam.backproject(
            np.stack([xs, ys], axis=1).astype(np.float64), depth[ys, xs].astype(np.float64)
        )
        here = colour[ys, xs]
        agree = np.zeros(len(ys), np.int32)
        disagree = np.zeros(len(ys), np.int32)
        for o, other in enumerate(cameras):
            o_mask, o_colour, o_depth = masks[o], means[o], depths[o]
            if o == c or o_mask is None or o_colour is None or o_depth is None:
                continue
            _, d, u, v, seen = other.nearest_pixels(points)
            with np.errstate(invalid="ignore"):
                seen &= np.abs(o_depth[v, u] - d) < config.depth_tol_rel * d
            seen &= ~np.asarray(o_mask, bool)[v, u]
            same = _same_colour(here, o_colour[v, u], config)
            mine, theirs = contrasts[c], contrasts[o]
            if mine is not None and theirs is not None:
                same &= _contrast_alike(mine[ys, xs], theirs[v, u], config.texture_tol)
            agree += seen & same
            disagree += seen & ~same
        static = (agree >= config.min_agree) & (agree > disagree)
        own = None if backgrounds is None else backgrounds[c]
        if own is not None and static.any():
            own_mean = np.asarray(cv2.blur(np.asarray(own, np.float32), (k, k)), np.float32)
            static &= ~_same_colour(here, own_mean[ys, xs], config)
        if static.any():
            mask = mask.copy()
            mask[ys[static], xs[static]] = False
            out[c] = mask
            removed[c] = int(static.sum())
    return out, removed


def _contrast_alike(
    a: NDArray[np.float32], b: NDArray[np.float32], tol: float
) -> NDArray[np.bool_]:
    """Local contrasts alike: within ``tol`` grey levels, or within a factor 3 (contrast
    scales with the surface's footprint, which differs between views)."""
    return np.asarray(np.abs(a - b) <= np.maximum(tol, 2 / 3 * np.maximum(a, b)))


def _same_colour(
    a: NDArray[np.float32], b: NDArray[np.float32], config: StaticCheckConfig
) -> NDArray[np.bool_]:
    sa = a.sum(axis=1) + 1.0
    sb = b.sum(axis=1) + 1.0
    chroma = np.abs(a / sa[:, None] - b / sb[:, None]).sum(axis=1)
    ratio = np.maximum(sa / sb, sb / sa)
    close = np.abs(a - b).max(axis=1) < config.max_diff
    return np.asarray(close | ((chroma < config.max_chroma) & (ratio < config.max_ratio)))
