"""Grouping foreground pixels into objects (the paper's k-means with an automatic k).

The paper clusters the moving pixels with k-means so that actors far apart get separate, small
masks. Measured on synthetic scenes with exact masks, k-means on pixel coordinates alone splits
tall silhouettes, merges a small actor into a large one's cluster, and its silhouette score
prefers too few clusters when three actors are unevenly spaced (72 % of images right on the
8-camera ring preset). Here connected components are the atoms:

1. 8-connected components of the clean mask; a region is never split (two actors who overlap
   in an image are one object in that view; the visual hull separates them in 3D);
2. fragments closer than ``merge_gap_fraction`` of the image diagonal (a foot cut off by a
   mask hole) join one object (single linkage on the gaps between region outlines), and
   small fragments (< ``fragment_fraction`` of the largest object) join the nearest object
   within ``fragment_gap_fraction``;
3. when more than ``max_objects`` groups remain, coarser groupings are proposed by k-means on
   the foreground pixel coordinates (k = 2..k_max; each region joins the cluster holding most
   of its pixels, clusters sharing a region merge) and by further single linkage; the grouping
   with the best mean silhouette score (on a pixel subsample) wins.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.scene._kernels import outline_gaps
from edgerecon.types import Mask

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ObjectConfig:
    """Parameters of the object clustering."""

    max_objects: int = 6
    """Largest number of objects (k_max of the k-means search)."""
    merge_gap_fraction: float = 0.015
    """Regions closer than this share of the image diagonal are fragments of one object."""
    fragment_fraction: float = 0.05
    """A group smaller than this share of the largest object ..."""
    fragment_gap_fraction: float = 0.06
    """... joins the nearest object within this share of the image diagonal."""
    sample_size: int = 1500
    """Foreground pixels sampled for k-means."""
    silhouette_sample: int = 300
    """Of those, pixels used for the silhouette score (its cost grows with the square)."""
    roi_margin_fraction: float = 0.1
    """Each object's region of interest is its bounding box grown by this share of its larger
    side on every side ..."""
    roi_margin_px: int = 8
    """... and by at least this many pixels."""
    seed: int = 0
    """Seed of the pixel subsample and of k-means (results are deterministic)."""

    def __post_init__(self) -> None:
        if not isinstance(self.max_objects, int | np.integer) or self.max_objects < 1:
            raise ValueError(
                f"ObjectConfig.max_objects must be an integer >= 1, got {self.max_objects!r}"
            )
        if not 0.0 <= self.merge_gap_fraction <= 1.0:
            raise ValueError(
                f"ObjectConfig.merge_gap_fraction must be in [0, 1], got {self.merge_gap_fraction}"
            )
        if self.silhouette_sample < 10:
            raise ValueError(
                f"ObjectConfig.silhouette_sample must be >= 10, got {self.silhouette_sample}"
            )
        for name in ("fragment_fraction", "fragment_gap_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"ObjectConfig.{name} must be in [0, 1], got {getattr(self, name)}"
                )
        if self.sample_size < 10:
            raise ValueError(f"ObjectConfig.sample_size must be >= 10, got {self.sample_size}")
        if self.roi_margin_fraction < 0 or self.roi_margin_px < 0:
            raise ValueError(
                "ObjectConfig.roi_margin_fraction and roi_margin_px must be >= 0, got "
                f"{self.roi_margin_fraction}, {self.roi_margin_px}"
            )


#: Above this many components the single-linkage candidates are skipped (k-means only).
_MAX_LINKAGE_COMPONENTS = 40

BBox = tuple[int, int, int, int]  # (x, y, width, height) in pixels


@dataclass(frozen=True, kw_only=True)
class ForegroundObject:
    """One object (group of foreground regions) in one image."""

    id: int
    """Object id within the image, 1..num_objects (0 is the background)."""
    area_px: int
    """Number of foreground pixels."""
    bbox: BBox
    """Tight bounding box (x, y, width, height)."""
    roi: BBox
    """Bounding box grown by the configured margin, clipped to the image."""
    centroid: tuple[float, float]
    """Mean pixel (x, y)."""

    def to_dict(self) -> dict[str, object]:
        return {
            "id": self.id,
            "area_px": self.area_px,
            "bbox": list(self.bbox),
            "roi": list(self.roi),
            "centroid": [round(self.centroid[0], 2), round(self.centroid[1], 2)],
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class ObjectSegmentation:
    """The objects of one image: a label image and per-object summaries."""

    labels: NDArray[np.int32]
    """(H, W) int32: 0 = background, k = object k."""
    objects: tuple[ForegroundObject, ...]
    """The objects, ids 1..k in order of decreasing area."""
    silhouette: float
    """Mean silhouette score of the chosen grouping (NaN for fewer than 2 objects)."""

    @property
    def num_objects(self) -> int:
        return len(self.objects)

    @property
    def foreground(self) -> Mask:
        return self.labels > 0

    def object_mask(self, object_id: int) -> Mask:
        """(H, W) mask of one object."""
        return self.labels == object_id

    def roi_mask(self) -> Mask:
        """(H, W) union of the objects' regions of interest (all False when empty)."""
        out = np.zeros(self.labels.shape, bool)
        for o in self.objects:
            x, y, w, h = o.roi
            out[y : y + h, x : x + w] = True
        return out


def _roi(bbox: BBox, shape: tuple[int, int], config: ObjectConfig) -> BBox:
    x, y, w, h = bbox
    m = max(config.roi_margin_px, round(config.roi_margin_fraction * max(w, h)))
    x0, y0 = max(0, x - m), max(0, y - m)
    x1, y1 = min(shape[1], x + w + m), min(shape[0], y + h + m)
    return (x0, y0, x1 - x0, y1 - y0)


def pairwise_distances(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, n) Euclidean distances between the rows of ``points``."""
    return np.sqrt(np.maximum(_sqdist(points, points), 0.0))


def silhouette_score(
    points: NDArray[np.float64],
    labels: NDArray[np.int64],
    distances: NDArray[np.float64] | None = None,
) -> float:
    """Mean silhouette coefficient of a labelling (Rousseeuw 1987); NaN for < 2 clusters.

    Points alone in their cluster score 0, as in scikit-learn. ``distances``: the points'
    ``pairwise_distances`` when several labellings of the same points are scored.
    """
    uniq, lab = np.unique(labels, return_inverse=True)
    k = len(uniq)
    if k < 2 or len(points) < 3:
        return float("nan")
    d = pairwise_distances(points) if distances is None else distances
    onehot = np.zeros((len(points), k))
    onehot[np.arange(len(points)), lab] = 1.0
    counts = onehot.sum(axis=0)
    sums = d @ onehot  # (n, k) total distance to each cluster
    own = counts[lab]
    a = sums[np.arange(len(points)), lab] / np.maximum(own - 1, 1)
    mean_other = sums / counts
    mean_other[np.arange(len(points)), lab] = np.inf
    b = mean_other.min(axis=1)
    s = np.where(own > 1, (b - a) / np.maximum(np.maximum(a, b), 1e-12), 0.0)
    return float(s.mean())


def _sqdist(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    return (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T


def _group_components(
    coords: NDArray[np.float32],
    comp: NDArray[np.int64],
    num_comp: int,
    k: int,
    rng_seed: int,
    sample: NDArray[np.int64],
) -> NDArray[np.int64]:
    """Group id per component (0-based) for one k-means run with k clusters."""
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 30, 0.5)
    cv2.setRNGSeed(rng_seed)
    kmeans: Any = cv2.kmeans  # OpenCV's stubs differ between releases on this overload
    _, _, centers = kmeans(coords[sample], k, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
    cluster = np.argmin(_sqdist(coords.astype(np.float64), centers.astype(np.float64)), axis=1)
    share = np.bincount(comp * k + cluster, minlength=num_comp * k).reshape(num_comp, k)
    share = share / np.maximum(share.sum(axis=1, keepdims=True), 1)
    # Union-find over clusters: a component with a large share in two clusters ties them.
    parent = list(range(k))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for row in share:
        linked = np.flatnonzero(row >= 0.2)
        for j in linked[1:]:
            parent[find(int(j))] = find(int(linked[0]))
    majority = np.argmax(share, axis=1)
    roots = np.array([find(int(c)) for c in majority])
    _, group = np.unique(roots, return_inverse=True)
    return group.astype(np.int64)


def _component_gaps(cc: NDArray[np.int32], num_comp: int) -> NDArray[np.float64]:
    """(n, n) smallest pixel distance between the outlines of every pair of components."""
    # RETR_LIST, not RETR_EXTERNAL: a component inside another one's hole (a person seen
    # through the arms of another) has only an inner outline; without it that component had
    # no points and the whole run died on an empty reduction.
    contours, _ = cv2.findContours(
        (cc > 0).astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE
    )
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.int32)
    owner = cc[pts[:, 1], pts[:, 0]].astype(np.int64) - 1
    missing = np.setdiff1d(np.arange(num_comp), owner)
    for i in missing:  # never expected; any pixel of the component will do
        ys, xs = np.nonzero(cc == i + 1)
        pts = np.vstack([pts, np.array([[xs[0], ys[0]]], np.int32)])
        owner = np.append(owner, i)
    # Every pair of outline points of two components, compiled (a k-d tree per component
    # took ~5 ms per mask at 480x270; the same distances).
    return outline_gaps(pts, owner, num_comp)


def _single_linkage(gaps: NDArray[np.float64]) -> list[tuple[float, NDArray[np.int64]]]:
    """Partitions of the components by single-linkage merging in order of increasing gap:
    [(gap at which this partition appears, group id per component), ...], finest first."""
    n = len(gaps)
    group = np.arange(n)
    out = [(0.0, group.copy())]
    iu = np.triu_indices(n, 1)
    order = np.argsort(gaps[iu], kind="stable")
    for e in order:
        i, j = iu[0][e], iu[1][e]
        gi, gj = group[i], group[j]
        if gi == gj:
            continue
        group[group == gj] = gi
        _, canon = np.unique(group, return_inverse=True)
        out.append((float(gaps[i, j]), canon.astype(np.int64)))
    return out


def _absorb_fragments(
    group: NDArray[np.int64],
    gaps: NDArray[np.float64],
    areas: NDArray[np.intp],
    fraction: float,
    max_gap: float,
) -> NDArray[np.int64]:
    """Merge each group smaller than ``fraction`` of the largest into the nearest group
    within ``max_gap`` pixels (a hand or a foot cut off from its body), smallest first."""
    group = group.copy()
    while True:
        ids = np.unique(group)
        if len(ids) < 2:
            return group
        area = np.array([areas[group == g].sum() for g in ids])
        small = np.flatnonzero(area < fraction * area.max())
        merged_any = False
        for i in small[np.argsort(area[small])]:
            mine = group == ids[i]
            others = ~mine
            if not others.any():
                break
            d = gaps[np.ix_(mine, others)]
            j = np.unravel_index(np.argmin(d), d.shape)
            if d[j] <= max_gap:
                group[mine] = group[np.flatnonzero(others)[j[1]]]
                merged_any = True
                break
        if not merged_any:
            _, canon = np.unique(group, return_inverse=True)
            return canon.astype(np.int64)


def _group(
    m: Mask,
    cc: NDArray[np.int32],
    num_comp: int,
    xs: NDArray[np.intp],
    ys: NDArray[np.intp],
    comp: NDArray[np.int64],
    config: ObjectConfig,
) -> tuple[NDArray[np.int64], float]:
    """Group id per component and the grouping's silhouette score (see module docstring)."""
    diag = float(np.hypot(*m.shape))
    merge_gap = config.merge_gap_fraction * diag
    linkage: list[tuple[float, NDArray[np.int64]]] = []
    merged = np.arange(num_comp, dtype=np.int64)
    if num_comp <= _MAX_LINKAGE_COMPONENTS:
        gaps = _component_gaps(cc, num_comp)
        linkage = _single_linkage(gaps)
        merged = next(g for gap, g in reversed(linkage) if gap <= merge_gap)
        merged = _absorb_fragments(
            merged,
            gaps,
            np.bincount(comp, minlength=num_comp),
            config.fragment_fraction,
            config.fragment_gap_fraction * diag,
        )
    coords = np.stack([xs, ys], axis=1).astype(np.float32)
    rng = np.random.default_rng(config.seed)
    size = min(config.sample_size, len(coords))
    sample = np.sort(rng.choice(len(coords), size=size, replace=False))
    score_at = sample[:: max(1, size // config.silhouette_sample)]
    pts = coords[score_at].astype(np.float64)
    dist = pairwise_distances(pts)  # once for every candidate grouping
    num_groups = int(merged.max()) + 1
    if num_groups <= config.max_objects:
        score = (
            silhouette_score(pts, merged[comp[score_at]], dist) if num_groups > 1 else float("nan")
        )
        return merged, score
    # More separate regions than objects allowed: k-means on the pixel coordinates proposes
    # coarser groupings (k = 2..k_max), as do the single-linkage levels; the best silhouette
    # wins.
    candidates = [g for _, g in linkage if int(g.max()) + 1 <= config.max_objects]
    for k in range(2, config.max_objects + 1):
        if size <= k:
            break
        candidates.append(_group_components(coords, comp, num_comp, k, config.seed + k, sample))
    best, best_score = np.zeros(num_comp, np.int64), float("nan")
    tried: set[tuple[int, ...]] = set()
    for cand in candidates:
        _, group = np.unique(_coarsest(cand, merged), return_inverse=True)
        key = tuple(group.tolist())
        if int(group.max()) + 1 > config.max_objects or key in tried:
            continue
        tried.add(key)
        score = silhouette_score(pts, group[comp[score_at]], dist) if group.max() > 0 else -1.0
        if not score <= best_score:
            best, best_score = group.astype(np.int64), score
    return best, best_score


def find_objects(mask: Mask, config: ObjectConfig | None = None) -> ObjectSegmentation:
    """Group a clean foreground mask into objects (see the module docstring).

    An empty mask gives an empty segmentation (no objects), not an error.
    """
    config = config or ObjectConfig()
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise ValueError(f"find_objects expects a (H, W) mask, got shape {m.shape}")
    labels = np.zeros(m.shape, np.int32)
    if not m.any():
        return ObjectSegmentation(labels=labels, objects=(), silhouette=float("nan"))
    n, cc_ = cv2.connectedComponents(m.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    cc: NDArray[np.int32] = np.asarray(cc_, np.int32)
    num_comp = n - 1
    ys, xs = np.nonzero(m)
    comp = cc[ys, xs].astype(np.int64) - 1
    best_group = np.zeros(num_comp, np.int64)
    best_score = float("nan")
    if num_comp > 1 and config.max_objects > 1:
        best_group, best_score = _group(m, cc, num_comp, xs, ys, comp, config)
    # Relabel groups by decreasing area, 1..k.
    areas = np.bincount(best_group[comp], minlength=int(best_group.max()) + 1)
    order = np.argsort(-areas, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(1, len(order) + 1)
    lut = np.zeros(n, np.int32)
    lut[1:] = rank[best_group]
    labels = lut[cc]
    obj_of_pixel = lut[cc[ys, xs]]
    objects = []
    sort = np.argsort(obj_of_pixel, kind="stable")
    bounds = np.searchsorted(obj_of_pixel[sort], np.arange(1, len(order) + 2))
    for obj_id in range(1, len(order) + 1):
        sel = sort[bounds[obj_id - 1] : bounds[obj_id]]
        if len(sel) == 0:
            continue
        ox, oy = xs[sel], ys[sel]
        x0, y0 = int(ox.min()), int(oy.min())
        bbox = (x0, y0, int(ox.max()) - x0 + 1, int(oy.max()) - y0 + 1)
        objects.append(
            ForegroundObject(
                id=obj_id,
                area_px=len(sel),
                bbox=bbox,
                roi=_roi(bbox, (m.shape[0], m.shape[1]), config),
                centroid=(float(ox.mean()), float(oy.mean())),
            )
        )
    if len(objects) < 2:
        best_score = float("nan")
    return ObjectSegmentation(labels=labels, objects=tuple(objects), silhouette=best_score)


def _coarsest(a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.int64]:
    """The finest partition coarser than both ``a`` and ``b`` (join: components of the union
    of their 'same group' relations), as a group id per element (the smallest member's index:
    union-find over the few components of one image)."""
    n = len(a)
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for labels in (a.tolist(), b.tolist()):
        first: dict[int, int] = {}
        for i, g in enumerate(labels):
            j = first.setdefault(g, i)
            ri, rj = find(i), find(j)
            if ri != rj:
                parent[max(ri, rj)] = min(ri, rj)
    return np.array([find(i) for i in range(n)], np.int64)
