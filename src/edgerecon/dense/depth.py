"""Per-view depth maps: a coarse multi-view plane sweep, refined coarse-to-fine.

For one reference view and a few source views:

1. **Plane sweep** at the coarsest level. Each plane of a family (``fronto``: parallel to the
   reference image; ``ground``: perpendicular to the scene's up direction) maps every source
   onto the reference by a homography; the windowed NCC of each source is aggregated over
   the best ``ncc_top_k`` sources, each counted as at least the best one's minus
   ``ncc_top_gap`` (:mod:`edgerecon.dense.kernels`). Planes are spaced so that
   consecutive planes move the image of every sampled ray by at most ``plane_step_px``
   coarse pixels in every source, which adapts the number of planes to the baselines and to
   the depth range. Winner-take-all with a parabola through the neighbouring planes gives
   sub-plane precision. The "ground" family makes windows on floors match across wide
   baselines, where fronto-parallel windows are sheared beyond recognition (on a 5-camera
   ring 30 degrees apart, fronto alone gets 11 % of the floor within 1 % depth error at the
   coarse level, fronto + ground 84 %). The "vertical" families (planes that hold the up
   direction, turned by +-``vertical_sweep_deg`` about it) do the same for upright surfaces
   that a camera 90 degrees away sees foreshortened: the sides of people.
2. **Refinement** at each finer octave: the inverse depth map is upsampled; whole-map
   propagation lets every pixel try its neighbours' depths (PatchMatch's propagation, for all
   pixels at once), then every pixel tests its own depth at +-``refine_radius`` steps (one
   step moves its image in the most sensitive source by ``refine_step_px`` pixels) with a
   parabola fit. Sources are resampled through the whole hypothesis map, so neighbouring
   pixels carry neighbouring hypotheses and each NCC window is compared along the current
   surface estimate: slanted surfaces match without explicit normals. The steps start from
   the map's median where it is close (``refine_median_px``): the noise of the neighbours'
   depths would otherwise warp each window unevenly.

All work happens on the crop of the reference that holds the region of interest, so cost
scales with the ROI's area; ``DepthEstimate.work`` counts pixel x source NCC evaluations.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.dense import gpu, kernels
from edgerecon.dense.config import DenseConfig
from edgerecon.dense.cost import F32, as_f32
from edgerecon.dense.threads import RowBands
from edgerecon.geometry.camera import Camera

logger = logging.getLogger(__name__)

#: Rays closer than this angle to a ground plane get no hypotheses from that family.
_MIN_GRAZING_SIN = np.sin(np.radians(4.0))
#: ... and rays closer than this angle to a vertical family's planes none from it.
_MIN_VERTICAL_SIN = np.sin(np.radians(10.0))

#: Sub-sampling of the inverse-depth axis when placing sweep planes.
_FINE_SAMPLES = 2048
#: Smallest crop side (pixels) worth a level of the pyramid.
_MIN_LEVEL_SIDE = 24
#: A last, non-octave pyramid level is added only if it is this much smaller than the
#: previous one.
_TOP_LEVEL_MIN_RATIO = 1.5


@dataclass(frozen=True, eq=False)
class ViewPyramid:
    """A view's grey images and cameras at the working resolution and the octaves below."""

    camera_id: int
    cameras: tuple[Camera, ...]
    """``cameras[l]`` is the camera at 2**-l of the working resolution."""
    greys: tuple[F32, ...]
    """Grey images (``cost.to_grey``) matching ``cameras``."""

    @property
    def num_levels(self) -> int:
        return len(self.cameras)

    @functools.cached_property
    def noise(self) -> float:
        """Standard deviation of the working image's noise (``noise_sigma``), measured once."""
        return noise_sigma(self.greys[0])


#: Immerkaer's 3x3 mask: the difference of two Laplacians, blind to a pixel's local plane and
#: curvature, so that on smooth image content only the noise answers it (36 sigma^2).
_NOISE_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def noise_sigma(grey: F32) -> float:
    """Standard deviation of a grey image's additive noise, in grey levels: the median
    absolute response to Immerkaer's mask (J. Immerkaer, "Fast noise variance estimation",
    CVIU 1996) over 6 sigma's median for Gaussian noise (0.6745). The median leaves out the
    edges and texture of a minority of pixels (texture everywhere reads as noise: an upper
    bound). 0 for images smaller than 3x3."""
    g = np.asarray(grey, np.float32)
    if g.ndim != 2 or min(g.shape) < 3:
        return 0.0
    response = cv2.filter2D(g, cv2.CV_32F, _NOISE_MASK, borderType=cv2.BORDER_REFLECT)
    inner = np.abs(response[1:-1:2, 1:-1:2])  # every other pixel: the same median, a quarter
    return float(np.median(inner)) / (0.6745 * 6.0)


def ncc_threshold(
    texture: F32, noise: float, min_ncc: float, min_snr: float
) -> NDArray[np.float32]:
    """Per pixel, the least NCC that accepts a depth when windows of grey standard deviation
    ``texture`` are seen through independent noise of standard deviation ``noise``. Two
    views of the same surface then correlate at most 1 - noise^2 / texture^2 (the signal's
    share of each window's variance: Spearman's attenuation), and a match needs ``min_ncc``
    of that ceiling. Only where the texture is at least ``min_snr`` times the noise: below
    it the best of many depth hypotheses scores as high by chance as the true one, and
    ``min_ncc`` stays (a dim 7x7 scene with texture near the noise lost 96 % of its depths to
    the chance winners that a lowered threshold let in, which then contradicted the true
    depths of the other views)."""
    std = np.asarray(texture, np.float32)
    n2 = np.float32(noise * noise)
    ceiling = np.clip(1.0 - n2 / np.maximum(std * std, np.float32(1e-12)), 0.0, 1.0)
    measurable = std >= np.float32(min_snr * noise)
    return np.where(measurable, np.float32(min_ncc) * ceiling, np.float32(min_ncc)).astype(
        np.float32
    )


def pyramid_scales(
    width: int,
    height: int,
    levels: int,
    top_side: int | None = None,
    *,
    small_exhaustive: bool = True,
) -> tuple[float, ...]:
    """The scales of :func:`build_pyramid`'s levels below a working image of ``width`` x
    ``height`` pixels (level 0, scale 1, not included): octaves, and with ``top_side`` a
    last level whose longer side is ``top_side`` pixels where the next octave would be
    smaller and the previous one is 1.5x larger than ``top_side`` and, with
    ``small_exhaustive``, at least an octave below the working image (the plane sweep runs
    there: its cost then follows the image scale instead of jumping fourfold between two
    octaves). A level under 8 pixels ends the pyramid."""
    scales: list[float] = []
    side = max(width, height)
    for level in range(1, levels + 1):
        scale = 0.5**level
        last = False
        if top_side is not None and side * scale < top_side:
            if (small_exhaustive and level == 1) or side * scale * 2 <= (
                top_side * _TOP_LEVEL_MIN_RATIO
            ):
                # The previous level is (nearly) the size asked for already, or it is the
                # working image itself: small images are swept exhaustively there, which
                # beat a coarser sweep + refinement (demo scene at r = 0.6: golden F 0.514
                # against 0.467; utrecht4cam at r = 0.6: the floor is found).
                break
            scale, last = top_side / side, True
        if min(max(1, round(width * scale)), max(1, round(height * scale))) < 8:
            break
        scales.append(scale)
        if last:
            break
    return tuple(scales)


def build_pyramid(
    camera_id: int,
    camera: Camera,
    grey: F32,
    levels: int,
    top_side: int | None = None,
    *,
    small_exhaustive: bool = True,
) -> ViewPyramid:
    """Pyramid of up to ``levels`` levels below the working image ``grey`` of ``camera``
    (:func:`pyramid_scales`)."""
    cams = [camera]
    greys = [grey]
    for scale in pyramid_scales(
        camera.width, camera.height, levels, top_side, small_exhaustive=small_exhaustive
    ):
        cam = camera.scaled(scale)
        cams.append(cam)
        greys.append(as_f32(cv2.resize(grey, cam.size, interpolation=cv2.INTER_AREA)))
    return ViewPyramid(camera_id=camera_id, cameras=tuple(cams), greys=tuple(greys))


def sweep_level(sides: Sequence[int], config: DenseConfig) -> int:
    """The pyramid level :func:`estimate_depth` sweeps a whole image at: the coarsest of the
    first ``coarse_levels`` whose longer side (``sides``, level 0 first) keeps
    ``sweep_min_side_px`` pixels (level 0 when none below it does)."""
    top = min(config.coarse_levels, len(sides) - 1)
    while top > 0 and sides[top] < config.sweep_min_side_px:
        top -= 1
    return top


#: What a pixel of the plane sweep costs against a pixel of the working image's
#: refinement with two local-search passes (:func:`depth_cost`), fitted to the foreground's
#: dense time over r on caliscope_charuco (1280x720, 10.2) and hd4 (1920x1080, 6.8) with
#: the sweep's and the working image's pixel counts (docs/BENCHMARKS.md).
SWEEP_PIXEL_COST = 8.0
#: Each local-search pass less than two takes this share off the working image's
#: refinement (one pass: 0.76 of two passes' on caliscope_charuco, 0.79 on hd4).
_REFINE_PASS_COST = 0.23


def depth_pixels(width: int, height: int, config: DenseConfig) -> tuple[int, int]:
    """The pixels of a depth map over a whole working image of ``width`` x ``height``: the
    working image's, and those of the pyramid level its plane sweep runs at
    (:func:`sweep_level` of :func:`pyramid_scales`)."""
    scales = pyramid_scales(
        width,
        height,
        config.coarse_levels,
        config.sweep_min_side_px,
        small_exhaustive=config.sweep_small_exhaustive,
    )
    sizes = [(width, height)] + [
        (max(1, round(width * s)), max(1, round(height * s))) for s in scales
    ]
    sweep_w, sweep_h = sizes[sweep_level([max(w, h) for w, h in sizes], config)]
    return width * height, sweep_w * sweep_h


def depth_cost(width: int, height: int, config: DenseConfig) -> float:
    """The relative cost of a depth map over a whole working image of ``width`` x
    ``height`` pixels (:func:`depth_pixels`): its pixels, weighted by the local-search passes
    (two: 1), plus the pixels of the level its plane sweep runs at, :data:`SWEEP_PIXEL_COST`
    each. Over the image scale r this is not monotonic: where the sweep's level drops to a
    coarser one (on 1280-wide frames between r = 0.55 and 0.6), a larger r costs less (the
    controller skips the scales that cost more than a larger one,
    ``pipeline.dominated_scales``)."""
    working, sweep = depth_pixels(width, height, config)
    refine = 1.0 - _REFINE_PASS_COST * (2 - config.refine_passes)
    return working * refine + SWEEP_PIXEL_COST * sweep


@dataclass(frozen=True)
class Roi:
    """Half-open pixel box ``[x0, x1) x [y0, y1)`` at the working resolution."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        return self.y1 - self.y0

    @property
    def area(self) -> int:
        return max(self.width, 0) * max(self.height, 0)


@dataclass(frozen=True, eq=False)
class DepthEstimate:
    """Depths of one ROI of one reference view, at the working resolution."""

    roi: Roi
    depth: F32
    """(h, w) depth along the optical axis; 0 = none."""
    score: F32
    """(h, w) aggregated NCC of the depth (-1 where none)."""
    texture: F32
    """(h, w) grey standard deviation of each reference window."""
    work: int
    """Pixel x source NCC evaluations performed (proportional to the compute spent)."""
    num_planes: int
    """Sweep planes tested (all families)."""


def crop_camera(camera: Camera, x0: int, y0: int, width: int, height: int) -> Camera:
    """The pinhole camera of the sub-image ``[x0, x0 + width) x [y0, y0 + height)``."""
    K = camera.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return Camera(
        name=camera.name, width=width, height=height, K=K, R=camera.R, t=camera.t, dist=camera.dist
    )


def roi_at_level(roi: Roi, cam0: Camera, cam: Camera) -> Roi:
    """The box of ``cam``'s image (a resized ``cam0``) that covers ``roi`` of ``cam0``."""
    sx, sy = cam.width / cam0.width, cam.height / cam0.height
    x0 = int(np.floor((roi.x0 + 0.5) * sx - 0.5))
    y0 = int(np.floor((roi.y0 + 0.5) * sy - 0.5))
    x1 = int(np.ceil((roi.x1 - 0.5) * sx - 0.5)) + 1
    y1 = int(np.ceil((roi.y1 - 0.5) * sy - 0.5)) + 1
    return Roi(max(x0, 0), max(y0, 0), min(x1, cam.width), min(y1, cam.height))


def _pixel_grid(width: int, height: int) -> tuple[F32, F32]:
    u = np.arange(width, dtype=np.float32)[None, :].repeat(height, axis=0)
    v = np.arange(height, dtype=np.float32)[:, None].repeat(width, axis=1)
    return u, v


def _rays(camera: Camera) -> NDArray[np.float32]:
    """(h, w, 3) camera-frame rays with z = 1 of every pixel."""
    u, v = _pixel_grid(camera.width, camera.height)
    Kinv = np.linalg.inv(camera.K)
    x = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
    y = Kinv[1, 1] * v + Kinv[1, 2]
    return np.stack([x, y, np.ones_like(x)], axis=-1).astype(np.float32)


@dataclass(frozen=True, eq=False)
class _Pair:
    """Relative geometry of the reference crop and one source at one level."""

    R: NDArray[np.float64]
    """Rotation source_from_ref."""
    t: NDArray[np.float64]
    """Translation source_from_ref."""
    K: NDArray[np.float64]
    """Source intrinsics."""
    grey: F32
    size: tuple[int, int]


def _pair(ref: Camera, src: Camera, grey: F32) -> _Pair:
    R = src.R @ ref.R.T
    t = src.t - R @ ref.t
    return _Pair(R=R, t=t, K=src.K, grey=grey, size=src.size)


# ================================================================================== sweep
@dataclass(frozen=True, eq=False)
class _Family:
    name: str
    normal: NDArray[np.float64]
    """Plane normal n in the reference camera frame; planes are n . X = 1 / lambda."""
    nray: F32
    """(h, w) n . ray of every pixel."""
    usable: NDArray[np.bool_]
    """(h, w) pixels this family may explain."""


def _families(
    cam: Camera, rays: NDArray[np.float32], up: NDArray[np.float64] | None, config: DenseConfig
) -> list[_Family]:
    out = []
    h, w = rays.shape[:2]
    norm = np.linalg.norm(rays, axis=2)
    for name in config.sweep_families:
        if name == "fronto":
            n = np.array([0.0, 0.0, 1.0])
            out.append(_Family(name, n, np.ones((h, w), np.float32), np.ones((h, w), dtype=bool)))
        elif name == "ground" and up is not None:
            n = cam.R @ up
            nray = (rays @ n.astype(np.float32)).astype(np.float32)
            # Below-camera horizontal planes only (floors, tables): n . X < 0 there.
            usable = nray < -_MIN_GRAZING_SIN * norm
            if usable.mean() > 0.02:
                out.append(_Family(name, n, nray, usable))
        elif name == "vertical" and up is not None:
            # Planes that hold the up direction, turned about it from the image plane.
            u = cam.R @ up
            u = u / np.linalg.norm(u)
            front = np.array([0.0, 0.0, 1.0]) - u[2] * u
            if np.linalg.norm(front) < 1e-6:
                continue  # a camera looking straight up or down: no such planes
            front /= np.linalg.norm(front)
            side = np.cross(u, front)
            for deg in config.vertical_sweep_deg:
                a = math.radians(deg)
                for sign in (1.0, -1.0):
                    n = front * math.cos(a) + sign * side * math.sin(a)
                    nray = (rays @ n.astype(np.float32)).astype(np.float32)
                    # Planes in front of the camera, not seen edge-on.
                    usable = nray > _MIN_VERTICAL_SIN * norm
                    if usable.mean() > 0.02:
                        out.append(_Family(f"{name}{sign * deg:+g}", n, nray, usable))
    return out


def _plane_parameters(
    family: _Family,
    rays: NDArray[np.float32],
    near: F32,
    far: F32,
    pairs: Sequence[_Pair],
    step_px: float,
    max_planes: int,
) -> NDArray[np.float64]:
    """Inverse plane offsets lambda = 1 / d spaced by at most ``step_px`` of image motion."""
    h, w = rays.shape[:2]
    gy, gx = np.meshgrid(
        np.linspace(0, h - 1, 6).round().astype(int),
        np.linspace(0, w - 1, 8).round().astype(int),
        indexing="ij",
    )
    gy, gx = gy.ravel(), gx.ravel()
    ok = family.usable[gy, gx] & (near[gy, gx] > 0) & (far[gy, gx] > near[gy, gx])
    if not ok.any():
        # Fall back to every usable pixel (small or odd-shaped ROIs).
        gy, gx = np.nonzero(family.usable & (near > 0) & (far > near))
        if len(gy) == 0:
            return np.zeros(0)
        pick = np.linspace(0, len(gy) - 1, min(len(gy), 108)).round().astype(int)
        gy, gx = gy[pick], gx[pick]
        ok = np.ones(len(gy), dtype=bool)
    gy, gx = gy[ok], gx[ok]
    r = rays[gy, gx].astype(np.float64)  # (S, 3)
    nr = family.nray[gy, gx].astype(np.float64)
    # lambda = 1 / (z * n.ray) over z in [near, far]
    lam_a = 1.0 / (near[gy, gx] * nr)
    lam_b = 1.0 / (far[gy, gx] * nr)
    lam_lo = np.minimum(lam_a, lam_b)
    lam_hi = np.maximum(lam_a, lam_b)
    grid = np.linspace(lam_lo.min(), lam_hi.max(), _FINE_SAMPLES)
    motion = np.zeros(_FINE_SAMPLES - 1)
    inside_pix = (grid[:, None] >= lam_lo[None]) & (grid[:, None] <= lam_hi[None])  # (G, S)
    g = grid[:, None]
    for p in pairs:
        a = (p.K @ p.R @ r.T).T  # (S, 3)
        b = np.outer(nr, p.K @ p.t)  # (S, 3)
        # The source pixel of each sample ray at each grid value, (G, S) per coordinate.
        zs = a[:, 2] + g * b[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = (a[:, 0] + g * b[:, 0]) / zs
            y = (a[:, 1] + g * b[:, 1]) / zs
        W, H = p.size
        vis = inside_pix & (zs > 0) & (x > -W) & (x < 2 * W) & (y > -H) & (y < 2 * H)
        dx = np.diff(x, axis=0)
        dy = np.diff(y, axis=0)
        with np.errstate(invalid="ignore", over="ignore"):
            d = np.sqrt(dx * dx + dy * dy)  # (G-1, S)
        d[~(vis[1:] & vis[:-1])] = 0.0
        motion = np.maximum(motion, d.max(axis=1))
    cum = np.concatenate([[0.0], np.cumsum(motion)])
    total = cum[-1]
    if total <= 0:
        return np.zeros(0)
    step = max(step_px, total / (max_planes - 1))
    n = int(np.floor(total / step)) + 1
    targets = np.arange(n) * step
    # cum is non-decreasing; interpolate on its strictly increasing part.
    keep = np.concatenate([[True], np.diff(cum) > 0])
    lam = np.interp(targets, cum[keep], grid[keep])
    return np.unique(lam)


def _homographies(
    pair: _Pair,
    K_ref_inv: NDArray[np.floating[Any]],
    n: NDArray[np.floating[Any]],
    lams: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(P, 3, 3) crop pixel -> source pixel for the planes ``n . X = 1 / lam`` (reference
    frame), one per ``lams``."""
    planes = pair.R[None] + np.asarray(lams, np.float64)[:, None, None] * np.outer(pair.t, n)
    return pair.K @ planes @ K_ref_inv


@dataclass(frozen=True, eq=False)
class _RefStats:
    """Reference crop and its window statistics (``kernels.window_stats``)."""

    image: F32
    mean: F32
    var: F32
    """Window variance + ``kernels.VAR_EPS``."""
    count: F32
    radius: int
    scored: NDArray[np.bool_]
    """Pixels to score."""
    active: NDArray[np.bool_]
    """Pixels whose sources are sampled: those to score, grown by the window radius."""

    @property
    def std(self) -> F32:
        return np.sqrt(np.maximum(self.var - kernels.VAR_EPS, 0.0)).astype(np.float32)


def _ref_stats(
    grey: F32, radius: int, region: NDArray[np.bool_] | None = None, min_texture: float = 0.0
) -> _RefStats:
    """Statistics of the reference crop ``grey``; ``region`` (same shape) the pixels to score
    (None = all), without those whose window's grey standard deviation is below
    ``min_texture`` (their depths would be discarded)."""
    grey = np.ascontiguousarray(grey, dtype=np.float32)
    mean, var, count = kernels.window_stats(grey, radius)
    if min_texture > 0:
        textured = var - kernels.VAR_EPS >= np.float32(min_texture) ** 2
        region = textured if region is None else region & textured
    if region is None or region.all():
        region = active = np.ones(grey.shape, dtype=bool)
    else:
        k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * radius + 3, 2 * radius + 3))
        active = cv2.dilate(region.astype(np.uint8), k).astype(bool)
    return _RefStats(
        image=grey,
        mean=mean,
        var=var,
        count=count,
        radius=radius,
        scored=np.asarray(region, bool),
        active=active,
    )


def _stack_sources(pairs: Sequence[_Pair]) -> tuple[F32, NDArray[np.int64]]:
    """Source images stacked into one (S, H, W) array (zero-padded) and their sizes."""
    H = max(p.grey.shape[0] for p in pairs)
    W = max(p.grey.shape[1] for p in pairs)
    srcs = np.zeros((len(pairs), H, W), np.float32)
    sizes = np.zeros((len(pairs), 2), np.int64)
    for i, p in enumerate(pairs):
        h, w = p.grey.shape
        srcs[i, :h, :w] = p.grey
        sizes[i] = (w, h)
    return srcs, sizes


def _run_rows(bands: RowBands | None, kernel: Callable[[int, int], None], height: int) -> None:
    if bands is None:
        kernel(0, height)
    else:
        bands.run(kernel, height)


def _sweep(
    cam: Camera,
    scorer: _Scorer,
    pairs: Sequence[_Pair],
    near: F32,
    far: F32,
    up: NDArray[np.float64] | None,
    config: DenseConfig,
) -> tuple[F32, F32, int, int]:
    """Plane sweep over all families: (inverse depth, score, work, number of planes)."""
    h, w = cam.height, cam.width
    rays = _rays(cam)
    Kinv = np.linalg.inv(cam.K)
    best_w = np.zeros((h, w), np.float32)
    best_s = np.full((h, w), -1.0, np.float32)
    work = 0
    planes_total = 0
    w_lo = np.where(far > 0, 1.0 / np.maximum(far, 1e-30), np.inf).astype(np.float32)
    w_hi = np.where(near > 0, 1.0 / np.maximum(near, 1e-30), -np.inf).astype(np.float32)
    for fam in _families(cam, rays, up, config):
        lams = _plane_parameters(
            fam, rays, near, far, pairs, config.plane_step_px, config.max_planes
        )
        if len(lams) < 3:
            continue
        planes_total += len(lams)
        Hs = np.ascontiguousarray(
            np.stack([_homographies(p, Kinv, fam.normal, lams) for p in pairs], axis=1)
        )
        best = np.full((h, w), -np.inf, np.float32)
        idx = np.zeros((h, w), np.int32)
        prev = np.full((h, w), -1.0, np.float32)
        nxt = np.full((h, w), -1.0, np.float32)
        scorer.sweep(
            Hs, lams.astype(np.float64), fam.nray, fam.usable, w_lo, w_hi, config, best, idx,
            prev, nxt,
        )  # fmt: skip
        work += len(lams) * h * w * len(pairs)
        lam_best = _subplane(best, idx, prev, nxt, lams)
        inv = (fam.nray * lam_best).astype(np.float32)
        better = best > best_s
        best_s = np.where(better, best, best_s)
        best_w = np.where(better, inv, best_w)
    return best_w, best_s, work, planes_total


def _subplane(
    s0: F32, idx: NDArray[np.integer[Any]], sm: F32, sp: F32, values: NDArray[np.float64]
) -> NDArray[np.float32]:
    """Parabola through the best hypothesis (score s0 at ``values[idx]``) and its neighbours
    (scores sm, sp; -1 = none) -> interpolated value."""
    n = len(values)
    denom = sm - 2.0 * s0 + sp
    interior = (idx > 0) & (idx < n - 1) & (denom < -1e-6) & (sm > -1) & (sp > -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(interior, 0.5 * (sm - sp) / denom, 0.0)
    off = np.clip(off, -0.5, 0.5)
    v = values.astype(np.float32)
    v0 = v[idx]
    vn = np.where(off > 0, v[np.clip(idx + 1, 0, n - 1)], v[np.clip(idx - 1, 0, n - 1)])
    return (v0 + np.abs(off) * (vn - v0)).astype(np.float32)


# ============================================================================= refinement
@dataclass(frozen=True, eq=False)
class _Sources:
    """Per-pixel projection terms of all sources: ``x_s ~ a[s] + w b[s]`` for inverse
    depth w, and the stacked source images."""

    a: NDArray[np.float32]
    """(S, 3, h, w) K_s R ray."""
    b: NDArray[np.float32]
    """(S, 3) K_s t."""
    srcs: F32
    sizes: NDArray[np.int64]
    ok: NDArray[np.bool_]
    """(S, h, w) False where a source cannot decide (``_epipolar_texture_ok``)."""


def _epipolar_texture_ok(
    cam: Camera,
    stats: _RefStats,
    pairs: Sequence[_Pair],
    min_texture: float,
    min_share: float = 0.0,
) -> NDArray[np.bool_]:
    """(S, h, w) True where the reference window has texture along the epipolar line of
    source s: the RMS of the image derivative along the line, in grey levels per pixel, at
    least ``min_texture`` and at least ``min_share`` of the window's whole gradient energy.

    Matching slides windows along epipolar lines; an edge parallel to them (a floor seam
    running parallel to the baseline) matches equally well everywhere along it (the aperture
    problem), and both views of such a pair can agree on the same wrong depth, which the
    consistency check cannot catch."""
    h, w = stats.image.shape
    out = np.ones((len(pairs), h, w), dtype=bool)
    if min_texture <= 0 and min_share <= 0:
        return out
    gx = as_f32(cv2.Sobel(stats.image, cv2.CV_32F, 1, 0, ksize=3, scale=0.125))
    gy = as_f32(cv2.Sobel(stats.image, cv2.CV_32F, 0, 1, ksize=3, scale=0.125))
    u, v = _pixel_grid(w, h)
    k = (2 * stats.radius + 1, 2 * stats.radius + 1)
    total = as_f32(cv2.boxFilter(gx * gx + gy * gy, -1, k)) if min_share > 0 else None
    for i, p in enumerate(pairs):
        # Source centre in the reference crop: x ~ K (R_ref C_s + t_ref) = K (-R^T t) ...
        c_src = -p.R.T @ p.t  # source centre in the reference camera frame
        e = cam.K @ c_src
        if abs(e[2]) > 1e-9 * np.linalg.norm(e):
            dx = u - np.float32(e[0] / e[2])
            dy = v - np.float32(e[1] / e[2])
        else:
            dx = np.full((h, w), np.float32(e[0]))
            dy = np.full((h, w), np.float32(e[1]))
        norm = np.sqrt(dx * dx + dy * dy) + np.float32(1e-12)
        g = (gx * dx + gy * dy) / norm
        energy = as_f32(cv2.boxFilter(g * g, -1, k))
        out[i] = energy >= np.float32(min_texture * min_texture)
        if total is not None:
            out[i] &= energy >= np.float32(min_share) * total
    return out


def _sources(rays: NDArray[np.float32], pairs: Sequence[_Pair], ok: NDArray[np.bool_]) -> _Sources:
    a = np.empty((len(pairs), 3, *rays.shape[:2]), np.float32)
    b = np.empty((len(pairs), 3), np.float32)
    for i, p in enumerate(pairs):
        M = (p.K @ p.R).astype(np.float32)
        a[i] = np.moveaxis(rays @ M.T, -1, 0)
        b[i] = p.K @ p.t
    srcs, sizes = _stack_sources(pairs)
    return _Sources(a=a, b=b, srcs=srcs, sizes=sizes, ok=ok)


class _Scorer:
    """The NCC scoring of one level of one reference view: the plane sweep and the scores
    of per-pixel hypotheses, by the compiled CPU kernels (row bands on the idle threads'
    cores) or, where :func:`gpu.use_gpu` says so, on the GPU (``gpu.CudaScorer``; a GPU that
    fails hands over to the CPU kernels for the rest of the process)."""

    def __init__(
        self, stats: _RefStats, src: _Sources, bands: RowBands | None, use_gpu: bool
    ) -> None:
        self.stats = stats
        self.src = src
        self.bands = bands
        self.cuda: gpu.CudaScorer | None = None
        # More sources than a GPU thread keeps (``gpu.MAX_SOURCES``): this level on the CPU.
        if use_gpu and len(src.b) <= gpu.MAX_SOURCES:
            try:
                self.cuda = gpu.CudaScorer(
                    stats.image, stats.mean, stats.var, stats.count, src.srcs, src.sizes,
                    src.ok, stats.active, stats.radius, src.a, src.b,
                )  # fmt: skip
            except Exception as exc:
                gpu.report_failure(exc)

    def _on_gpu(self) -> gpu.CudaScorer | None:
        return self.cuda if self.cuda is not None and gpu.cuda_status()[0] else None

    def sweep(
        self,
        Hs: NDArray[np.float64],
        lams: NDArray[np.float64],
        nray: F32,
        usable: NDArray[np.bool_],
        w_lo: F32,
        w_hi: F32,
        config: DenseConfig,
        best: F32,
        idx: NDArray[np.int32],
        prev: F32,
        nxt: F32,
    ) -> None:
        """``kernels.sweep`` of one plane family (updates best / idx / prev / nxt)."""
        if (cuda := self._on_gpu()) is not None:
            try:  # writes best / idx / prev / nxt only once the whole family succeeded
                cuda.sweep(
                    Hs, lams, nray, usable, w_lo, w_hi, config.ncc_top_k, config.ncc_top_gap,
                    best, idx, prev, nxt,
                )  # fmt: skip
                return
            except Exception as exc:
                gpu.report_failure(exc)
        st, src = self.stats, self.src
        rows = functools.partial(
            kernels.sweep,
            st.image, st.mean, st.var, st.count, src.srcs, src.sizes, src.ok, st.active, Hs,
            lams, nray, usable, w_lo, w_hi, st.radius, config.ncc_top_k, config.ncc_top_gap,
            best, idx, prev, nxt,
        )  # fmt: skip
        _run_rows(self.bands, rows, st.image.shape[0])

    def evaluate(self, inv: F32, w_lo: F32, w_hi: F32, config: DenseConfig) -> F32:
        """Aggregated NCC of the per-pixel inverse depths ``inv`` (``kernels.evaluate``)."""
        inv = np.ascontiguousarray(inv, dtype=np.float32)
        if (cuda := self._on_gpu()) is not None:
            try:
                return cuda.evaluate(inv, w_lo, w_hi, config.ncc_top_k, config.ncc_top_gap)
            except Exception as exc:
                gpu.report_failure(exc)
        st, src = self.stats, self.src
        out = np.empty(inv.shape, np.float32)
        rows = functools.partial(
            kernels.evaluate,
            st.image, st.mean, st.var, st.count, src.srcs, src.sizes, src.ok, st.active, src.a,
            src.b, inv, w_lo, w_hi, st.radius, config.ncc_top_k, config.ncc_top_gap, out,
        )  # fmt: skip
        _run_rows(self.bands, rows, inv.shape[0])
        return out


def _step_map(inv: F32, src: _Sources, step_px: float) -> F32:
    """Inverse-depth step that moves the image in the most sensitive source by step_px."""
    sens = np.zeros_like(inv)
    for s in range(len(src.b)):
        a = src.a[s]
        b = src.b[s]
        den = a[2] + inv * b[2]
        ok = den > 1e-12
        den = np.where(ok, den, 1.0)
        # Rays nearly parallel to a source's image plane overflow float32 (rig units of
        # millimetres): no usable sensitivity there.
        with np.errstate(over="ignore", invalid="ignore"):
            mx = (a[0] + inv * b[0]) / den
            my = (a[1] + inv * b[1]) / den
            dx = (b[0] - mx * b[2]) / den
            dy = (b[1] - my * b[2]) / den
            norm = np.sqrt(dx * dx + dy * dy)
        sens = np.maximum(sens, np.where(ok & np.isfinite(norm), norm, 0.0))
    return (step_px / np.maximum(sens, 1e-12)).astype(np.float32)


def _shift(a: F32, dx: int, dy: int) -> F32:
    """``out[y, x] = a[y - dy, x - dx]`` with edge replication."""
    h, w = a.shape
    pad = max(abs(dx), abs(dy))
    p = cv2.copyMakeBorder(a, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    return as_f32(p[pad - dy : pad - dy + h, pad - dx : pad - dx + w])


#: Neighbour offsets tried by whole-map propagation (near ones repair noise, far ones holes).
_PROPAGATION = ((-2, 0), (2, 0), (0, -2), (0, 2), (-6, 0), (6, 0), (0, -6), (0, 6))


def _refine(
    inv: F32,
    score: F32 | None,
    scorer: _Scorer,
    w_lo: F32,
    w_hi: F32,
    config: DenseConfig,
    local_search: bool = True,
) -> tuple[F32, F32, int]:
    work = 0
    src = scorer.src
    n_src = len(src.b)
    npix = inv.size
    if score is None:
        score = scorer.evaluate(inv, w_lo, w_hi, config)
        work += npix * n_src
    for _ in range(config.propagation_iterations):
        for dx, dy in _PROPAGATION:
            cand = _shift(inv, dx, dy)
            s = scorer.evaluate(cand, w_lo, w_hi, config)
            work += npix * n_src
            better = s > score
            inv = np.where(better, cand, inv)
            score = np.where(better, s, score)
    K = config.refine_radius
    for _ in range(config.refine_passes if K > 0 and local_search else 0):
        # The search steps from a smoothed surface (see ``_median_base``); where the base is
        # the map itself, its scores are known already.
        base = _median_base(inv, config.refine_median_px, config.refine_median_rel)
        step = _step_map(base, src, config.refine_step_px)
        scores = np.empty((2 * K + 1, *inv.shape), np.float32)
        for i, k_off in enumerate(range(-K, K + 1)):
            if k_off == 0 and base is inv:
                scores[i] = score
                continue
            scores[i] = scorer.evaluate(base + k_off * step, w_lo, w_hi, config)
            work += npix * n_src
        idx = np.argmax(scores, axis=0)
        s0 = np.take_along_axis(scores, idx[None], axis=0)[0]
        sm = np.take_along_axis(scores, np.clip(idx - 1, 0, 2 * K)[None], axis=0)[0]
        sp = np.take_along_axis(scores, np.clip(idx + 1, 0, 2 * K)[None], axis=0)[0]
        offsets = _subplane(s0, idx, sm, sp, np.arange(-K, K + 1, dtype=np.float64))
        cand = (base + offsets * step).astype(np.float32)
        # The sub-step position is a prediction: keep it only where it scores as well.
        s_sub = scorer.evaluate(cand, w_lo, w_hi, config)
        work += npix * n_src
        use_sub = s_sub >= s0 - 1e-3
        new = np.where(use_sub, cand, base + (idx - K).astype(np.float32) * step)
        new_score = np.where(use_sub, s_sub, s0)
        if base is not inv:
            # From a smoothed base, a pixel whose own depth scored better keeps it.
            keep = score > new_score
            new = np.where(keep, inv, new)
            new_score = np.where(keep, score, new_score)
        inv, score = new, new_score
    return inv.astype(np.float32), score.astype(np.float32), work


def _median_base(inv: F32, kernel: int, rel: float) -> F32:
    """Where the local search starts: the inverse-depth map median-filtered with ``kernel``
    (3 or 5; 0 = the map itself, returned as is), kept where it is within ``rel`` of the
    pixel's own value (depth edges keep theirs).

    Each NCC window is compared along the hypothesis map of its pixels (``_Sources``), so
    noise in the neighbours' depths warps the window unevenly and blurs the match of the
    pixel's own depth; from a median-smoothed map every window sees one coherent surface,
    shifted as a whole."""
    if kernel <= 0:
        return inv
    med = np.asarray(cv2.medianBlur(np.ascontiguousarray(inv, np.float32), kernel), np.float32)
    far = np.abs(med - inv) > np.float32(rel) * np.abs(inv)
    return np.where(far, inv, med).astype(np.float32)


def _upsample(inv: F32, roi_c: Roi, cam_c: Camera, roi_f: Roi, cam_f: Camera) -> F32:
    """Resample a coarse crop's inverse depth onto a finer crop (same view)."""
    sx, sy = cam_c.width / cam_f.width, cam_c.height / cam_f.height
    u, v = _pixel_grid(roi_f.width, roi_f.height)
    mx = (u + roi_f.x0 + 0.5) * sx - 0.5 - roi_c.x0
    my = (v + roi_f.y0 + 0.5) * sy - 0.5 - roi_c.y0
    return as_f32(
        cv2.remap(
            inv,
            mx.astype(np.float32),
            my.astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
    )


def _block(cam0: Camera, cam: Camera) -> NDArray[np.uint8]:
    """Square structuring element of the working pixels one pixel of the level camera
    ``cam`` covers (2^level for octaves, rounded up for a resized level)."""
    k = max(1, math.ceil(cam0.width / cam.width - 1e-6))
    return np.ones((k, k), np.uint8)


@functools.lru_cache(maxsize=64)
def _nearest_index(src: int, dst: int) -> NDArray[np.intp]:
    """The source index ``cv2.resize(..., INTER_NEAREST)`` takes for each of ``dst`` output
    pixels along an axis of ``src`` pixels (asked of OpenCV itself, so that a crop sampled
    through it equals the crop of the resized image)."""
    line = np.arange(src, dtype=np.float32)[None]
    idx = cv2.resize(line, (dst, 1), interpolation=cv2.INTER_NEAREST)[0].astype(np.intp)
    idx.flags.writeable = False
    return idx


def _bounds_at(near: F32, far: F32, roi: Roi, cam0: Camera, cam: Camera) -> tuple[F32, F32]:
    """Per-pixel near/far of the crop ``roi`` of level camera ``cam`` (0 = none)."""
    if cam.size == cam0.size:
        return (
            near[roi.y0 : roi.y1, roi.x0 : roi.x1],
            far[roi.y0 : roi.y1, roi.x0 : roi.x1],
        )
    # Conservative resampling: nearest-neighbour of min(near) / max(far) over the blocks of
    # working pixels each level pixel covers; only around the working pixels the crop
    # samples (the morphology's window stays inside that margin, so the values are those
    # of the whole image's).
    ker = _block(cam0, cam)
    k = ker.shape[0]
    xs = _nearest_index(cam0.width, cam.width)[roi.x0 : roi.x1]
    ys = _nearest_index(cam0.height, cam.height)[roi.y0 : roi.y1]
    if len(xs) == 0 or len(ys) == 0:
        empty = np.zeros((len(ys), len(xs)), np.float32)
        return empty, empty.copy()
    x0, x1 = max(int(xs[0]) - k, 0), min(int(xs[-1]) + k + 1, near.shape[1])
    y0, y1 = max(int(ys[0]) - k, 0), min(int(ys[-1]) + k + 1, near.shape[0])
    n = near[y0:y1, x0:x1]
    nz = np.where(n > 0, n, np.inf).astype(np.float32)
    n = as_f32(cv2.erode(nz, ker))
    n = np.where(np.isfinite(n), n, 0).astype(np.float32)
    f = as_f32(cv2.dilate(np.ascontiguousarray(far[y0:y1, x0:x1]), ker))
    pick = np.ix_(ys - y0, xs - x0)
    return np.ascontiguousarray(n[pick]), np.ascontiguousarray(f[pick])


def _region_at(region: NDArray[np.bool_], roi: Roi, cam0: Camera, cam: Camera) -> NDArray[np.bool_]:
    """The crop ``roi`` of level camera ``cam`` of a working-resolution ``region``: a level
    pixel belongs to it when any of the working pixels it covers does."""
    if cam.size != cam0.size:
        grown = cv2.dilate(region.astype(np.uint8), _block(cam0, cam))
        region = cv2.resize(grown, cam.size, interpolation=cv2.INTER_NEAREST) > 0
    return np.asarray(region[roi.y0 : roi.y1, roi.x0 : roi.x1], bool)


def estimate_depth(
    ref: ViewPyramid,
    sources: Sequence[ViewPyramid],
    roi: Roi,
    near: F32,
    far: F32,
    up: NDArray[np.float64] | None,
    config: DenseConfig,
    region: NDArray[np.bool_] | None = None,
    bands: RowBands | None = None,
) -> DepthEstimate:
    """Depth of the pixels of ``roi`` (working resolution) of ``ref``.

    ``near``/``far`` are (H, W) per-pixel depth bounds of the whole working image (0 = pixel
    excluded). ``up`` is the scene's up direction (world frame) for the "ground" family.
    ``region`` (H, W) restricts the work to these pixels (and their windows) inside the ROI
    (default: the pixels with bounds). ``bands`` lends idle threads to the kernels.
    """
    cam0 = ref.cameras[0]
    empty = DepthEstimate(
        roi=roi,
        depth=np.zeros((roi.height, roi.width), np.float32),
        score=np.full((roi.height, roi.width), -1.0, np.float32),
        texture=np.zeros((roi.height, roi.width), np.float32),
        work=0,
        num_planes=0,
    )
    if not sources or roi.area == 0:
        return empty
    sides = [max(c.width, c.height) for c in ref.cameras]
    top = min(sweep_level(sides, config), *(s.num_levels - 1 for s in sources))
    while top > 0:
        r = roi_at_level(roi, cam0, ref.cameras[top])
        if min(r.width, r.height) >= _MIN_LEVEL_SIDE:
            break
        top -= 1
    work = 0
    planes = 0
    inv: F32 | None = None
    score: F32 | None = None
    prev: tuple[Roi, Camera] | None = None
    stats: _RefStats | None = None
    on_gpu = gpu.use_gpu(config.device)
    for level in range(top, -1, -1):
        cam_l = ref.cameras[level]
        r = roi_at_level(roi, cam0, cam_l) if level else roi
        crop = crop_camera(cam_l, r.x0, r.y0, r.width, r.height)
        near_l, far_l = _bounds_at(near, far, r, cam0, cam_l)
        todo = near_l > 0
        if region is not None:
            todo &= _region_at(region, r, cam0, cam_l)
        # At the working level, textureless windows are discarded whatever they score: no
        # work for them.
        stats = _ref_stats(
            ref.greys[level][r.y0 : r.y1, r.x0 : r.x1],
            config.window_radius,
            todo,
            config.min_texture if level == 0 else 0.0,
        )
        pairs = [_pair(crop, s.cameras[level], s.greys[level]) for s in sources]
        w_lo = np.where(far_l > 0, 1.0 / np.maximum(far_l, 1e-30), np.inf).astype(np.float32)
        w_hi = np.where(near_l > 0, 1.0 / np.maximum(near_l, 1e-30), 0.0).astype(np.float32)
        src_ok = _epipolar_texture_ok(
            crop, stats, pairs, config.min_epipolar_texture, config.min_epipolar_share
        )
        src_ok &= stats.scored[None]  # no scores outside the region
        scorer = _Scorer(stats, _sources(_rays(crop), pairs, src_ok), bands, on_gpu)
        lo, hi = w_lo * np.float32(0.999), w_hi * np.float32(1.001)
        if inv is None:
            inv, score, wk, planes = _sweep(crop, scorer, pairs, near_l, far_l, up, config)
            work += wk
            # Propagation at the coarsest level cleans the winner-take-all noise; the local
            # search waits for the next (finer) level unless this is the last one.
            inv, score, wk = _refine(inv, score, scorer, lo, hi, config, level == 0)
        else:
            assert prev is not None
            inv = _upsample(inv, prev[0], prev[1], r, cam_l)
            inv, score, wk = _refine(inv, None, scorer, lo, hi, config)
        work += wk
        prev = (r, cam_l)
    assert inv is not None and score is not None and stats is not None
    with np.errstate(divide="ignore"):
        depth = np.where(inv > 0, 1.0 / inv, 0.0).astype(np.float32)
    texture = stats.std
    if config.noise_adaptive_ncc:
        least = ncc_threshold(texture, ref.noise, config.min_ncc, config.ncc_min_snr)
        ok = score >= least
    else:
        ok = score >= config.min_ncc
    ok &= (texture >= config.min_texture) & (depth > 0)
    ok &= near[roi.y0 : roi.y1, roi.x0 : roi.x1] > 0
    depth[~ok] = 0.0
    return DepthEstimate(
        roi=roi, depth=depth, score=score, texture=texture, work=work, num_planes=planes
    )
