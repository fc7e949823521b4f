"""Source-view selection: which views each reference view is matched against.

A source is useful where it sees what the reference sees under a triangulation angle that
is neither tiny (depth is ill-conditioned) nor huge (the surfaces look too different, or the
source sees their back). Both are measured per sample point of the reference (its sparse
points and points on a grid of its pixel rays at several depths of its range), and the
sources are chosen together: greedily, each one adding the most to the expected share of
sample points that at least one chosen source matches. Ranking sources one by one picks
several that see the same central region and none for the parts only one neighbour sees
(the side walls at the ends of a camera arc: 3 % recall with the three best-ranked sources).
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
#: Chance that one source under a good angle matches a point (occlusion, specularity, image
#: border): below 1, so that a second source for the same points still counts.
MATCH_PROBABILITY = 0.7


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
    """Mean over the sample points of seen x angle weight (higher is better)."""


def angle_weight(angle_deg: float) -> float:
    """1 between ``GOOD_ANGLE_DEG`` and ``WIDE_ANGLE_DEG``, lower outside."""
    if angle_deg < GOOD_ANGLE_DEG:
        return max(angle_deg / GOOD_ANGLE_DEG, 0.0)
    if angle_deg > WIDE_ANGLE_DEG:
        return float(np.exp(-(((angle_deg - WIDE_ANGLE_DEG) / 45.0) ** 2)))
    return 1.0


def point_weights(
    ref: Camera, cameras: Sequence[Camera], ref_index: int, samples: NDArray[np.float64]
) -> tuple[list[SourceScore], NDArray[np.float64]]:
    """Scores of every other camera as a source for ``cameras[ref_index]`` = ``ref``, and the
    (len(cameras), len(samples)) weights: ``MATCH_PROBABILITY`` x ``angle_weight`` of the
    triangulation angle at each sample point the source sees (in front, inside its image), 0
    elsewhere and for the reference itself."""
    out: list[SourceScore] = []
    weights = np.zeros((len(cameras), len(samples)))
    if len(samples) == 0:
        return out, weights
    to_ref = samples - ref.center
    to_ref /= np.linalg.norm(to_ref, axis=1, keepdims=True) + 1e-300
    for j, cam in enumerate(cameras):
        if j == ref_index:
            continue
        uv, z = cam.project(samples)
        seen = (z > 0) & cam.in_image(uv)
        if not seen.any():
            out.append(SourceScore(index=j, overlap=0.0, angle_deg=0.0, score=0.0))
            continue
        to_src = samples[seen] - cam.center
        to_src /= np.linalg.norm(to_src, axis=1, keepdims=True) + 1e-300
        cos = np.clip(np.einsum("ij,ij->i", to_ref[seen], to_src), -1.0, 1.0)
        angles = np.degrees(np.arccos(cos))
        weights[j, seen] = [MATCH_PROBABILITY * angle_weight(float(a)) for a in angles]
        out.append(
            SourceScore(
                index=j,
                overlap=float(seen.mean()),
                angle_deg=float(np.median(angles)),
                score=float(weights[j].mean()),
            )
        )
    return out, weights


def select_sources(
    scores: Sequence[SourceScore],
    max_sources: int,
    min_angle_deg: float,
    max_angle_deg: float,
    min_overlap: float = 0.05,
    weights: NDArray[np.float64] | None = None,
    sample_weights: NDArray[np.float64] | None = None,
    min_gain: float = 0.0,
    min_sources: int = 0,
) -> list[int]:
    """Indices of the chosen sources within the angle and overlap limits, best first.

    With the per-point ``weights`` of ``point_weights`` (and optional ``sample_weights``,
    the importance of each sample point), sources are added greedily by their gain in
    ``sum_p sample_weight_p (1 - prod_chosen (1 - w_jp))``: the expected share of sample
    points at least one chosen source matches, which still rewards a second source for the
    same points (occlusions, ambiguities) but first covers what no source sees yet; after the
    first ``min_sources``, a source is added only if its gain is at least ``min_gain``.
    Without ``weights``, the best ``max_sources`` by score. Ties go to the lower index."""
    ok = [
        s
        for s in scores
        if s.overlap >= min_overlap and min_angle_deg <= s.angle_deg <= max_angle_deg
    ]
    if weights is None:
        ok.sort(key=lambda s: (-s.score, s.index))
        return [s.index for s in ok[:max_sources]]
    sw = (
        np.full(weights.shape[1], 1.0 / max(weights.shape[1], 1))
        if sample_weights is None
        else np.asarray(sample_weights, np.float64)
    )
    missed = np.ones(weights.shape[1])  # prod over chosen of (1 - w)
    chosen: list[int] = []
    candidates = sorted(s.index for s in ok)
    while len(chosen) < max_sources and candidates:
        gains = [float(sw @ (missed * weights[j])) for j in candidates]
        best = int(np.argmax(gains))
        if gains[best] <= 0 or (len(chosen) >= min_sources and gains[best] < min_gain):
            break
        j = candidates.pop(best)
        chosen.append(j)
        missed *= 1.0 - weights[j]
    return chosen
