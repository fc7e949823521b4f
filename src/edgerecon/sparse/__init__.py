"""Sparse reconstruction with known camera poses (structure from known poses).

``reconstruct_sparse(views, config)`` turns the undistorted views of one task into a sparse
coloured point cloud and the point-camera visibility matrix that camera selection (problem P2)
is built on:

1. SIFT features per view, in a thread pool (:mod:`.features`);
2. matching of camera pairs constrained by the known epipolar geometry, with a ratio test among
   the epipolar candidates only (:mod:`.matching`) — the key to wide-baseline rigs;
3. multi-view tracks by connected components of the match graph (:mod:`.tracks`);
4. multi-view DLT + Gauss-Newton triangulation vectorised over points, reprojection /
   cheirality / triangulation-angle filters, guided extension of tracks into the views that
   did not match them (:mod:`.triangulation`, :mod:`.reconstruction`).
"""

from edgerecon.sparse.config import SparseConfig
from edgerecon.sparse.features import Features, extract_all, extract_features
from edgerecon.sparse.matching import PairMatches, match_pair, select_pairs
from edgerecon.sparse.reconstruction import SparseReconstruction, reconstruct_sparse
from edgerecon.sparse.tracks import Tracks, build_tracks
from edgerecon.sparse.triangulation import (
    max_triangulation_angle_deg,
    refine_points,
    reprojection_errors,
    triangulate_dlt,
)

__all__ = [
    "Features",
    "PairMatches",
    "SparseConfig",
    "SparseReconstruction",
    "Tracks",
    "build_tracks",
    "extract_all",
    "extract_features",
    "match_pair",
    "max_triangulation_angle_deg",
    "reconstruct_sparse",
    "refine_points",
    "reprojection_errors",
    "select_pairs",
    "triangulate_dlt",
]
