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

from edgerecon.geometry.camera import Camera, Rig
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
    d = np.stack([np.asarray(xn, np.float64), np.asarray(yn, np.float64), np.ones(len(xn))], axis=1)
    return camera.center + (d * np.asarray(depth, np.float64)[:, None]) @ camera.R


def voxel_first(points: NDArray[np.float64], voxel_m: float) -> NDArray[np.intp]:
    """Indices of the first point in each occupied voxel of size ``voxel_m`` (sorted)."""
    if len(points) == 0:
        return np.zeros(0, np.intp)
    keys = np.floor(points / voxel_m).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) < 2**62:
        flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        _, first = np.unique(flat, return_index=True)
    else:  # pragma: no cover - astronomically large extents
        _, first = np.unique(keys, axis=0, return_index=True)
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
    for cam, depth, mask in zip(rig, depths, masks, strict=True):
        counts += visible_in(cam, points, labels, depth, mask)
    return counts


def visible_in(
    cam: Camera,
    points: NDArray[np.float64],
    labels: NDArray[np.int32],
    depth: DepthMap,
    mask: NDArray[np.uint8],
) -> NDArray[np.bool_]:
    """(N,) True where camera ``cam`` sees the point (depth and object id agree)."""
    out = np.zeros(len(points), bool)
    if len(points) == 0:
        return out
    uv, z = cam.project(points)
    h, w = depth.shape
    with np.errstate(invalid="ignore"):
        ok = (
            (z > 0)
            & (uv[:, 0] >= -0.5)
            & (uv[:, 0] <= w - 0.5)
            & (uv[:, 1] >= -0.5)
            & (uv[:, 1] <= h - 0.5)
        )
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return out
    # The 2x2 neighbourhood around the projection (clamped so that border pixels have one).
    u0 = np.clip(np.floor(uv[idx, 0]).astype(np.intp), 0, max(w - 2, 0))
    v0 = np.clip(np.floor(uv[idx, 1]).astype(np.intp), 0, max(h - 2, 0))
    zi = z[idx]
    tol = VISIBILITY_TOL_ABS_M + VISIBILITY_TOL_REL * zi
    lab = labels[idx]
    seen = np.zeros(idx.size, bool)
    dmin = np.full(idx.size, np.inf)
    dmax = np.full(idx.size, -np.inf)
    for du in (0, 1):
        for dv in (0, 1):
            uu = np.minimum(u0 + du, w - 1)
            vv = np.minimum(v0 + dv, h - 1)
            same = mask[vv, uu] == lab
            d = depth[vv, uu].astype(np.float64)
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
        pts_list.append(rays_to_points(cam, xn.ravel()[idx], yn.ravel()[idx], d))
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

    def actor_positions(self, t: int) -> dict[int, tuple[float, float]]:
        """Floor positions (metres) of the actors present at time ``t``."""
        row = self.meta.get("actor_positions", [])[self._check_time(t)]
        return {int(k): (float(v[0]), float(v[1])) for k, v in row.items()}


@lru_cache(maxsize=64)
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
