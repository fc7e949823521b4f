"""Multi-view tracks from pairwise matches.

Tracks are the connected components of the graph whose nodes are keypoint locations of all
views and whose edges are pairwise matches (SciPy's ``connected_components``, i.e. a vectorised
union-find). A component holding two different locations of the same view is inconsistent
(at least one of its matches is wrong) and is rejected as a whole.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components

from edgerecon.sparse.matching import PairMatches


@dataclass(frozen=True, kw_only=True, eq=False)
class Tracks:
    """Tracks as a dense (T, V) table of location indices (-1 = not observed)."""

    locations: NDArray[np.int64]
    """(T, V) location index of the track in each view, -1 where the view has none."""
    ratio: NDArray[np.float32] | None = None
    """(T,) smallest ratio-test value of the matches that formed each track (its most
    distinctive match); None when unknown."""
    num_conflicting: int = 0
    """Components that hold two locations of one view (inconsistent)."""
    num_recovered: int = 0
    """Tracks recovered from inconsistent components by keeping their distinctive matches."""

    def __len__(self) -> int:
        return int(self.locations.shape[0])

    @property
    def observed(self) -> NDArray[np.bool_]:
        """(T, V) True where the track has a location."""
        return self.locations >= 0


def build_tracks(
    num_locations: Sequence[int],
    matches: Sequence[PairMatches],
    strict_ratio: float | None = None,
) -> Tracks:
    """Connected components of the match graph over ``num_locations[v]`` locations per view.

    Components holding two locations of one view are inconsistent. When ``strict_ratio`` is
    given, they are split again using only their matches whose ratio-test value is at most
    ``strict_ratio`` (the most distinctive ones); what is still inconsistent is rejected.
    """
    num_views = len(num_locations)
    offsets = np.concatenate([[0], np.cumsum(num_locations)]).astype(np.int64)
    total = int(offsets[-1])
    empty = Tracks(locations=np.zeros((0, num_views), np.int64), ratio=np.zeros(0, np.float32))
    if total == 0 or not any(len(m) for m in matches):
        return empty
    s = np.concatenate([m.location_a + offsets[m.view_a] for m in matches if len(m)])
    d = np.concatenate([m.location_b + offsets[m.view_b] for m in matches if len(m)])
    r = np.concatenate([m.ratio for m in matches if len(m)]).astype(np.float32)
    table, ratio, bad_nodes, num_conflicting = _components(s, d, r, offsets, total)
    num_recovered = 0
    if strict_ratio is not None and num_conflicting:
        # Retry the inconsistent components with their distinctive matches only.
        in_bad = np.zeros(total, bool)
        in_bad[bad_nodes] = True
        sel = in_bad[s] & (r <= strict_ratio)
        if np.any(sel):
            t2, r2, _, _ = _components(s[sel], d[sel], r[sel], offsets, total)
            table, ratio = np.concatenate([table, t2]), np.concatenate([ratio, r2])
            num_recovered = len(t2)
    return Tracks(
        locations=table,
        ratio=ratio,
        num_conflicting=num_conflicting,
        num_recovered=num_recovered,
    )


def _components(
    s: NDArray[np.int64],
    d: NDArray[np.int64],
    r: NDArray[np.float32],
    offsets: NDArray[np.int64],
    total: int,
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.int64], int]:
    """Consistent components as a (C, V) table with their smallest edge ratio, the nodes of
    the inconsistent components and their number."""
    num_views = len(offsets) - 1
    graph = sp.coo_matrix((np.ones(len(s), np.int8), (s, d)), shape=(total, total)).tocsr()
    _, label = connected_components(graph, directed=False)
    nodes = np.unique(np.concatenate([s, d]))
    comps, comp = np.unique(label[nodes], return_inverse=True)
    view = np.searchsorted(offsets, nodes, side="right") - 1
    per_view = np.zeros((len(comps), num_views), np.int64)
    np.add.at(per_view, (comp, view), 1)
    consistent = per_view.max(axis=1) <= 1
    table = np.full((len(comps), num_views), -1, np.int64)
    table[comp, view] = nodes - offsets[view]  # conflicting rows are overwritten, then dropped
    ratio = np.full(len(comps), np.inf, np.float32)
    np.minimum.at(ratio, np.searchsorted(comps, label[s]), r)
    bad_nodes = nodes[~consistent[comp]]
    return table[consistent], ratio[consistent], bad_nodes, int(np.count_nonzero(~consistent))
