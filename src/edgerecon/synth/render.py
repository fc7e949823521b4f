"""Vectorised ray casting of the synthetic scene into every camera of the rig.

Per camera, the ray of every pixel (through the lens distortion, if any) is computed once;
the static background (room + furniture) is ray-cast once into a depth map and a radiance
image (albedo x Lambertian irradiance) and cached. Per timestamp only the actors are cast,
each body part restricted to its projected bounding box, with a z-buffer against the cached
background depth; shading is deferred to the winning pixels. Imaging (per-camera gains,
global illumination, optical blur, sensor noise, 8-bit quantisation) is applied to the whole
frame with OpenCV. Everything is float32 NumPy/OpenCV; there is no per-pixel Python.

Outputs per camera and timestamp: the BGR image, the depth map (float32, depth along the
optical axis, the same convention as ``Camera.project``) and the object-id mask (uint8,
0 = background, k = actor k).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera
from edgerecon.synth.primitives import Ellipsoid, Surface
from edgerecon.synth.scene import Lighting, SynthScene
from edgerecon.types import DepthMap, Image, StageTimings

logger = logging.getLogger(__name__)

_T = TypeVar("_T")
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Extra texels of noise beyond the image in each direction; frames take shifted windows of
#: one precomputed noise field per camera (cheap, and independent between nearby frames).
_NOISE_MARGIN = 64
#: Bounding boxes of distorted projections get this many pixels of margin.
_BBOX_MARGIN_PX = 2


@dataclass(frozen=True, kw_only=True, eq=False)
class RenderedFrame:
    """The images and ground truth of one timestamp, one entry per rig camera."""

    time_index: int
    """Frame index (negative for frames of the background-only clip)."""
    images: tuple[Image, ...]
    """BGR uint8 frames as the cameras see them (noise, gains, blur, distortion)."""
    depths: tuple[DepthMap, ...]
    """float32 depth along the optical axis, metres (every pixel sees a surface)."""
    masks: tuple[NDArray[np.uint8], ...]
    """uint8 object ids: 0 = static background, k = actor k."""
    clean: tuple[Image, ...] | None = None
    """Noise-free albedo x irradiance (no camera gains, no blur), BGR uint8; on request."""
    timings: StageTimings
    """Seconds spent (summed over cameras, which may run in parallel)."""


def pixel_grid_rays(camera: Camera) -> tuple[F32, F32]:
    """(H, W) float32 normalised ray coordinates (xn, yn) of every pixel centre (z = 1)."""
    w, h = camera.width, camera.height
    if not camera.has_distortion:
        Kinv = np.linalg.inv(camera.K)
        u = np.arange(w, dtype=np.float64)[None, :]
        v = np.arange(h, dtype=np.float64)[:, None]
        xn = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
        yn = Kinv[1, 1] * v + Kinv[1, 2] + 0.0 * u
        return xn.astype(np.float32), np.ascontiguousarray(yn, dtype=np.float32)
    xn = np.empty((h, w), np.float32)
    yn = np.empty((h, w), np.float32)
    u = np.arange(w, dtype=np.float64)
    step = max(1, 262144 // w)
    for y0 in range(0, h, step):
        y1 = min(h, y0 + step)
        vv, uu = np.meshgrid(np.arange(y0, y1, dtype=np.float64), u, indexing="ij")
        x, y = _undistort_newton(camera, uu.ravel(), vv.ravel())
        xn[y0:y1] = x.reshape(y1 - y0, w)
        yn[y0:y1] = y.reshape(y1 - y0, w)
    return xn, yn


def _undistort_newton(camera: Camera, u: F64, v: F64, max_iterations: int = 20) -> tuple[F64, F64]:
    """Invert OpenCV's (k1, k2, p1, p2, k3) model for pixels (u, v) by Newton's method with the
    analytic Jacobian (the same root as ``Camera.pixel_rays``, ~20x faster on full images);
    pixels that do not converge fall back to ``Camera.pixel_rays``."""
    K = camera.K
    k1, k2, p1, p2, k3 = camera.dist
    ty = (v - K[1, 2]) / K[1, 1]
    tx = (u - K[0, 2] - K[0, 1] * ty) / K[0, 0]
    x, y = tx.copy(), ty.copy()
    for _ in range(max_iterations):
        xx, yy, xy = x * x, y * y, x * y
        r2 = xx + yy
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        fx = x * rad + 2 * p1 * xy + p2 * (r2 + 2 * xx) - tx
        fy = y * rad + p1 * (r2 + 2 * yy) + 2 * p2 * xy - ty
        j11 = rad + 2 * xx * drad + 2 * p1 * y + 6 * p2 * x
        j12 = 2 * xy * drad + 2 * p1 * x + 2 * p2 * y
        j22 = rad + 2 * yy * drad + 6 * p1 * y + 2 * p2 * x
        det = j11 * j22 - j12 * j12
        dx = (j22 * fx - j12 * fy) / det
        dy = (j11 * fy - j12 * fx) / det
        x -= dx
        y -= dy
        if not np.nanmax(np.abs(dx) + np.abs(dy)) > 1e-15:
            break
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    res = np.hypot(
        x * rad + 2 * p1 * xy + p2 * (r2 + 2 * xx) - tx,
        y * rad + p1 * (r2 + 2 * yy) + 2 * p2 * xy - ty,
    )
    bad = ~(res < 1e-12)
    if bad.any():
        rays = camera.pixel_rays(np.stack([u[bad], v[bad]], axis=1))
        x[bad], y[bad] = rays[:, 0], rays[:, 1]
    return x, y


def irradiance(lighting: Lighting, normals: F32, points: F32) -> F32:
    """(N,) Lambertian irradiance at surface points (view-independent)."""
    key = np.asarray(lighting.key_direction, np.float32)
    key /= np.linalg.norm(key)
    e = np.float32(lighting.ambient) + np.float32(lighting.key) * np.maximum(normals @ key, 0)
    d = np.asarray(lighting.lamp_position, np.float32) - points
    dist2 = np.einsum("ij,ij->i", d, d)
    cos = np.maximum(np.einsum("ij,ij->i", normals, d), 0)
    soft = np.float32(lighting.lamp_softness_m**2)
    e += np.float32(lighting.lamp) * cos / (np.sqrt(dist2) * (dist2 + soft))
    return e.astype(np.float32)


@dataclass(eq=False)
class _CameraState:
    camera: Camera
    xn: F32
    yn: F32
    norm_bounds: tuple[float, float, float, float]
    """(xmin, xmax, ymin, ymax) of the image's normalised ray coordinates."""
    bg_depth: F32
    bg_radiance: F32
    bg_blurred: F32
    """``bg_radiance`` after the optical blur (the same array when there is none)."""
    bg_label: NDArray[np.int16]
    noise: F32 | None = None
    floor_xy: tuple[F32, F32] | None = None


class Renderer:
    """Renders a ``SynthScene``; caches per-camera rays and the static background.

    Thread-safe for concurrent ``render`` calls; ``threads`` cameras are rendered in parallel
    (NumPy and OpenCV release the GIL in the heavy calls).
    """

    def __init__(self, scene: SynthScene, *, threads: int = 2) -> None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.scene = scene
        self.threads = threads
        self._states: list[_CameraState | None] = [None] * len(scene.rig)
        self._locks = [threading.Lock() for _ in scene.rig]
        self.prepare_seconds = 0.0

    # ------------------------------------------------------------------------ caches
    def prepare(self, cameras: Sequence[int] | None = None) -> float:
        """Cast the static background into ``cameras`` (default all); returns seconds."""
        ids = list(range(len(self.scene.rig))) if cameras is None else list(cameras)
        timings = StageTimings()
        with timings.stage("prepare"):
            self._map(self._state, ids)
        return timings.total

    def _map(self, fn: Callable[[int], _T], ids: list[int]) -> list[_T]:
        if self.threads == 1 or len(ids) == 1:
            return [fn(i) for i in ids]
        with ThreadPoolExecutor(max_workers=self.threads) as pool:
            return list(pool.map(fn, ids))

    def _state(self, index: int) -> _CameraState:
        state = self._states[index]
        if state is not None:
            return state
        with self._locks[index]:
            state = self._states[index]
            if state is None:
                state = self._build_state(index)
                self._states[index] = state
        return state

    def _build_state(self, index: int) -> _CameraState:
        scene = self.scene
        cam = scene.rig[index]
        xn, yn = pixel_grid_rays(cam)
        bounds = (float(xn.min()), float(xn.max()), float(yn.min()), float(yn.max()))
        origin, Rwc = cam.center, cam.R.T
        depth = scene.room.intersect(origin, Rwc, xn, yn)
        label = np.zeros(depth.shape, np.int16)
        for j, prim in enumerate(scene.furniture):
            bb = _pixel_bbox(cam, prim.corners(), bounds)
            if bb is None:
                continue
            x0, y0, x1, y1 = bb
            sub = depth[y0:y1, x0:x1]
            s = prim.intersect(origin, Rwc, xn[y0:y1, x0:x1], yn[y0:y1, x0:x1])
            closer = s < sub
            sub[closer] = s[closer]
            label[y0:y1, x0:x1][closer] = j + 1
        if not np.all(np.isfinite(depth)):
            raise RuntimeError(f"camera {cam.name!r}: background rays escaped the room")
        radiance = np.empty(depth.shape + (3,), np.float32)
        flat_lab = label.ravel()
        surfaces = [scene.room.surface] + [f.surface for f in scene.furniture]
        order = np.argsort(flat_lab, kind="stable")
        bounds_j = np.searchsorted(flat_lab[order], np.arange(len(surfaces) + 1))
        groups = [
            (fn, order[bounds_j[j] : bounds_j[j + 1]])
            for j, fn in enumerate(surfaces)
            if bounds_j[j + 1] > bounds_j[j]
        ]
        idx, rad = self._shade(cam, groups, depth.ravel(), xn.ravel(), yn.ravel())
        radiance.reshape(-1, 3)[idx] = rad
        blur = scene.config.realism.blur_sigma_px
        blurred = cv2.GaussianBlur(radiance, (0, 0), blur) if blur > 0 else radiance
        return _CameraState(
            camera=cam,
            xn=xn,
            yn=yn,
            norm_bounds=bounds,
            bg_depth=depth,
            bg_radiance=radiance,
            bg_blurred=np.asarray(blurred, np.float32),
            bg_label=label,
        )

    def _shade(
        self,
        cam: Camera,
        groups: Sequence[tuple[Callable[[F32], Surface], NDArray[np.intp]]],
        depth_flat: F32,
        xn_flat: F32,
        yn_flat: F32,
    ) -> tuple[NDArray[np.intp], F32]:
        """Radiance of the pixels ``idx`` (flat indices into the camera's image) of each
        ``(surface_fn, idx)`` group. Returns the concatenated indices and (N, 3) radiance;
        textures are sampled once per material over all groups."""
        idx = np.concatenate([g[1] for g in groups])
        s = depth_flat[idx]
        x = xn_flat[idx]
        y = yn_flat[idx]
        Rwc = cam.R.T.astype(np.float32)
        dirs = np.empty((len(idx), 3), np.float32)
        for k in range(3):
            dirs[:, k] = Rwc[k, 0] * x + Rwc[k, 1] * y + Rwc[k, 2]
        points = cam.center.astype(np.float32) + s[:, None] * dirs
        surfs: list[Surface] = []
        start = 0
        for fn, gidx in groups:
            surfs.append(fn(points[start : start + len(gidx)]))
            start += len(gidx)
        normals = np.concatenate([f.normals for f in surfs])
        u = np.concatenate([f.u for f in surfs])
        v = np.concatenate([f.v for f in surfs])
        mats = np.concatenate([f.material for f in surfs])
        dnorm = np.sqrt(x * x + y * y + 1)
        cos_t = np.abs(np.einsum("ij,ij->i", normals, dirs)) / dnorm
        # Pixel footprint on the surface (geometric mean of its two axes), metres.
        footprint = s / np.float32(cam.focal_px) * np.sqrt(1.0 / dnorm / np.maximum(cos_t, 0.05))
        albedo = np.empty((len(idx), 3), np.float32)
        for m in np.unique(mats):
            sel = np.flatnonzero(mats == m)
            tex = self.scene.textures[int(m)]
            albedo[sel] = tex.sample(u[sel], v[sel], footprint[sel])
        albedo *= irradiance(self.scene.lighting, normals, points)[:, None]
        return idx, albedo

    def background_depth(self, camera: int) -> DepthMap:
        """Depth of the empty scene (cached; do not modify)."""
        return self._state(camera).bg_depth

    def background_labels(self, camera: int) -> NDArray[np.int16]:
        """Which static primitive each pixel sees: 0 = the room, j = ``scene.furniture[j-1]``."""
        return self._state(camera).bg_label

    def background_clean(self, camera: int) -> Image:
        """Noise-free radiance of the empty scene as BGR uint8 (no camera gains, no blur)."""
        rad = self._state(camera).bg_radiance
        return _to_u8(rad, 255.0)

    def rays(self, camera: int) -> tuple[F32, F32]:
        """(H, W) normalised ray coordinates (xn, yn) of the camera's pixels (cached)."""
        st = self._state(camera)
        return st.xn, st.yn

    # ------------------------------------------------------------------------ frames
    def render(
        self, t: int, *, cameras: Sequence[int] | None = None, clean: bool = False
    ) -> RenderedFrame:
        """Render frame ``t`` (``-background_frames <= t < num_frames``; t < 0 = empty scene)
        into ``cameras`` (default all, in rig order)."""
        c = self.scene.config
        if not -c.background_frames <= t < c.num_frames:
            raise ValueError(f"frame {t} out of range {-c.background_frames}..{c.num_frames - 1}")
        ids = list(range(len(self.scene.rig))) if cameras is None else list(cameras)
        parts: list[tuple[int, Ellipsoid]] = []
        feet: list[F64] = []
        if t >= 0:
            for actor in self.scene.actors_at(t):
                parts += [(actor.actor_id, p) for p in actor.parts(float(t))]
                feet.append(actor.position(float(t)))
        results = self._map(lambda i: self._render_camera(i, t, parts, feet, clean), ids)
        timings = StageTimings()
        for r in results:
            timings.merge(r[4])
        return RenderedFrame(
            time_index=t,
            images=tuple(r[0] for r in results),
            depths=tuple(r[1] for r in results),
            masks=tuple(r[2] for r in results),
            clean=tuple(r[3] for r in results if r[3] is not None) if clean else None,
            timings=timings,
        )

    def _render_camera(
        self,
        index: int,
        t: int,
        parts: list[tuple[int, Ellipsoid]],
        feet: list[F64],
        want_clean: bool,
    ) -> tuple[Image, DepthMap, NDArray[np.uint8], Image | None, StageTimings]:
        timings = StageTimings()
        with timings.stage("background"):
            st = self._state(index)
        scene = self.scene
        gain = scene.camera_gains[index] * np.float32(255.0 * scene.illumination(t))
        scalar = (float(gain[0]), float(gain[1]), float(gain[2]), 0.0)
        with timings.stage("compose"):
            multiply: Any = cv2.multiply  # OpenCV's stubs differ between releases here
            image: NDArray[np.float32] = multiply(st.bg_blurred, scalar)
            depth = st.bg_depth.copy()
            mask = np.zeros(depth.shape, np.uint8)
            clean = st.bg_radiance.copy() if want_clean else None
        with timings.stage("actors"):
            hit = self._cast_actors(st, parts, depth, mask)
            shadow = self._floor_shadows(st, feet, mask)
            if shadow is not None:
                hit = (
                    shadow
                    if hit is None
                    else (
                        np.concatenate([hit[0], shadow[0]]),
                        np.concatenate([hit[1], shadow[1]]),
                    )
                )
        with timings.stage("imaging"):
            if hit is not None:
                self._composite(st, hit, image, clean, gain)
            real = scene.config.realism
            if real.noise_sigma > 0:
                noise = self._noise_window(st, index, t)
                cv2.add(image, noise, dst=image)
            frame = _to_u8(image, 1.0)
            clean_u8 = None
            if clean is not None:
                clean_u8 = _to_u8(clean, 255.0)
        return frame, depth, mask, clean_u8, timings

    def _floor_shadows(
        self, st: _CameraState, feet: list[F64], mask: NDArray[np.uint8]
    ) -> tuple[NDArray[np.intp], F32] | None:
        """Soft contact shadows: floor pixels near the actors' feet, darkened (radiance of the
        unoccluded background times ``1 - strength (1 - d^2 / R^2)^2`` within R of each
        actor). None when there is nothing to do."""
        real = self.scene.config.realism
        if real.contact_shadow <= 0 or not feet:
            return None
        cam = st.camera
        reach = real.contact_shadow_radius_m
        boxes = []
        for p in feet:
            corners = np.array(
                [[p[0] + dx, p[1] + dy, 0.0] for dx in (-reach, reach) for dy in (-reach, reach)]
            )
            bb = _pixel_bbox(cam, corners, st.norm_bounds)
            if bb is not None:
                boxes.append(bb)
        if not boxes:
            return None
        x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
        x1, y1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
        fx, fy = self._floor_xy(st)
        fx, fy = fx[y0:y1, x0:x1], fy[y0:y1, x0:x1]
        factor = np.ones(fx.shape, np.float32)
        inv = np.float32(1.0 / reach**2)
        strength = np.float32(real.contact_shadow)
        with np.errstate(invalid="ignore"):
            for p in feet:
                q = 1 - ((fx - np.float32(p[0])) ** 2 + (fy - np.float32(p[1])) ** 2) * inv
                factor *= 1 - strength * np.square(np.maximum(q, 0))
        keep = (factor < 0.999) & (mask[y0:y1, x0:x1] == 0)  # NaN (not floor) is never < 0.999
        local = np.flatnonzero(keep)
        if local.size == 0:
            return None
        r, c = np.divmod(local, x1 - x0)
        idx = (r + y0) * cam.width + (c + x0)
        return idx, st.bg_radiance.reshape(-1, 3)[idx] * factor.ravel()[local, None]

    def _floor_xy(self, st: _CameraState) -> tuple[F32, F32]:
        """(H, W) world x and y of the floor seen by each pixel (NaN where it is not floor)."""
        if st.floor_xy is None:
            cam = st.camera
            Rwc = cam.R.T.astype(np.float32)
            c = cam.center.astype(np.float32)
            s, xn, yn = st.bg_depth, st.xn, st.yn
            z = c[2] + s * (Rwc[2, 0] * xn + Rwc[2, 1] * yn + Rwc[2, 2])
            floor = (np.abs(z) < 1e-3) & (st.bg_label == 0)
            x = c[0] + s * (Rwc[0, 0] * xn + Rwc[0, 1] * yn + Rwc[0, 2])
            y = c[1] + s * (Rwc[1, 0] * xn + Rwc[1, 1] * yn + Rwc[1, 2])
            nan = np.float32(np.nan)
            st.floor_xy = (np.where(floor, x, nan), np.where(floor, y, nan))
        return st.floor_xy

    def _composite(
        self,
        st: _CameraState,
        hit: tuple[NDArray[np.intp], F32],
        image: F32,
        clean: F32 | None,
        gain: NDArray[np.float32],
    ) -> None:
        """Paint the actors' radiance into ``image`` (already gained, blurred background):
        the region around them is re-composed from the unblurred background and re-blurred,
        so that the frame equals blurring the whole composite."""
        idx, rad = hit
        h, w = st.bg_depth.shape
        rows, cols = np.divmod(idx, w)
        if clean is not None:
            clean.reshape(-1, 3)[idx] = rad
        sigma = self.scene.config.realism.blur_sigma_px
        if sigma <= 0:
            image.reshape(-1, 3)[idx] = rad * gain
            return
        m = int(np.ceil(4 * sigma)) + 1
        # Actors apart in the image get their own regions (columns with a gap between them).
        used = np.unique(cols)
        cuts = np.flatnonzero(np.diff(used) > 4 * m) + 1
        for span in np.split(used, cuts):
            lo, hi = int(span[0]), int(span[-1])
            inside = (cols >= lo) & (cols <= hi)
            # Hits of other spans that fall into this region's margin are composed too.
            x0, x1 = max(0, lo - 2 * m), min(w, hi + 1 + 2 * m)
            near = (cols >= x0) & (cols < x1)
            r_in = rows[inside]
            y0, y1 = max(0, int(r_in.min()) - 2 * m), min(h, int(r_in.max()) + 1 + 2 * m)
            near &= (rows >= y0) & (rows < y1)
            region = st.bg_radiance[y0:y1, x0:x1] * gain
            flat = (rows[near] - y0) * (x1 - x0) + (cols[near] - x0)
            region.reshape(-1, 3)[flat] = rad[near] * gain
            region = np.asarray(cv2.GaussianBlur(region, (0, 0), sigma), np.float32)
            # Inner part only: near the region's cut edges the blur lacks context (image
            # borders are fine: the cached background was blurred with the same rule).
            iy0 = 0 if y0 == 0 else m
            ix0 = 0 if x0 == 0 else m
            iy1 = (y1 - y0) if y1 == h else (y1 - y0 - m)
            ix1 = (x1 - x0) if x1 == w else (x1 - x0 - m)
            image[y0 + iy0 : y0 + iy1, x0 + ix0 : x0 + ix1] = region[iy0:iy1, ix0:ix1]

    def _noise_window(self, st: _CameraState, index: int, t: int) -> F32:
        seed = self.scene.config.seed
        if st.noise is None:
            rng = np.random.default_rng([seed, 3, index])
            h, w = st.bg_depth.shape
            pool = rng.standard_normal((h + _NOISE_MARGIN, w + _NOISE_MARGIN, 3), np.float32)
            pool *= np.float32(self.scene.config.realism.noise_sigma)
            st.noise = pool
        rng = np.random.default_rng([seed, 4, index, t + 1_000_000])
        dy, dx = (int(v) for v in rng.integers(0, _NOISE_MARGIN + 1, 2))
        h, w = st.bg_depth.shape
        window = st.noise[dy : dy + h, dx : dx + w]
        return window if rng.random() < 0.5 else np.negative(window)

    def _cast_actors(
        self,
        st: _CameraState,
        parts: list[tuple[int, Ellipsoid]],
        depth: F32,
        mask: NDArray[np.uint8],
    ) -> tuple[NDArray[np.intp], F32] | None:
        """Z-buffer the actors' parts against ``depth`` (updated in place, ``mask`` too);
        returns the flat indices of the actor pixels and their radiance (None: none)."""
        cam = st.camera
        origin, Rwc = cam.center, cam.R.T
        boxes = []
        for aid, part in parts:
            bb = _pixel_bbox(cam, part.corners(), st.norm_bounds)
            if bb is not None:
                boxes.append((aid, part, bb))
        if not boxes:
            return None
        x0 = min(b[2][0] for b in boxes)
        y0 = min(b[2][1] for b in boxes)
        x1 = max(b[2][2] for b in boxes)
        y1 = max(b[2][3] for b in boxes)
        label = np.zeros((y1 - y0, x1 - x0), np.int16)
        for p, (_, part, (bx0, by0, bx1, by1)) in enumerate(boxes):
            sub = depth[by0:by1, bx0:bx1]
            s = part.intersect(origin, Rwc, st.xn[by0:by1, bx0:bx1], st.yn[by0:by1, bx0:bx1])
            closer = s < sub
            sub[closer] = s[closer]
            label[by0 - y0 : by1 - y0, bx0 - x0 : bx1 - x0][closer] = p + 1
        w = depth.shape[1]
        lab = label.ravel()
        won = np.flatnonzero(lab)
        if won.size == 0:
            return None
        order = won[np.argsort(lab[won], kind="stable")]
        ends = np.searchsorted(lab[order], np.arange(1, len(boxes) + 2))
        groups = []
        for p, (aid, part, _) in enumerate(boxes):
            local = order[ends[p] : ends[p + 1]]
            if local.size == 0:
                continue
            r, c = np.divmod(local, x1 - x0)
            gidx = (r + y0) * w + (c + x0)
            groups.append((part.surface, gidx))
            mask.reshape(-1)[gidx] = aid
        return self._shade(cam, groups, depth.ravel(), st.xn.ravel(), st.yn.ravel())


def _to_u8(image: F32, scale: float) -> Image:
    """Round ``image * scale`` to uint8 with saturation (negative values become 0)."""
    out = cv2.convertScaleAbs(np.maximum(image, np.float32(0.0)), alpha=scale)
    return np.asarray(out, dtype=np.uint8)


def _pixel_bbox(
    cam: Camera, corners: F64, norm_bounds: tuple[float, float, float, float]
) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1), end-exclusive, containing the projection of the convex hull
    of ``corners`` (world); None when it is entirely behind the camera or outside the image."""
    Xc = cam.world_to_cam(corners)
    z = Xc[:, 2]
    xmin, xmax, ymin, ymax = norm_bounds
    if np.all(z <= 1e-6):
        return None
    if np.any(z <= 1e-6):
        rect = (xmin, xmax, ymin, ymax)  # straddles the camera plane: be conservative
    else:
        xs, ys = Xc[:, 0] / z, Xc[:, 1] / z
        rect = (
            max(xmin, float(xs.min())),
            min(xmax, float(xs.max())),
            max(ymin, float(ys.min())),
            min(ymax, float(ys.max())),
        )
        if rect[0] > rect[1] or rect[2] > rect[3]:
            return None
    if cam.has_distortion:
        k = np.linspace(0.0, 1.0, 9)
        bx = np.concatenate(
            [
                rect[0] + (rect[1] - rect[0]) * k,
                np.full(9, rect[1]),
                rect[0] + (rect[1] - rect[0]) * k,
                np.full(9, rect[0]),
            ]
        )
        by = np.concatenate(
            [
                np.full(9, rect[2]),
                rect[2] + (rect[3] - rect[2]) * k,
                np.full(9, rect[3]),
                rect[2] + (rect[3] - rect[2]) * k,
            ]
        )
        pts_cam = np.stack([bx, by, np.ones_like(bx)], axis=1)
        uv, _ = cam.project((pts_cam - cam.t) @ cam.R)
        margin = _BBOX_MARGIN_PX
    else:
        corners2 = np.array(
            [
                [rect[0], rect[2], 1],
                [rect[1], rect[2], 1],
                [rect[0], rect[3], 1],
                [rect[1], rect[3], 1],
            ]
        )
        uv = (corners2 @ cam.K.T)[:, :2]
        margin = 1
    x0 = max(0, int(np.floor(uv[:, 0].min())) - margin)
    y0 = max(0, int(np.floor(uv[:, 1].min())) - margin)
    x1 = min(cam.width, int(np.ceil(uv[:, 0].max())) + margin + 1)
    y1 = min(cam.height, int(np.ceil(uv[:, 1].max())) + margin + 1)
    if x0 >= x1 or y0 >= y1:
        return None
    return x0, y0, x1, y1
