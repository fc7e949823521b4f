"""Configuration of sparse reconstruction with known camera poses."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class SparseConfig:
    """Options of :func:`edgerecon.sparse.reconstruct_sparse`.

    Pixel thresholds (``*_px``) are in the pixels of the views given to the stage (i.e. at the
    task's image scale); lengths are in rig units.
    """

    # ------------------------------------------------------------------ features
    max_features: int = 8000
    """Most SIFT keypoints kept per view (strongest responses); 0 = no limit."""
    contrast_threshold: float = 0.02
    """SIFT contrast threshold (OpenCV's default is 0.04; lower finds more keypoints on the
    weakly textured walls and floors of real rooms)."""
    edge_threshold: float = 10.0
    """SIFT edge threshold (OpenCV's default)."""
    min_features: int = 400
    """Feature budget: a view that yields fewer keypoints than this (scaled by the share of
    the image its mask covers) at ``contrast_threshold`` is detected again with the threshold
    multiplied by ``contrast_step`` (at most ``contrast_steps`` times) until it has them, so
    that low-contrast images (grey objects, dim rooms) still give the sparse points that
    depth ranges come from. 0 disables the budget."""
    contrast_step: float = 0.4
    """Factor applied to the contrast threshold at each step of the feature budget."""
    contrast_steps: int = 2
    """Most threshold reductions of the feature budget (0.02 -> 0.008 -> 0.0032)."""
    feature_max_size_px: int = 1100
    """Longest image side used for feature detection: larger views are downscaled first
    (OpenCV's SIFT doubles the image internally, so 1920x1080 costs ~15x more than 960x540
    for a similar number of useful keypoints). 0 = always detect at full size."""
    affine_simulation: str = "auto"
    """Also detect SIFT on each view compressed by ``affine_tilt`` along x and along y (two
    simulated tilts of ASIFT; ~2x the feature time): "on", "off", or "auto" = on for
    wide-baseline rigs (median angle to the nearest camera above ``affine_auto_angle_deg``).
    Measured on utrecht4cam frame 200 (cameras ~90 degrees apart): about 2x the points."""
    affine_tilt: float = 2.0
    """Compression factor of the simulated tilts (2 = surfaces seen at 60 degrees)."""
    affine_auto_angle_deg: float = 40.0
    """Median nearest-neighbour angle between optical axes above which "auto" simulates
    tilts."""
    location_merge_px: float = 1.0
    """Keypoints of the simulated tilts closer than this share a location (one point with
    several descriptors)."""
    root_sift: bool = True
    """Use RootSIFT descriptors (Hellinger kernel: L1-normalise, square root)."""
    num_threads: int = 2
    """Worker threads for per-view feature extraction and per-pair matching (OpenCV and NumPy
    release the GIL)."""

    # ------------------------------------------------------------------ matching
    epipolar_threshold_px: float = 3.0
    """Largest distance of a candidate match from the epipolar line of its partner (both
    directions)."""
    ratio: float = 0.85
    """Lowe ratio among the *epipolar candidates*: best / second-best descriptor distance
    (second best taken at a different location) must be below this for a match to enter a
    track; tracks confirmed by three or more views need no stricter test."""
    two_view_ratio: float = 0.75
    """Stricter ratio for points observed by only two views (nothing else confirms them)."""
    confirm_angle_deg: float = 40.0
    """Reject a two-view point when a third view sees it from between the two (its ray closer
    in angle to both than they are to each other, and within this angle of both) and did not
    match it: with a viewpoint that similar to both, a wrong match is likelier than an
    occlusion. 0 disables the test."""
    max_descriptor_distance: float = 0.75
    """Largest (Root)SIFT descriptor distance of a match (unit-norm descriptors: 0..sqrt 2)."""
    neighbour_competitors: int = 8
    """Also count as ratio-test competitors this many keypoints near the match (off the
    epipolar line) in each view; 0 = epipolar candidates only. Rejects matches along lines and
    repeated textures whose epipolar line holds no competitor (utrecht4cam's floor seams
    triangulated 1 m below the floor); measured: precision at 2 cm 0.87 -> 0.89 on the
    synthetic arc7 with more points, 0.96 -> 0.99 on the 5-camera box scene."""
    neighbour_radius: float = 0.05
    """Radius of that neighbourhood as a share of the image diagonal (40 px at 644x486)."""
    mutual: bool = True
    """Keep only matches that are each other's best candidate in both directions."""
    min_depth: float = 0.0
    """Smallest depth (rig units) of a triangulated match in both cameras (cheirality: > 0)."""
    max_depth: float = math.inf
    """Largest depth (rig units) of a match in either camera (a room's size bounds it)."""
    max_pair_angle_deg: float = 180.0
    """Camera pairs whose optical axes differ by more than this are not matched (180 = all
    pairs with any overlap of their viewing frusta)."""

    # ------------------------------------------------------------------ triangulation
    max_reprojection_error_px: float = 2.0
    """Observations reprojecting farther than this are dropped (point rejected if fewer than
    two remain)."""
    min_triangulation_angle_deg: float = 1.5
    """Smallest largest angle between two observing rays of a point."""
    refine_iterations: int = 5
    """Gauss-Newton steps on the reprojection error after the linear (DLT) triangulation."""
    guided_matching: bool = True
    """Project each point into the views that do not observe it and add the nearest keypoint
    whose descriptor is close (extends tracks: denser visibility matrix)."""
    guided_radius_px: float = 3.0
    """Search radius around the projection for guided matching."""
    guided_max_descriptor_distance: float = 0.5
    """Largest descriptor distance between a guided keypoint and the closest of the track's
    descriptors (stricter than pairwise matching: nothing else tests it)."""

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, allowed: str) -> None:
            if not ok:
                raise ValueError(
                    f"SparseConfig.{name} = {getattr(self, name)!r} is invalid: {allowed}"
                )

        check("max_features", self.max_features >= 0, "must be >= 0")
        check("contrast_threshold", self.contrast_threshold > 0, "must be > 0")
        check("edge_threshold", self.edge_threshold > 0, "must be > 0")
        check("min_features", self.min_features >= 0, "must be >= 0")
        check("contrast_step", 0 < self.contrast_step < 1, "must be in (0, 1)")
        check("contrast_steps", 0 <= self.contrast_steps <= 8, "must be in 0..8")
        check("feature_max_size_px", self.feature_max_size_px >= 0, "must be >= 0")
        check(
            "affine_simulation",
            self.affine_simulation in ("auto", "on", "off"),
            'must be "auto", "on" or "off"',
        )
        check("affine_tilt", self.affine_tilt > 1, "must be > 1")
        check(
            "affine_auto_angle_deg", 0 <= self.affine_auto_angle_deg <= 180, "must be in [0, 180]"
        )
        check("location_merge_px", self.location_merge_px >= 0, "must be >= 0")
        check("num_threads", self.num_threads >= 1, "must be >= 1")
        check("epipolar_threshold_px", self.epipolar_threshold_px > 0, "must be > 0")
        check("ratio", 0 < self.ratio <= 1, "must be in (0, 1]")
        check("two_view_ratio", 0 < self.two_view_ratio <= 1, "must be in (0, 1]")
        check(
            "max_descriptor_distance",
            0 < self.max_descriptor_distance <= 2,
            "must be in (0, 2]",
        )
        check("neighbour_competitors", self.neighbour_competitors >= 0, "must be >= 0")
        check("neighbour_radius", self.neighbour_radius > 0, "must be > 0")
        check("min_depth", self.min_depth >= 0, "must be >= 0")
        check("max_depth", self.max_depth > self.min_depth, "must be > min_depth")
        check("max_pair_angle_deg", 0 < self.max_pair_angle_deg <= 180, "must be in (0, 180]")
        check("max_reprojection_error_px", self.max_reprojection_error_px > 0, "must be > 0")
        check(
            "min_triangulation_angle_deg",
            0 <= self.min_triangulation_angle_deg < 180,
            "must be in [0, 180)",
        )
        check("confirm_angle_deg", 0 <= self.confirm_angle_deg <= 180, "must be in [0, 180]")
        check("refine_iterations", self.refine_iterations >= 0, "must be >= 0")
        check("guided_radius_px", self.guided_radius_px > 0, "must be > 0")
        check(
            "guided_max_descriptor_distance",
            0 < self.guided_max_descriptor_distance <= 2,
            "must be in (0, 2]",
        )


#: The default configuration (a shared immutable instance, used as the default argument).
DEFAULT_CONFIG = SparseConfig()
