"""What the viewer draws: point colourings and the decimation to a point budget.

Pure NumPy on ``PointCloud`` objects (no viewer library), so the choices are tested alone.

Colourings (``COLORINGS``; :func:`available_colorings` lists those a cloud supports):

* ``rgb``: the points' own colours (grey where a cloud has none);
* ``fg_bg``: foreground (labels >= 1) orange, background (label 0) blue-grey, unknown magenta;
* ``object``: background light grey, object k a fixed colour of a 10-colour palette (k mod 10),
  unknown magenta;
* ``bg_version``: background points by the version of the background rebuild they come from
  (``attributes["bg_version"]``; oldest dark purple to newest yellow, viridis-like; version 0 =
  the initial reconstruction), foreground points dark grey;
* ``inferred``: measured points blue, inferred points (``attributes["inferred"] == 1``) red;
  offered only when the cloud has inferred points (every PLY edgerecon writes has the
  attribute, mostly all 0).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from edgerecon.types import BACKGROUND_LABEL, UNKNOWN_LABEL, Colors, PointCloud

#: Colouring names, in the order the viewer offers them, with their menu labels.
COLORINGS: dict[str, str] = {
    "rgb": "RGB",
    "fg_bg": "foreground / background",
    "object": "object id",
    "bg_version": "background version",
    "inferred": "measured / inferred",
}
#: Per-point attribute marking inferred (not measured) points: uint8 0/1.
INFERRED = "inferred"
#: Per-point attribute with the background version a point comes from (scene.merge).
BG_VERSION = "bg_version"

_GREY = np.array([150, 150, 150], np.uint8)
_FOREGROUND = np.array([255, 140, 0], np.uint8)
_BACKGROUND = np.array([110, 130, 160], np.uint8)
_UNKNOWN = np.array([230, 0, 230], np.uint8)
_LIGHT_GREY = np.array([200, 200, 200], np.uint8)
_DARK_GREY = np.array([70, 70, 70], np.uint8)
_MEASURED = np.array([40, 110, 220], np.uint8)
_INFERRED_COLOR = np.array([230, 40, 40], np.uint8)
#: Tableau-10: distinct colours for object ids 1, 2, ... (k - 1 mod 10).
_PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    np.uint8,
)
#: Viridis at 5 stops (dark purple -> yellow), interpolated linearly.
_VIRIDIS = np.array(
    [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float64
)


def available_colorings(cloud: PointCloud) -> list[str]:
    """The colourings that mean something for ``cloud`` (``inferred`` only with inferred
    points, label-based ones only with labels)."""
    names = ["rgb"]
    if cloud.labels is not None:
        names += ["fg_bg", "object"]
        if BG_VERSION in cloud.attributes:
            names.append("bg_version")
    if INFERRED in cloud.attributes and np.any(np.asarray(cloud.attributes[INFERRED]) != 0):
        names.append("inferred")
    return names


def colorize(cloud: PointCloud, coloring: str) -> Colors:
    """(N, 3) uint8 RGB colours of ``cloud``'s points under ``coloring`` (see module
    docstring). A colouring the cloud cannot support (no labels, no attribute) falls back to
    ``rgb``; an unknown name raises ValueError."""
    if coloring not in COLORINGS:
        raise ValueError(f"coloring must be one of {list(COLORINGS)}, got {coloring!r}")
    n = len(cloud)
    if coloring not in available_colorings(cloud) or coloring == "rgb":
        if cloud.colors is None:
            return np.tile(_GREY, (n, 1))
        return np.ascontiguousarray(cloud.colors, dtype=np.uint8)
    if coloring == "inferred":
        inferred = np.asarray(cloud.attributes[INFERRED]) != 0
        return np.where(inferred[:, None], _INFERRED_COLOR, _MEASURED).astype(np.uint8)
    assert cloud.labels is not None
    labels = cloud.labels
    out = np.empty((n, 3), np.uint8)
    if coloring == "fg_bg":
        out[:] = _UNKNOWN
        out[labels == BACKGROUND_LABEL] = _BACKGROUND
        out[labels >= 1] = _FOREGROUND
        return out
    if coloring == "object":
        out[:] = _UNKNOWN
        out[labels == BACKGROUND_LABEL] = _LIGHT_GREY
        fg = labels >= 1
        out[fg] = _PALETTE[(labels[fg] - 1) % len(_PALETTE)]
        return out
    # bg_version
    versions = np.asarray(cloud.attributes[BG_VERSION]).astype(np.int64)
    out[:] = _DARK_GREY
    bg = labels == BACKGROUND_LABEL
    if bg.any():
        out[bg] = version_colors(versions[bg], int(versions[bg].max()))
    out[labels == UNKNOWN_LABEL] = _UNKNOWN
    return out


def version_colors(versions: NDArray[np.integer], newest: int) -> Colors:
    """Viridis-like colours of background versions 0..``newest`` (newest = yellow)."""
    x = np.zeros(len(versions)) if newest <= 0 else np.clip(versions / newest, 0.0, 1.0)
    pos = x * (len(_VIRIDIS) - 1)
    i = np.minimum(pos.astype(np.int64), len(_VIRIDIS) - 2)
    w = (pos - i)[:, None]
    return np.rint((1 - w) * _VIRIDIS[i] + w * _VIRIDIS[i + 1]).astype(np.uint8)


def decimate(cloud: PointCloud, budget: int) -> NDArray[np.int64]:
    """Indices of at most ``budget`` points of ``cloud`` to draw, deterministic.

    The foreground (labels >= 1) is what changes and what people look at: it keeps at
    least half the budget (all of it when it is smaller) and the background fills the rest.
    Within each part the points are an even stride through the cloud (fusion writes points
    in voxel order, so a stride thins them evenly in space), so consecutive tasks keep the
    same background points and nothing flickers.
    """
    if budget < 1:
        raise ValueError(f"budget must be >= 1, got {budget}")
    n = len(cloud)
    if n <= budget:
        return np.arange(n, dtype=np.int64)
    if cloud.labels is None:
        return _stride(np.arange(n, dtype=np.int64), budget)
    fg = np.flatnonzero(cloud.labels >= 1)
    rest = np.flatnonzero(cloud.labels < 1)
    keep_fg = min(len(fg), max(budget // 2, round(budget * len(fg) / n)))
    keep_rest = min(len(rest), budget - keep_fg)
    keep_fg = min(len(fg), budget - keep_rest)
    return np.sort(np.concatenate([_stride(fg, keep_fg), _stride(rest, keep_rest)]))


def _stride(index: NDArray[np.int64], k: int) -> NDArray[np.int64]:
    if k >= len(index):
        return index
    if k <= 0:
        return index[:0]
    pick = (np.arange(k, dtype=np.int64) * len(index)) // k
    return index[pick]


def point_spacing(points: NDArray[np.float64], sample: int = 2000) -> float:
    """Median nearest-neighbour distance of (a deterministic sample of) ``points``: the
    natural size of a drawn point. 0 for fewer than two points."""
    if len(points) < 2:
        return 0.0
    from scipy.spatial import cKDTree

    sub = points[_stride(np.arange(len(points), dtype=np.int64), sample)]
    d, _ = cKDTree(points).query(sub, k=2)
    return float(np.median(d[:, 1]))


def unit_to_metres(unit: str) -> float:
    """Factor from a rig's length unit to metres (the viewer works in metres so that its
    camera controls and point sizes behave the same for every rig); 1 for unknown units."""
    return {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "um": 1e-6, "km": 1000.0}.get(
        unit.strip().lower(), 1.0
    )
