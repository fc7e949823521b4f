"""Source-view selection: which views each reference view is matched against.

A source is useful when it sees much of what the reference sees (overlap) under a
triangulation angle that is neither tiny (depth is ill-conditioned) nor huge (the surfaces
look too different, or the source sees their back). Both are measured on sample points of
the reference: its sparse points when there are enough, otherwise points on its pixel rays
at several depths of its range.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera

#: Triangulation angle (degrees) below which a source's weight falls linearly to zero.
GOOD_ANGLE_DEG = 10.0
#: Above this angle (degrees), the weight decays (appearance changes, self-occlusion).
WIDE_ANGLE_DEG = 45.0


@dataclass(frozen=True, kw_only=True)
class SourceScore:
    """How well one source view suits one reference view."""

    index: int
    """Position of the source in the list of views."""
    overlap: float
    """Share of the reference's sample points the source sees (in front, inside its image)."""
    angle_deg: float
    """Median triangulation angle over those points."""
    score: float
    """overlap x angle weight (higher is better)."""


def angle_weight(angle_deg: float) -> float:
    """1 between ``GOOD_ANGLE_DEG`` and ``WIDE_ANGLE_DEG``, lower outside."""
    if angle_deg < GOOD_ANGLE_DEG:
        return max(angle_deg / GOOD_ANGLE_DEG, 0.0)
    if angle_deg > WIDE_ANGLE_DEG:
        return float(np.exp(-(((angle_deg - WIDE_ANGLE_DEG) / 45.0) ** 2)))
    return 1.0


def score_sources(
    ref: Camera, cameras: Sequence[Camera], ref_index: int, samples: NDArray[np.float64]
) -> list[SourceScore]:
    """Scores of every other camera as a source for ``cameras[ref_index]`` = ``ref``."""
    out: list[SourceScore] = []
    if len(samples) == 0:
        return out
    to_ref = samples - ref.center
    to_ref /= np.linalg.norm(to_ref, axis=1, keepdims=True) + 1e-300
    for j, cam in enumerate(cameras):
        if j == ref_index:
            continue
        uv, z = cam.project(samples)
        seen = (z > 0) & cam.in_image(uv)
        overlap = float(seen.mean())
        if not seen.any():
            out.append(SourceScore(index=j, overlap=0.0, angle_deg=0.0, score=0.0))
            continue
        to_src = samples[seen] - cam.center
        to_src /= np.linalg.norm(to_src, axis=1, keepdims=True) + 1e-300
        cos = np.clip(np.einsum("ij,ij->i", to_ref[seen], to_src), -1.0, 1.0)
        angle = float(np.degrees(np.median(np.arccos(cos))))
        out.append(
            SourceScore(
                index=j, overlap=overlap, angle_deg=angle, score=overlap * angle_weight(angle)
            )
        )
    return out


def select_sources(
    scores: Sequence[SourceScore],
    max_sources: int,
    min_angle_deg: float,
    max_angle_deg: float,
    min_overlap: float = 0.05,
) -> list[int]:
    """Indices of the best sources (by score) within the angle limits, best first."""
    ok = [
        s
        for s in scores
        if s.overlap >= min_overlap and min_angle_deg <= s.angle_deg <= max_angle_deg
    ]
    ok.sort(key=lambda s: -s.score)
    return [s.index for s in ok[:max_sources]]
