"""Still foreground: what did not change since the back-end densified it is not densified
again on every task.

A person who sits, stands or lies still is foreground (the person model, the models'
hold), yet most of their pixels are the same from one task to the next: a torso, a
standing leg, a seated body. Densified on every task, they cost the task's r as much as
the hands that move. The back-end's background rebuild of time ``s`` also densifies that
time's whole foreground at the golden configuration (its *snapshot*, ``runtime.backend``).
A task at time ``t`` then compares each camera's frame with time ``s``'s:

1. Per camera, the grey level (at ``1 / downsample`` of the masks' resolution, blurred
   over ``blur_px``, brought to the snapshot's exposure by the static scene's median grey) of
   ``t`` against ``s`` (the snapshot carries its own, so a snapshot of any age is usable);
   a pixel whose grey level moved by more than ``change_threshold`` has *changed* (grown by
   ``margin_px``). A mask pixel of ``t`` that was a mask pixel at ``s`` and did not change
   is *still*, unless its object's outline moved (``min_outline_iou``): a uniform shirt
   that walks changes no grey level inside its outlines.
2. The task densifies only its mask pixels near something that is not still (the rest of
   the masks grown by ``margin_px``, so that the two parts overlap; slivers of an outline
   that moved by a pixel and specks smaller than ``min_change_px`` are not worth a box of
   the dense stage).
3. Of the snapshot's points it keeps those that some camera which saw them at ``s`` (the
   snapshot's own depth per camera) sees still at ``t``, that no such camera sees changed
   (an arm lowered; a hand in front of a torso hides the torso's points there until the
   hand leaves) and that at most one camera sees outside its mask (a body that moved
   along one camera's line of sight). The task's masks then label them like its own
   points (``pipeline.label_by_masks``): a person who left takes their points along.

Where less than ``min_share`` of the task's mask pixels are still (people walking), where
it would keep too few of the snapshot's points (``min_kept``), or where no snapshot is held
yet, the task densifies its whole foreground as before. What it cannot
see: a textureless surface that moves within its own outline (a black shirt turning, a
uniform body shifted by less than ``1 - min_outline_iou`` of its width) changes no grey
level; its points stay where the snapshot put them until the next snapshot replaces it
(one per background rebuild, every few seconds).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera
from edgerecon.scene.background import downscale
from edgerecon.scene.hull import depth_map
from edgerecon.scene.masks import disk
from edgerecon.types import Mask, PointCloud
from edgerecon.views import resize_mask


@dataclass(frozen=True, kw_only=True)
class StillConfig:
    """How a task reuses the back-end's snapshot of the foreground (``RuntimeConfig.still``;
    None: every task densifies its whole foreground)."""

    change_threshold: float = 10.0
    """Grey levels (0-255, blurred) by which a pixel must differ from the snapshot's frame to
    have changed."""
    blur_px: int = 3
    """Box blur before the comparison (pixels of the compared grid): sensor noise and
    compression blocks are not changes."""
    downsample: int = 2
    """The comparison's grid: the working resolution divided by this."""
    min_change_px: int = 16
    """Changed pixels in a connected group smaller than this (on the compared grid) are not
    a change: flicker and compression noise would scatter small boxes for the dense stage,
    each of which costs about as much as a large one."""
    min_outline_iou: float = 0.7
    """An object (a connected part of a camera's mask) whose outline overlaps its outline at
    the snapshot's time (the parts of that time's mask it touches) by less than this
    (intersection over union) has moved as a whole: all of it is densified. Grey levels
    alone would keep the inside of a uniform shirt that walked by less than its width."""
    margin_px: int = 6
    """Working pixels by which the changed pixels grow, and the densified part into the still
    one."""
    min_share: float = 0.25
    """Below this share of the task's mask pixels still, the task densifies everything."""
    min_kept: float = 0.3
    """... and so it does when it would keep less than this share of the snapshot's points
    that its still share promises (``share x`` the snapshot's points): cameras that each
    see something else change (a person gesturing to all sides) leave few points that no
    camera saw change, and the task would lose more than it saves."""
    visibility_tol: float = 0.05
    """A snapshot point is seen by a camera when its depth is within this share of the
    nearest snapshot depth at its pixel."""

    def __post_init__(self) -> None:
        if not (self.change_threshold > 0):
            raise ValueError(
                f"StillConfig.change_threshold must be > 0, got {self.change_threshold}"
            )
        if self.blur_px < 1 or self.downsample < 1 or self.margin_px < 0 or self.min_change_px < 0:
            raise ValueError(
                "StillConfig: need blur_px >= 1, downsample >= 1, margin_px >= 0 and "
                f"min_change_px >= 0, got {self.blur_px}, {self.downsample}, {self.margin_px}, "
                f"{self.min_change_px}"
            )
        if not (0.0 <= self.min_outline_iou <= 1.0):
            raise ValueError(
                f"StillConfig.min_outline_iou must be in [0, 1], got {self.min_outline_iou}"
            )
        if not (0.0 <= self.min_kept <= 1.0):
            raise ValueError(f"StillConfig.min_kept must be in [0, 1], got {self.min_kept}")
        if not (0.0 <= self.min_share <= 1.0):
            raise ValueError(f"StillConfig.min_share must be in [0, 1], got {self.min_share}")
        if not (self.visibility_tol >= 0):
            raise ValueError(f"StillConfig.visibility_tol must be >= 0, got {self.visibility_tol}")


@dataclass(frozen=True, eq=False)
class StillReference:
    """One time's frames as the comparison sees them, per rig camera (None: no frame)."""

    time_index: int
    greys: tuple[NDArray[np.float32] | None, ...]
    """Grey levels on the compared grid (:func:`grey_image`)."""
    levels: tuple[float, ...]
    """Each frame's exposure: the median grey of its static scene (0: unknown)."""
    masks: tuple[Mask | None, ...]
    """The time's final foreground masks on the compared grid."""


@dataclass(frozen=True, eq=False)
class StillSnapshot:
    """The back-end's densified foreground of one time, with what a task compares it by."""

    reference: StillReference
    cloud: PointCloud
    pixels: NDArray[np.int64]
    """(N, cameras) flat index of each point's pixel on the compared grid of each camera,
    -1 outside its image (:func:`snapshot_pixels`)."""
    seen: NDArray[np.bool_]
    """(N, cameras) whether the camera saw the point at the snapshot's time."""

    @property
    def time_index(self) -> int:
        return self.reference.time_index


@dataclass(frozen=True, eq=False)
class StillPlan:
    """What one task densifies and what it keeps of the snapshot."""

    dense_masks: tuple[Mask | None, ...]
    """Per rig camera, the mask pixels to densify (the masks' resolution)."""
    kept: PointCloud
    """The snapshot's points kept (to be labelled by the task's masks)."""
    share: float
    """Share of the task's mask pixels that are still (not densified)."""
    snapshot_time: int
    """Time index of the snapshot."""


def _grid(mask: Mask, config: StillConfig) -> tuple[int, int]:
    h, w = mask.shape[:2]
    return max(1, round(w / config.downsample)), max(1, round(h / config.downsample))


def _grow(mask: Mask, radius: int) -> Mask:
    if radius <= 0 or not mask.any():
        return mask
    return np.asarray(cv2.dilate(mask.view(np.uint8), disk(radius)), bool)


def moved_objects(mask: Mask, before: Mask, min_iou: float) -> Mask:
    """The connected parts of ``mask`` (8-connected) whose outline overlaps their outline
    in ``before`` (the parts of ``before`` they touch) by less than ``min_iou``."""
    out = np.zeros_like(mask)
    if min_iou <= 0 or not mask.any():
        return out
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    _, old_labels, old_stats, _ = cv2.connectedComponentsWithStats(
        before.view(np.uint8), connectivity=8
    )
    for k in range(1, n):
        x, y, bw, bh = (int(v) for v in stats[k, :4])
        part = labels[y : y + bh, x : x + bw] == k
        touched = np.unique(old_labels[y : y + bh, x : x + bw][part])
        touched = touched[touched > 0]
        if not len(touched):
            out[y : y + bh, x : x + bw] |= part
            continue
        # The box of the part and of the old parts it touches.
        xs = [x, *(int(old_stats[j, 0]) for j in touched)]
        ys = [y, *(int(old_stats[j, 1]) for j in touched)]
        xe = [x + bw, *(int(old_stats[j, 0] + old_stats[j, 2]) for j in touched)]
        ye = [y + bh, *(int(old_stats[j, 1] + old_stats[j, 3]) for j in touched)]
        box = (slice(min(ys), max(ye)), slice(min(xs), max(xe)))
        now = labels[box] == k
        old = np.isin(old_labels[box], touched)
        union = np.count_nonzero(now | old)
        if np.count_nonzero(now & old) < min_iou * union:
            out[box] |= now
    return out


def _solid(moving: Mask, config: StillConfig) -> Mask:
    """``moving`` (on the compared grid) without its slivers (an outline that moved by a
    pixel: opened over 3 x 3) and its parts of fewer than ``min_change_px`` pixels: what is
    not worth a box of the dense stage."""
    if not moving.any():
        return moving
    opened = cv2.morphologyEx(moving.view(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    if n <= 1:
        return np.zeros_like(moving)
    big = stats[:, cv2.CC_STAT_AREA] >= config.min_change_px
    big[0] = False
    return np.asarray(big[labels], bool)


def grey_image(
    image: NDArray[Any], mask: Mask, config: StillConfig
) -> tuple[NDArray[np.float32], float]:
    """A frame (BGR, any resolution) as the comparison sees it: grey on the compared grid (the
    resolution of its foreground ``mask`` over ``downsample``), blurred over ``blur_px``, and
    its exposure: the median grey of the pixels outside the mask (the static scene tells the
    camera's gain on either node; 0 when the mask leaves too little outside)."""
    size = _grid(mask, config)
    small = downscale(np.asarray(image, np.uint8), size)  # the models' reduction
    if small.ndim == 3 and small.shape[2] == 3:
        small = np.asarray(cv2.cvtColor(small, cv2.COLOR_BGR2GRAY), np.uint8)
    grey = np.asarray(cv2.blur(small.astype(np.float32), (config.blur_px,) * 2), np.float32)
    outside = ~resize_mask(mask, size)
    level = float(np.median(grey[outside])) if np.count_nonzero(outside) >= 64 else 0.0
    return grey, level


def reference_of(
    time_index: int,
    images: Sequence[NDArray[Any] | None],
    masks: Sequence[Mask | None],
    config: StillConfig,
) -> StillReference:
    """The comparison's view of one time: its frames (any resolution) and final masks."""
    greys: list[NDArray[np.float32] | None] = []
    levels: list[float] = []
    small: list[Mask | None] = []
    for im, m in zip(images, masks, strict=True):
        if m is None or im is None:
            greys.append(None)
            levels.append(0.0)
            small.append(None)
            continue
        grey, level = grey_image(im, m, config)
        greys.append(grey)
        levels.append(level)
        small.append(resize_mask(m, _grid(m, config)))
    return StillReference(
        time_index=time_index, greys=tuple(greys), levels=tuple(levels), masks=tuple(small)
    )


def changed_pixels(
    grey: NDArray[np.float32],
    reference: NDArray[np.float32],
    config: StillConfig,
    gain: float = 1.0,
) -> Mask:
    """Pixels of the compared grid whose grey level (times ``gain``: the reference's
    exposure over the frame's) moved by more than ``change_threshold`` since ``reference``,
    grown by ``margin_px`` (the masks' pixels)."""
    moved = np.abs(grey * np.float32(gain) - reference) > config.change_threshold
    if config.min_change_px > 1 and moved.any():
        _, labels, stats, _ = cv2.connectedComponentsWithStats(moved.view(np.uint8), connectivity=8)
        big = stats[:, cv2.CC_STAT_AREA] >= config.min_change_px
        big[0] = False
        moved = big[labels]
    return _grow(moved, round(config.margin_px / config.downsample))


def snapshot_pixels(
    points3D: NDArray[np.float64],
    cameras: Sequence[Camera],
    reference: StillReference,
    config: StillConfig,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """(N, cameras) flat pixel index on the compared grid of each point in each camera (at
    the masks' resolution; -1 outside its image), and whether the camera sees it: its depth
    within ``visibility_tol`` of the nearest point's at that pixel (the points' own depth
    map)."""
    out = np.full((len(points3D), len(cameras)), -1, np.int64)
    seen = np.zeros(out.shape, bool)
    for c, (cam, grey) in enumerate(zip(cameras, reference.greys, strict=True)):
        if grey is None or not len(points3D):
            continue
        h, w = grey.shape
        small = cam.resized(w, h)
        uv, depth = small.project(points3D)
        ok = (depth > 0) & small.in_image(uv)
        if not ok.any():
            continue
        u = np.clip(np.rint(uv[ok, 0]).astype(np.int64), 0, w - 1)
        v = np.clip(np.rint(uv[ok, 1]).astype(np.int64), 0, h - 1)
        nearest = depth_map(points3D[ok], small, fill_px=1)[v, u]
        idx = np.flatnonzero(ok)
        out[idx, c] = v * w + u
        seen[idx, c] = depth[ok] <= nearest * (1.0 + config.visibility_tol)
    return out, seen


def make_snapshot(
    time_index: int,
    cloud: PointCloud,
    images: Sequence[NDArray[Any] | None],
    masks: Sequence[Mask | None],
    cameras: Sequence[Camera],
    config: StillConfig,
) -> StillSnapshot:
    """The snapshot of ``cloud``, the foreground of the frames ``images`` (masks ``masks``
    at the resolution of ``cameras``) densified."""
    ref = reference_of(time_index, images, masks, config)
    pixels, seen = snapshot_pixels(np.asarray(cloud.points3D, np.float64), cameras, ref, config)
    return StillSnapshot(reference=ref, cloud=cloud, pixels=pixels, seen=seen)


def plan_still(
    masks: Sequence[Mask | None],
    current: StillReference,
    snapshot: StillSnapshot,
    config: StillConfig,
) -> StillPlan | None:
    """What a task with ``masks`` and frames ``current`` densifies and keeps of
    ``snapshot`` (module docstring, steps 1-3); None (densify everything) when less than
    ``min_share`` of its mask pixels are still."""
    ref = snapshot.reference
    if len(ref.greys) != len(masks):
        return None
    dense: list[Mask | None] = []
    n = len(snapshot.cloud)
    still_votes = np.zeros(n, np.int32)
    changed_votes = np.zeros(n, np.int32)
    outside_votes = np.zeros(n, np.int32)
    total = 0
    still_total = 0
    margin = round(config.margin_px / config.downsample)
    for c, m in enumerate(masks):
        g, g0, m0 = current.greys[c], ref.greys[c], ref.masks[c]
        if m is None or g is None or g0 is None or m0 is None or g.shape != g0.shape:
            dense.append(m)
            if m is not None:
                total += int(np.count_nonzero(resize_mask(m, _grid(m, config))))
            continue
        # On the compared grid (a quarter of the masks' pixels at the default downsample).
        grid = (g.shape[1], g.shape[0])
        mg = resize_mask(m, grid)
        level, level0 = current.levels[c], ref.levels[c]
        gain = level0 / level if level > 1.0 and level0 > 1.0 else 1.0
        changed = changed_pixels(g, g0, config, gain)
        moved = moved_objects(mg, m0, config.min_outline_iou)
        moving = _solid(mg & ~(m0 & ~changed & ~moved), config)
        still = mg & ~moving
        total += int(np.count_nonzero(mg))
        still_total += int(np.count_nonzero(still))
        dense.append(m & resize_mask(_grow(moving, margin), (m.shape[1], m.shape[0])))
        at = snapshot.pixels[:, c]
        inside = at >= 0
        if not inside.any():
            continue
        pix = at[inside]
        # Outside the task's mask (grown by the margin): the point is not where the
        # camera sees the object now (it moved along another camera's line of sight).
        outside_votes[inside] += ~_grow(mg, margin + 1).ravel()[pix]
        sees = snapshot.seen[inside, c]
        # On the grid a mask's outline is a pixel off either way: grown by one.
        still_votes[inside] += sees & _grow(still, 1).ravel()[pix]
        changed_votes[inside] += sees & (changed | moved).ravel()[pix]
    share = still_total / total if total else 0.0
    if share < config.min_share:
        return None
    keep = (still_votes >= 1) & (changed_votes == 0) & (outside_votes <= 1)
    if np.count_nonzero(keep) < config.min_kept * share * n:
        return None
    return StillPlan(
        dense_masks=tuple(dense),
        kept=snapshot.cloud.select(keep),
        share=share,
        snapshot_time=snapshot.time_index,
    )


class StillCache:
    """The front-end's newest snapshot (module docstring). Thread-safe: the back-end pushes
    while tasks plan."""

    def __init__(self, config: StillConfig) -> None:
        self.config = config
        self._snapshot: StillSnapshot | None = None
        self._lock = threading.Lock()
        self.snapshots = 0
        """Snapshots received."""
        self._uses = 0

    def set_snapshot(self, snapshot: StillSnapshot | None) -> None:
        with self._lock:
            self._snapshot = snapshot
            self._uses = 0
            if snapshot is not None:
                self.snapshots += 1

    @property
    def snapshot_time(self) -> int | None:
        snap = self._snapshot
        return None if snap is None else snap.time_index

    def plan(
        self,
        images: Sequence[NDArray[Any] | None],
        fg_masks: Sequence[Mask | None],
        time_index: int,
    ) -> StillPlan | None:
        """What a task of frames ``images`` and masks ``fg_masks`` densifies and keeps;
        None: everything (no snapshot, too little still)."""
        with self._lock:
            snap = self._snapshot
        if snap is None:
            return None
        current = reference_of(time_index, images, fg_masks, self.config)
        plan = plan_still(fg_masks, current, snap, self.config)
        if plan is not None:
            with self._lock:
                if self._snapshot is snap:
                    self._uses += 1
        return plan

    def uses(self) -> tuple[int, int] | None:
        """The newest snapshot's time index and how many tasks used it (None: none held)."""
        with self._lock:
            snap = self._snapshot
            return None if snap is None else (snap.time_index, self._uses)


__all__ = [
    "StillCache",
    "StillConfig",
    "StillPlan",
    "StillReference",
    "StillSnapshot",
    "changed_pixels",
    "grey_image",
    "make_snapshot",
    "plan_still",
    "reference_of",
    "snapshot_pixels",
]
