"""Foreground / object mask scores against ground-truth object-id masks (synthetic scenes).

* ``mask_iou(pred, gt)``: intersection over union of two boolean masks (both empty: 1).
* ``score_masks(pred, gt_labels)``: binary foreground IoU, precision and recall of
  ``pred > 0`` against ``gt_labels > 0``, and per ground-truth object the IoU with the
  predicted object matched to it. Predicted object ids are arbitrary (clustering numbers
  objects as it likes), so they are matched to ground-truth ids one-to-one by the Hungarian
  algorithm on IoU; ``match="identity"`` compares equal ids instead. An unmatched ground-truth
  object scores 0.
* ``score_mask_set(preds, gts)``: the same over several images (cameras and/or timestamps):
  intersections and unions are summed over images, each image matched on its own.
* ``labels_to_view(camera, labels, scale)``: a full-resolution (distorted) label mask mapped
  onto a task's ``View`` (undistorted, rescaled), nearest-neighbour so ids survive.

Labels: 0 = background; k >= 1 = object k; negative values (unknown) count as background.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from edgerecon.geometry.camera import Camera
from edgerecon.views import resize_mask_smooth

LabelMask = NDArray[np.integer[Any]] | NDArray[np.bool_]


def at_resolution(pred: NDArray[Any], shape: tuple[int, ...]) -> NDArray[Any]:
    """A predicted mask or label image (e.g. at the scene stage's working resolution) brought
    to the ``(H, W)`` of a ground-truth mask: boolean masks are resized smoothly (bilinear,
    0.5 threshold), label images by nearest neighbour. Same shape: returned as is."""
    m = np.asarray(pred)
    h, w = int(shape[0]), int(shape[1])
    if m.shape[:2] == (h, w):
        return m
    if m.dtype == bool:
        return resize_mask_smooth(m, (w, h))
    return np.asarray(cv2.resize(m.astype(np.int32), (w, h), interpolation=cv2.INTER_NEAREST))


def _fit(pred: NDArray[Any], shape: tuple[int, ...]) -> NDArray[Any]:
    """``pred`` at ``shape`` when it is a reduced-resolution mask of the same aspect ratio."""
    m = np.asarray(pred)
    if m.ndim != 2 or m.shape == shape[:2]:
        return m
    h, w = shape[:2]
    if abs(m.shape[0] / h - m.shape[1] / w) > 0.01 + 1.0 / min(m.shape):
        return m  # not the same aspect: let the caller's shape check say so
    return at_resolution(m, shape)


def mask_iou(pred: NDArray[Any], gt: NDArray[Any]) -> float:
    """IoU of the non-zero pixels of two masks (both empty: 1.0). A prediction at a reduced
    resolution with the truth's aspect ratio is first brought to the truth's
    (``at_resolution``)."""
    g = _binary(gt)
    p = _binary(_fit(pred, g.shape))
    if p.shape != g.shape:
        raise ValueError(f"mask shapes differ: predicted {p.shape}, ground truth {g.shape}")
    union = int(np.count_nonzero(p | g))
    if union == 0:
        return 1.0
    return int(np.count_nonzero(p & g)) / union


def _binary(mask: NDArray[Any]) -> NDArray[np.bool_]:
    m = np.asarray(mask)
    return m if m.dtype == bool else m > 0


def _labels(mask: NDArray[Any]) -> NDArray[np.int64]:
    m = np.asarray(mask)
    if m.dtype == bool:
        return m.astype(np.int64)
    out = m.astype(np.int64)
    out[out < 0] = 0
    return out


@dataclass(frozen=True, kw_only=True)
class _Counts:
    """Confusion counts of one image: intersections of matched objects and their unions."""

    fg_inter: int
    fg_union: int
    pred_fg: int
    gt_fg: int
    inter: dict[int, int]
    union: dict[int, int]
    matching: dict[int, int]


@dataclass(frozen=True, kw_only=True)
class MaskScore:
    """Mask quality against ground truth (one image or summed over several)."""

    foreground_iou: float
    """IoU of predicted foreground (label > 0) and ground-truth foreground."""
    precision: float
    """Share of predicted foreground pixels that are ground-truth foreground (1 if none)."""
    recall: float
    """Share of ground-truth foreground pixels predicted as foreground (1 if none)."""
    object_iou: dict[int, float]
    """Per ground-truth object id: IoU with its matched predicted object (0 if unmatched)."""
    matching: dict[int, int]
    """Ground-truth id -> predicted id (single image; empty for a summed score)."""
    mean_object_iou: float
    """Mean of ``object_iou`` over the ground-truth objects present (1 if there are none)."""
    num_images: int = 1
    """Images the score sums over."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "foreground_iou": self.foreground_iou,
            "precision": self.precision,
            "recall": self.recall,
            "object_iou": {str(k): v for k, v in self.object_iou.items()},
            "matching": {str(k): v for k, v in self.matching.items()},
            "mean_object_iou": self.mean_object_iou,
            "num_images": self.num_images,
        }


def _counts(pred: NDArray[Any], gt: NDArray[Any], match: str) -> _Counts:
    g = _labels(gt)
    p = _labels(_fit(pred, g.shape))
    if p.shape != g.shape:
        raise ValueError(f"mask shapes differ: predicted {p.shape}, ground truth {g.shape}")
    if match not in ("hungarian", "identity"):
        raise ValueError(f"match must be 'hungarian' or 'identity', got {match!r}")
    np_, ng = int(p.max(initial=0)) + 1, int(g.max(initial=0)) + 1
    conf = np.bincount((g * np_ + p).ravel(), minlength=ng * np_).reshape(ng, np_)
    gt_area = conf.sum(axis=1)
    pred_area = conf.sum(axis=0)
    gt_fg = int(gt_area[1:].sum())
    pred_fg = int(pred_area[1:].sum())
    fg_inter = int(conf[1:, 1:].sum())
    fg_union = gt_fg + pred_fg - fg_inter
    gt_ids = [k for k in range(1, ng) if gt_area[k] > 0]
    pred_ids = [k for k in range(1, np_) if pred_area[k] > 0]
    inter = conf[1:, 1:].astype(np.float64)
    union = gt_area[1:, None] + pred_area[None, 1:] - conf[1:, 1:]
    matching: dict[int, int] = {}
    if match == "identity":
        matching = {k: k for k in gt_ids if k in pred_ids}
    elif gt_ids and pred_ids:
        iou = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
        gi = np.array(gt_ids) - 1
        pi = np.array(pred_ids) - 1
        rows, cols = linear_sum_assignment(-iou[np.ix_(gi, pi)])
        matching = {
            int(gi[r] + 1): int(pi[c] + 1)
            for r, c in zip(rows, cols, strict=True)
            if iou[gi[r], pi[c]] > 0
        }
    obj_inter, obj_union = {}, {}
    for k in gt_ids:
        if k in matching:
            j = matching[k]
            obj_inter[k] = int(conf[k, j])
            obj_union[k] = int(gt_area[k] + pred_area[j] - conf[k, j])
        else:
            obj_inter[k], obj_union[k] = 0, int(gt_area[k])
    return _Counts(
        fg_inter=fg_inter,
        fg_union=fg_union,
        pred_fg=pred_fg,
        gt_fg=gt_fg,
        inter=obj_inter,
        union=obj_union,
        matching=matching,
    )


def _score(counts: Sequence[_Counts]) -> MaskScore:
    fg_i = sum(c.fg_inter for c in counts)
    fg_u = sum(c.fg_union for c in counts)
    pred_fg = sum(c.pred_fg for c in counts)
    gt_fg = sum(c.gt_fg for c in counts)
    ids = sorted({k for c in counts for k in c.union})
    obj = {}
    for k in ids:
        u = sum(c.union.get(k, 0) for c in counts)
        obj[k] = sum(c.inter.get(k, 0) for c in counts) / u if u else 0.0
    return MaskScore(
        foreground_iou=fg_i / fg_u if fg_u else 1.0,
        precision=fg_i / pred_fg if pred_fg else 1.0,
        recall=fg_i / gt_fg if gt_fg else 1.0,
        object_iou=obj,
        matching=dict(counts[0].matching) if len(counts) == 1 else {},
        mean_object_iou=float(np.mean(list(obj.values()))) if obj else 1.0,
        num_images=len(counts),
    )


def score_masks(
    pred: LabelMask, gt_labels: LabelMask, *, match: Literal["hungarian", "identity"] = "hungarian"
) -> MaskScore:
    """Score a predicted mask (bool foreground or int object ids) against ground-truth object
    ids of the same shape (or a reduced-resolution prediction, see ``mask_iou``)."""
    return _score([_counts(pred, gt_labels, match)])


def score_mask_set(
    preds: Sequence[LabelMask],
    gts: Sequence[LabelMask],
    *,
    match: Literal["hungarian", "identity"] = "hungarian",
) -> MaskScore:
    """Score several images at once (IoUs from intersections and unions summed over images)."""
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} predicted masks for {len(gts)} ground-truth masks")
    if not preds:
        raise ValueError("no masks to score")
    return _score([_counts(p, g, match) for p, g in zip(preds, gts, strict=True)])


def labels_to_view(camera: Camera, labels: NDArray[Any], scale: float = 1.0) -> NDArray[Any]:
    """Map a full-resolution label mask of ``camera`` (distorted frame) onto the view at
    ``scale`` (``camera.scaled(scale).undistorted()``), nearest neighbour."""
    lab = np.asarray(labels)
    if lab.shape[:2] != (camera.height, camera.width):
        raise ValueError(
            f"camera {camera.name!r}: mask is {lab.shape[1]}x{lab.shape[0]}, frames are "
            f"{camera.width}x{camera.height}"
        )
    src = lab.astype(np.uint8) if lab.dtype == bool else lab
    if not camera.has_distortion:
        out = cv2.resize(src, camera.scaled(scale).size, interpolation=cv2.INTER_NEAREST)
    else:
        mx, my = camera.undistort_maps(scale)
        out = cv2.remap(src, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
    out = np.asarray(out)
    return out.astype(bool) if lab.dtype == bool else out.astype(lab.dtype)
