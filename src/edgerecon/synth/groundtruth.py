"""Ground truth of a synthetic sequence: visible-surface clouds, view counts, and the reader.

Ground-truth clouds are sampled on *visible* surfaces: every pixel of every camera is
back-projected with its exact depth (the renderer's own ray, so the point lies on the analytic
surface to float32 precision), then the union is thinned with a voxel grid (one real surface
point kept per voxel, not the voxel centre): ``SceneConfig.gt_voxel_foreground_m`` (3 mm by
default) for the actors at each timestamp, ``gt_voxel_background_m`` (6 mm) for the static
scene, rendered once without actors. Each point carries ``num_views``: how many cameras see it
(it projects inside the image, its depth matches the camera's ground-truth depth map within
2 mm + 0.2 % of the depth over the 2x2 pixel neighbourhood, and, for actors, the object id
matches). A reconstruction can only recover points seen by >= 2 cameras, so scores are
reported against that subset as well as against all points.

The folder layout is documented in docs/ARCHITECTURE.md ("Ground truth folder");
``GroundTruth.open(path)`` reads it.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig, _distort
from edgerecon.io.ply import read_ply
from edgerecon.types import DataError, DepthMap, PointCloud

logger = logging.getLogger(__name__)

GT_FORMAT = "edgerecon-synth-gt"
GT_VERSION = 1
Part = Literal["foreground", "background", "all"]
PARTS = ("foreground", "background", "all")

#: Visibility test tolerance: |depth - ground-truth depth| <= abs + rel * depth (metres).
VISIBILITY_TOL_ABS_M = 0.002
VISIBILITY_TOL_REL = 0.002


def rays_to_points(
    camera: Camera, xn: NDArray[np.float32], yn: NDArray[np.float32], depth: NDArray[np.float32]
) -> NDArray[np.float64]:
    """World points of rays with normalised coordinates (xn, yn) at ``depth`` (flat arrays)."""
    x = np.asarray(xn, np.float64)
    y = np.asarray(yn, np.float64)
    s = np.asarray(depth, np.float64)
    R, c = camera.R, camera.center
    out = np.empty((len(s), 3))
    for k in range(3):  # X = C + s R^T (x, y, 1), one coordinate at a time (fast, exact)
        out[:, k] = c[k] + s * (R[0, k] * x + R[1, k] * y + R[2, k])
    return out


_KEY_BITS = 21
_KEY_BIAS = 1 << (_KEY_BITS - 1)


def _voxel_keys(points: NDArray[np.float64], voxel_m: float) -> NDArray[np.int64] | None:
    """One int64 per point naming its voxel (None if the extent needs more than 21 bits)."""
    k = np.floor(points / voxel_m).astype(np.int64) + _KEY_BIAS
    if len(k) and (k.min() < 0 or k.max() >= (1 << _KEY_BITS)):
        return None
    return (k[:, 0] << (2 * _KEY_BITS)) | (k[:, 1] << _KEY_BITS) | k[:, 2]


def voxel_first(points: NDArray[np.float64], voxel_m: float) -> NDArray[np.intp]:
    """Indices of the first point in each occupied voxel of size ``voxel_m`` (sorted)."""
    if len(points) == 0:
        return np.zeros(0, np.intp)
    keys = _voxel_keys(points, voxel_m)
    if keys is not None:
        _, first = np.unique(keys, return_index=True)
    else:  # pragma: no cover - extents of thousands of kilometres
        _, first = np.unique(np.floor(points / voxel_m), axis=0, return_index=True)
    return np.sort(first)


def count_views(
    points: NDArray[np.float64],
    labels: NDArray[np.int32],
    rig: Rig,
    depths: Sequence[DepthMap],
    masks: Sequence[NDArray[np.uint8]],
) -> NDArray[np.uint8]:
    """(N,) number of cameras that see each point (see the module docstring for the test).

    ``depths[i]`` / ``masks[i]`` are camera i's ground-truth depth map and object-id mask at
    the points' timestamp; a point with label k counts only where the mask says k.
    """
    counts = np.zeros(len(points), np.uint8)
    cols = np.ascontiguousarray(np.asarray(points, np.float64).T)
    for cam, depth, mask in zip(rig, depths, masks, strict=True):
        counts += _visible_columns(cam, cols, labels, depth, mask)
    return counts


def _project_columns(
    cam: Camera, cols: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``Camera.project`` on (3, N) world coordinates, one coordinate at a time."""
    R, t, K = cam.R, cam.t, cam.K
    X, Y, Z = cols
    xc = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
    yc = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
    z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = xc / z
        yn = yc / z
    if cam.has_distortion:
        xn, yn = _distort(xn, yn, cam.dist)
    u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
    v = K[1, 1] * yn + K[1, 2]
    return u, v, z


def visible_in(
    cam: Camera,
    points: NDArray[np.float64],
    labels: NDArray[np.int32],
    depth: DepthMap,
    mask: NDArray[np.uint8],
) -> NDArray[np.bool_]:
    """(N,) True where camera ``cam`` sees the (N, 3) points (depth and object id agree)."""
    cols = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3).T)
    return _visible_columns(cam, cols, labels, depth, mask)


def _visible_columns(
    cam: Camera,
    cols: NDArray[np.float64],
    labels: NDArray[np.int32],
    depth: DepthMap,
    mask: NDArray[np.uint8],
) -> NDArray[np.bool_]:
    n = cols.shape[1]
    out = np.zeros(n, bool)
    if n == 0:
        return out
    u, v, z = _project_columns(cam, cols)
    h, w = depth.shape
    with np.errstate(invalid="ignore"):
        ok = (z > 0) & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return out
    # The 2x2 neighbourhood around the projection (clamped so that border pixels have one).
    u0 = np.clip(np.floor(u[idx]).astype(np.intp), 0, max(w - 2, 0))
    v0 = np.clip(np.floor(v[idx]).astype(np.intp), 0, max(h - 2, 0))
    base = v0 * w + u0
    zi = z[idx]
    tol = VISIBILITY_TOL_ABS_M + VISIBILITY_TOL_REL * zi
    flat_depth = depth.ravel()
    offsets = (0, 1 if w > 1 else 0, w if h > 1 else 0, (w if h > 1 else 0) + (1 if w > 1 else 0))
    lab = labels[idx]
    if not lab.any() and not mask.any():
        # Everything is background: no object-id test (the common, large case).
        d4 = [flat_depth[base + o] for o in offsets]
        dmin = np.minimum(np.minimum(d4[0], d4[1]), np.minimum(d4[2], d4[3]))
        dmax = np.maximum(np.maximum(d4[0], d4[1]), np.maximum(d4[2], d4[3]))
        out[idx] = (zi >= dmin - tol) & (zi <= dmax + tol)
        return out
    flat_mask = mask.ravel()
    seen = np.zeros(idx.size, bool)
    dmin = np.full(idx.size, np.inf)
    dmax = np.full(idx.size, -np.inf)
    for o in offsets:
        same = flat_mask[base + o] == lab
        d = flat_depth[base + o].astype(np.float64)
        dmin = np.where(same, np.minimum(dmin, d), dmin)
        dmax = np.where(same, np.maximum(dmax, d), dmax)
        seen |= same
    seen &= (zi >= dmin - tol) & (zi <= dmax + tol)
    out[idx] = seen
    return out


def sample_visible_cloud(
    rig: Rig,
    rays: Sequence[tuple[NDArray[np.float32], NDArray[np.float32]]],
    depths: Sequence[DepthMap],
    masks: Sequence[NDArray[np.uint8]],
    colors: Sequence[NDArray[np.uint8]] | None,
    *,
    voxel_m: float,
    part: Literal["foreground", "background"],
) -> PointCloud:
    """Ground-truth cloud of the visible surfaces of ``part`` at one timestamp.

    ``rays[i]`` = camera i's per-pixel normalised ray coordinates (xn, yn); ``colors[i]`` its
    noise-free BGR image (point colours, RGB in the cloud). Points get ``labels`` (object ids)
    and a ``num_views`` attribute (uint8).
    """
    pts_list, lab_list, col_list = [], [], []
    for i, cam in enumerate(rig):
        m = masks[i].ravel()
        idx = np.flatnonzero(m > 0) if part == "foreground" else np.flatnonzero(m == 0)
        if idx.size == 0:
            continue
        xn, yn = rays[i]
        d = depths[i].ravel()[idx]
        pts = rays_to_points(cam, xn.ravel()[idx], yn.ravel()[idx], d)
        # Thin each camera on its own first (cheap), then the union.
        first = voxel_first(pts, voxel_m)
        idx, pts = idx[first], pts[first]
        pts_list.append(pts)
        lab_list.append(m[idx].astype(np.int32))
        if colors is not None:
            col_list.append(colors[i].reshape(-1, 3)[idx][:, ::-1])
    if not pts_list:
        return PointCloud(
            points3D=np.zeros((0, 3)),
            colors=np.zeros((0, 3), np.uint8) if colors is not None else None,
            labels=np.zeros(0, np.int32),
            attributes={"num_views": np.zeros(0, np.uint8)},
        )
    pts = np.concatenate(pts_list)
    labels = np.concatenate(lab_list)
    keep = voxel_first(pts, voxel_m)
    pts, labels = pts[keep], labels[keep]
    cols = np.concatenate(col_list)[keep] if col_list else None
    views = count_views(pts, labels, rig, depths, masks)
    return PointCloud(points3D=pts, colors=cols, labels=labels, attributes={"num_views": views})


# ------------------------------------------------------------------------------- reader
class GroundTruth:
    """Reader of a synthetic dataset's ground-truth folder.

    >>> gt = GroundTruth.open("work/demo")            # doctest: +SKIP
    >>> gt.depth("cam0", 3), gt.object_mask(0, 3)     # doctest: +SKIP
    >>> gt.reference_cloud(3, part="foreground", min_views=2)  # doctest: +SKIP
    """

    def __init__(self, root: Path, meta: dict[str, Any]) -> None:
        self.root = root
        self.meta = meta
        self.rig = Rig.from_dict(meta["rig"])
        self.num_frames = int(meta["num_frames"])
        self.background_frames = int(meta.get("background_frames", 0))
        self.actor_ids: list[int] = [int(a["id"]) for a in meta.get("actors", [])]

    @classmethod
    def open(cls, path: str | Path) -> GroundTruth:
        """Open a ground-truth folder, or a dataset folder whose dataset.json names one."""
        root = Path(path)
        if not root.exists():
            raise DataError(f"ground truth not found: {root}")
        descriptor = root / "dataset.json"
        if descriptor.is_file() and not (root / "scene.json").is_file():
            try:
                desc = json.loads(descriptor.read_text())
            except (OSError, ValueError) as exc:
                raise DataError(f"{descriptor}: unreadable dataset descriptor ({exc})") from None
            gt_rel = desc.get("ground_truth")
            if not gt_rel:
                raise DataError(f"{root}: dataset has no ground truth (not a synthetic scene)")
            root = root / gt_rel
        meta_path = root / "scene.json"
        if not meta_path.is_file():
            raise DataError(f"{root}: not a ground-truth folder (no scene.json)")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError) as exc:
            raise DataError(f"{meta_path}: unreadable ({exc})") from None
        if meta.get("format") != GT_FORMAT:
            raise DataError(f"{meta_path}: not an edgerecon ground-truth file")
        if int(meta.get("version", 0)) > GT_VERSION:
            raise DataError(f"{meta_path}: version {meta.get('version')} is newer than supported")
        return cls(root, meta)

    # -------------------------------------------------------------------- lookups
    @property
    def camera_names(self) -> list[str]:
        return self.rig.names

    def _camera(self, camera: int | str) -> tuple[int, Camera]:
        try:
            i = self.rig.index(camera)
        except ValueError as exc:
            raise DataError(str(exc)) from None
        return i, self.rig[i]

    def _check_time(self, t: int) -> int:
        if not 0 <= int(t) < self.num_frames:
            raise DataError(f"time {t} out of range 0..{self.num_frames - 1} ({self.root})")
        return int(t)

    def _file(self, key: str, **fmt: Any) -> Path:
        return self.root / self.meta["files"][key].format(**fmt)

    def background_depth(self, camera: int | str) -> DepthMap:
        """(H, W) float32 depth of the empty scene (metres along the optical axis)."""
        _, cam = self._camera(camera)
        return _load_npy(self._file("background_depth", camera=cam.name)).copy()

    def object_mask(self, camera: int | str, t: int) -> NDArray[np.uint8]:
        """(H, W) uint8 object ids at time ``t``: 0 = background, k = actor k."""
        _, cam = self._camera(camera)
        path = self._file("mask", camera=cam.name, index=self._check_time(t))
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if mask is None:
            raise DataError(f"ground-truth mask missing or unreadable: {path}")
        return np.asarray(mask, dtype=np.uint8)

    def foreground_mask(self, camera: int | str, t: int) -> NDArray[np.bool_]:
        return self.object_mask(camera, t) > 0

    def depth(self, camera: int | str, t: int) -> DepthMap:
        """(H, W) float32 depth at time ``t`` along the optical axis (``Camera.project``'s
        convention), metres; every pixel sees a surface."""
        mask = self.object_mask(camera, t)
        _, cam = self._camera(camera)
        depth = self.background_depth(camera)
        fg = mask > 0
        if fg.any():
            path = self._file("foreground_depth", camera=cam.name, index=int(t))
            values = _load_npy(path)
            if values.shape != (int(fg.sum()),):
                raise DataError(f"{path}: {values.shape[0]} depths for {int(fg.sum())} pixels")
            depth[fg] = values
        return depth

    def reference_cloud(
        self, t: int | None = None, part: Part = "foreground", min_views: int = 2
    ) -> PointCloud:
        """Ground-truth cloud: ``part`` at time ``t`` (the background needs no time), keeping
        the points seen by at least ``min_views`` cameras (1 = every visible point)."""
        if part not in PARTS:
            raise DataError(f"part must be one of {PARTS}, got {part!r}")
        if min_views < 1:
            raise DataError(f"min_views must be >= 1, got {min_views}")
        clouds = []
        if part in ("background", "all"):
            clouds.append(_read_cloud(self._file("background_cloud")))
        if part in ("foreground", "all"):
            if t is None:
                raise DataError("the foreground ground truth needs a time (--time)")
            clouds.append(_read_cloud(self._file("foreground_cloud", index=self._check_time(t))))
        cloud = PointCloud.concatenate(clouds)
        views = cloud.attributes.get("num_views")
        if views is None:
            raise DataError(f"{self.root}: ground-truth clouds lack the num_views attribute")
        return cloud.select(views >= min_views)

    @property
    def stretches(self) -> dict[str, list[dict[str, Any]]]:
        """The scene's difficult stretches, integer frame intervals [start, stop): ``still``,
        ``away``, ``seated`` (each with its ``actor``) and ``dimming`` (with ``min_level``);
        empty lists for datasets written before they were recorded."""
        recorded = self.meta.get("stretches", {})
        return {k: list(recorded.get(k, [])) for k in ("still", "away", "seated", "dimming")}

    @property
    def seated_from_start(self) -> list[int]:
        """Ids of the actors seated from the first frame: no motion cue ever separates them
        from the room, so scores that leave them out (``bench_scene``'s moving IoU,
        ``bench_online``'s moving F) say what the scene model can do with the others."""
        return sorted({int(s["actor"]) for s in self.stretches["seated"] if s["start"] == 0})

    def illumination(self, t: int) -> float:
        """Global light level at time ``t`` (1 = the scene's full light)."""
        levels = self.meta.get("scene", {}).get("illumination")
        if not levels:
            return 1.0
        return float(levels[self.background_frames + self._check_time(t)])

    def actor_positions(self, t: int) -> dict[int, tuple[float, float]]:
        """Floor positions (metres) of the actors present at time ``t``."""
        row = self.meta.get("actor_positions", [])[self._check_time(t)]
        return {int(k): (float(v[0]), float(v[1])) for k, v in row.items()}


@lru_cache(maxsize=16)
def _load_npy_cached(path: str, mtime: float) -> NDArray[Any]:
    arr = np.load(path, allow_pickle=False)
    arr.setflags(write=False)
    return arr


def _load_npy(path: Path) -> NDArray[Any]:
    try:
        return _load_npy_cached(str(path), path.stat().st_mtime)
    except FileNotFoundError:
        raise DataError(f"ground-truth file missing: {path}") from None
    except ValueError as exc:
        raise DataError(f"{path}: unreadable ({exc})") from None


def _read_cloud(path: Path) -> PointCloud:
    if not path.is_file():
        raise DataError(f"ground-truth cloud missing: {path}")
    return read_ply(path)
