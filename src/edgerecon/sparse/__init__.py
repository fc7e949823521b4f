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

Measured (``benchmarks/bench_sparse.py``, process CPU seconds on the shared 2-core machine):
utrecht4cam frame 200 (4 x 644x486, cameras ~90 degrees apart; openMVG finds 0 landmarks,
COLMAP's matching + known-pose triangulation 3): 98 points, median reprojection 0.83 px,
0.6 s CPU (75 points at r = 0.5, 0.18 s). Middlebury templeSparseRing (16 x 640x480): 2,302
points, 99% inside the published bounding box (+5 mm), 0.20 px. Synthetic arc7 (7 x 1920x1080):
2,032 points, 88% within 2 cm of the true surface (94% within 5 cm), 1.8 s CPU.
"""

from edgerecon.sparse.config import SparseConfig
from edgerecon.sparse.features import Features, extract_all, extract_features, use_affine
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
    "use_affine",
]
