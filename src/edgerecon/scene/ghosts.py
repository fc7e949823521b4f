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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera
from edgerecon.types import DataError, DepthMap, Mask


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
        None if im is None or not config.texture_px else _local_contrast(im, config.texture_px)
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
            uv, d = other.project(points)
            seen = (d > 0) & other.in_image(uv)
            safe = np.where(seen[:, None], uv, 0.0)
            u = np.clip(np.rint(safe[:, 0]), 0, other.width - 1).astype(np.intp)
            v = np.clip(np.rint(safe[:, 1]), 0, other.height - 1).astype(np.intp)
            with np.errstate(invalid="ignore"):
                seen &= np.abs(o_depth[v, u] - d) < config.depth_tol_rel * d
            seen &= ~np.asarray(o_mask, bool)[v, u]
            same = _same_colour(here, o_colour[v, u], config)
            mine, theirs = contrasts[c], contrasts[o]
            if mine is not None and theirs is not None:
                a, b = mine[ys, xs], theirs[v, u]
                # Alike: within texture_tol, or within a factor 3 (contrast scales with the
                # surface's footprint, which differs between views).
                same &= np.abs(a - b) <= np.maximum(config.texture_tol, 2 / 3 * np.maximum(a, b))
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


def _local_contrast(
    image: NDArray[np.floating] | NDArray[np.uint8], size: int
) -> NDArray[np.float32]:
    """Grey-level standard deviation in a ``size`` x ``size`` box around each pixel."""
    im = np.asarray(image, np.float32)
    grey = im.mean(axis=2) if im.ndim == 3 else im
    m1 = cv2.blur(grey, (size, size))
    m2 = cv2.blur(grey * grey, (size, size))
    return np.sqrt(np.maximum(m2 - m1 * m1, 0.0)).astype(np.float32)


def _same_colour(
    a: NDArray[np.float32], b: NDArray[np.float32], config: StaticCheckConfig
) -> NDArray[np.bool_]:
    sa = a.sum(axis=1) + 1.0
    sb = b.sum(axis=1) + 1.0
    chroma = np.abs(a / sa[:, None] - b / sb[:, None]).sum(axis=1)
    ratio = np.maximum(sa / sb, sb / sa)
    close = np.abs(a - b).max(axis=1) < config.max_diff
    return np.asarray(close | ((chroma < config.max_chroma) & (ratio < config.max_ratio)))
