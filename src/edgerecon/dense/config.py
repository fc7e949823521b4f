"""Configuration of dense multi-view stereo (:func:`edgerecon.dense.reconstruct_dense`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Plane families the coarse sweep can test (see ``DenseConfig.sweep_families``).
SWEEP_FAMILIES = ("fronto", "ground", "vertical")


@dataclass(frozen=True, kw_only=True)
class DenseConfig:
    """Settings of the dense stage. Lengths are in rig units unless the name ends in ``_px``
    (pixels at the working resolution) or ``_deg``; ``rel`` means relative to depth."""

    resolution_level: int = 1
    """Depth maps are computed at ``2**-resolution_level`` of the view images (openMVS also
    densifies at half resolution by default); 0 = full view resolution."""
    min_resolution_px: int = 640
    """... but the level is lowered (finer depth maps) while the larger side of a camera's
    *frames* (the golden image, r = 1) at that level would be under this many pixels, as
    openMVS's ``--min-resolution`` (also 640): a 640x480 rig densifies at full resolution,
    a 1920x1080 one at half. The level comes from the frames, not from the task's views, so
    the image scale r still scales the cost (``View.scale``). 0 = always
    ``resolution_level``."""
    coarse_levels: int = 3
    """At most this many octaves below the working resolution for the plane sweep; each finer
    octave refines the depths by propagation and a local search (coarse-to-fine)."""
    sweep_min_side_px: int = 120
    """The sweep runs at the coarsest pyramid level whose longer side keeps at least this
    many pixels: an octave of the working image, or a last level resized to exactly this
    side where the next octave would be smaller and the previous one (not the working image
    itself) is over 1.5x larger (1920x1080 at level 1: the octave 120x68; 1536x864: 120x68
    instead of the octave 192x108, which made r = 0.8 slower than r = 1)."""
    sweep_small_exhaustive: bool = True
    """Working images under twice ``sweep_min_side_px`` (whose first octave would be smaller
    than it) are swept at their own resolution, exhaustively, instead of at a level resized
    to ``sweep_min_side_px``: better depths for whole scenes at small scales (demo scene at
    r = 0.6: golden F 0.514 against 0.467), but such a sweep costs more than the resized
    level of a larger image (caliscope_charuco's foreground at r = 0.3, 192x108 depth maps:
    0.33 s against 0.26 s at r = 0.4). The foreground turns it off
    (``pipeline.foreground_dense_config``): its cost must fall with r for the controller."""
    max_source_views: int = 4
    """At most this many source views are matched against each reference view, chosen
    together for the share of the reference's surfaces they cover (see ``min_source_gain``)."""
    min_source_views: int = 3
    """The first this many sources are always taken (when the angle and overlap limits leave
    them); further ones only if they pay for themselves by ``min_source_gain``."""
    min_source_gain: float = 0.03
    """A source beyond ``min_source_views`` is added only if it raises the expected share of
    the reference's sample points that some source matches by at least this much (on arc7,
    5 of the 7 views take a 4th source: F@2cm 0.844 -> 0.856 for about +10 % depth time;
    a 4th source for every view: 0.848 for +30 %)."""
    min_source_angle_deg: float = 2.0
    """Sources whose median triangulation angle with the reference is smaller are skipped."""
    max_source_angle_deg: float = 110.0
    """Sources whose median triangulation angle with the reference is larger are skipped."""
    window_radius: int = 3
    """NCC window half-size in pixels (3 -> 7x7 windows), at every pyramid level."""
    ncc_top_k: int = 2
    """Matching score of a depth = mean of the best ``ncc_top_k`` source NCCs (occlusion-robust)."""
    ncc_top_gap: float = 0.15
    """In that mean, a source's NCC counts as at least the best one's minus this: a source
    that does not see the pixel (occluded) takes at most ``gap / k`` off the score, one that
    sees it confirms the depth (inf: the plain mean; 0: the best source alone). Best 2 with
    0.15, against the best source alone (with 2 passes): arc7 P/R@1cm 0.951/0.650 ->
    0.963/0.654, the object preset's P/R at 0.1 % 0.892/0.865 -> 0.921/0.906;
    caliscope_charuco's board median at t=100 1.73 -> 1.44 mm (``docs/BENCHMARKS.md``)."""
    sweep_families: tuple[str, ...] = ("fronto", "ground")
    """Plane orientations of the coarse sweep: "fronto" (parallel to the reference image),
    "ground" (perpendicular to the scene's up direction: floors, tables, seats) and
    "vertical" (planes that hold the up direction, turned by +-``vertical_sweep_deg`` about
    it from the reference image's plane: the sides of people, walls and furniture that a
    camera 90 degrees away sees foreshortened). The foreground sweeps "fronto" and
    "vertical" (``SplitPipelineConfig.fg_vertical_sweep``)."""
    vertical_sweep_deg: tuple[float, ...] = (20.0,)
    """The turns of the "vertical" family: each angle gives two families (+ and -)."""
    plane_step_px: float = 1.0
    """Largest image motion in any source between consecutive sweep planes, in coarse pixels."""
    max_planes: int = 192
    """Cap on planes per family; the step grows when the depth range needs more (measured:
    128 lost nothing on arc7 and made utrecht4cam's sweep a third cheaper, but took the demo
    scene's golden F from 0.585 to 0.521: its wide ring needs the finer steps)."""
    refine_radius: int = 2
    """The local search at each finer level tests depths at +-refine_radius steps."""
    refine_step_px: float = 1.0
    """Image motion in the most sensitive source per local-search step, in pixels of that level."""
    refine_median_px: int = 5
    """The local search steps from a median-filtered copy of the depth map (this kernel, 3 or
    5 pixels; 0 = from the map itself), kept where it stays within ``refine_median_rel`` of
    each pixel's own depth: a window is warped through its neighbours' hypotheses, and their
    noise blurs the match of its own (``bench_precision.py``: arc7 t=20 P@1cm 0.868 ->
    0.930 with R 0.627 -> 0.636; demo F@2cm 0.595 -> 0.607; object P/R@0.1 % .727/.871 ->
    .742/.884; same CPU). The foreground keeps it only where the median is within 1 % of
    the pixel's depth (``SplitPipelineConfig.fg_refine_median_rel``)."""
    refine_median_rel: float = 0.05
    """Largest relative difference between a pixel's depth and the median around it for the
    median to be its local search's starting point (depth edges keep their own depth)."""
    refine_passes: int = 2
    """Local searches per level, each from the median of the last (the second, with the best
    two sources' score: object preset recall at 0.1 % 0.894 -> 0.906; arc7 R@1cm, with a
    gap of 0.2, 0.646 -> 0.654), for +8-10 % dense CPU on arc7."""
    propagation_iterations: int = 1
    """Rounds of whole-map propagation per level (neighbours' depths as hypotheses)."""
    min_ncc: float = 0.5
    """Depths whose aggregated NCC is lower are discarded."""
    noise_adaptive_ncc: bool = False
    """Scale ``min_ncc`` by the NCC that a true match can reach through the images' noise:
    1 - sigma^2 / s^2 for a window of grey standard deviation s, in a reference view whose
    noise sigma is measured from the image (``depth.noise_sigma``), where s is at least
    ``ncc_min_snr`` sigma (``depth.ncc_threshold``). Weakly textured windows of noisy or dim
    images keep their true matches; clean images (sigma << s) keep ``min_ncc``. On for the
    foreground, whose search the visual hull bounds (``SplitPipelineConfig.
    fg_noise_adaptive_ncc``): over a whole scene's depth range the chance winners of weak
    windows score as high."""
    ncc_min_snr: float = 1.5
    """Windows whose texture is below this multiple of the noise keep ``min_ncc``."""
    min_texture: float = 1.5
    """Reference windows with a grey-level standard deviation below this (0..255 scale) are
    discarded: NCC is meaningless on flat patches."""
    min_epipolar_texture: float = 0.5
    """A source is ignored at pixels whose reference window has less texture along that
    source's epipolar lines (RMS derivative, grey levels per pixel): edges parallel to the
    baseline match anywhere along themselves (aperture problem); 0 disables the test."""
    min_epipolar_share: float = 0.0
    """... and at least this share of the window's gradient energy must lie along the
    epipolar direction (0.1 ~ edges at least 18 degrees off the epipolar lines); 0 disables
    it. Off by default: on the synthetic arc (cameras side by side, near-horizontal epipolar
    lines) 0.1 drops the F-score at 2 cm from 0.84 to 0.77 (horizontal stripes and seams
    are lost with the mismatches), while utrecht4cam's floor moves only 4 mm closer to
    z = 0 (27 vs 31 mm median)."""
    consistency_rel_depth: float = 0.01
    """A depth agrees with another view when their depths differ by less than this share
    (the most; see ``consistency_noise_factor``)."""
    consistency_noise_factor: float = 4.0
    """The agreement tolerance is this multiple of the views' measured depth noise (the
    median relative difference of agreeing view pairs, ``consistency.depth_noise``), within
    [``consistency_rel_depth_min``, ``consistency_rel_depth``]; 0 = always
    ``consistency_rel_depth``."""
    consistency_rel_depth_min: float = 0.003
    """The least agreement tolerance ``consistency_noise_factor`` may set (at or above
    ``consistency_rel_depth``: the fixed tolerance)."""
    consistency_px: float = 0.0
    """... and, when > 0, when the other view's point reprojects within this many working
    pixels of the pixel (COLMAP's fusion: 2 px and 1 %); 0 = the depth test alone."""
    min_consistent_views: int = 1
    """A depth is kept only if at least this many other views agree (1 -> seen by >= 2 views)."""
    ground_completion: bool = True
    """Fill the floor pixels stereo left without depth from the ground plane fitted to the
    stereo points, where the other views confirm the colour (and, on textured pixels, the
    pattern) and none sees through (``dense.planes``)."""
    ground_color_tol: float = 20.0
    """Largest per-channel difference (0..255) of 5x5-mean colours for a view to confirm."""
    ground_max_texture: float = 16.0
    """Only pixels whose 7x7 grey standard deviation is below this are completed: strongly
    textured pixels without a consistent depth are occlusions or mismatches. Floors of mild
    texture (carpet, concrete, worn tiles) that stereo misses at grazing angles or where
    only two views overlap are completed where the other views confirm colour and pattern
    (``ground_min_ncc``; demo scene: golden F@2cm 0.607 -> 0.667 with precision up at every
    threshold, arc7 0.796 -> 0.813; 4.0, blank floors only, before)."""
    ground_min_ncc: float = 0.5
    """A textured floor pixel (7x7 grey standard deviation of at least
    ``dense.planes.BLANK_TEXTURE``) is confirmed by a view only where that view's image,
    warped through the plane, matches its pattern with at least this NCC."""
    ground_min_support: int = 100
    """Stereo points on the ground needed before the plane is used."""
    ground_level_cell: float = 16.0
    """Cell edge, in fusion voxels, of the level map that keeps ground completion off other
    measured levels (a raised deck, a platform, a step; ``dense.planes.level_map``); 0 turns
    the map off."""
    ground_level_min_points: int = 5
    """Measured horizontal points off the plane (of at most 500,000 sampled) that make a
    cell another level."""
    voxel_size: float | None = None
    """Fusion merges points within one voxel of this edge (rig units); None = ``voxel_rel``
    times the median pixel footprint (depth / focal) of the depth maps."""
    voxel_rel: float = 1.0
    """Voxel edge in median pixel footprints when ``voxel_size`` is None."""
    max_depth_rel_scene: float = 6.0
    """Without sparse points or given ranges, depths run up to this multiple of the rig's
    median camera distance."""
    range_margin_rel: float = 0.15
    """Depth ranges from sparse points are widened by this share at both ends."""
    min_sparse_points: int = 12
    """A view needs this many sparse points to take its depth range from them."""
    roi_margin_px: int = 8
    """Masks are grown by this many working pixels before cropping (window support)."""
    num_threads: int = 2
    """Reference views processed in parallel (OpenCV releases the GIL)."""
    device: str = "auto"
    """Where the depth maps' NCC scoring (the plane sweep and the refinement's hypothesis
    scores, most of the dense stage's time) runs: "cpu" (the compiled CPU kernels), "cuda"
    (a CUDA GPU through numba.cuda; an error without one) or "auto" (the GPU where numba
    finds one, else the CPU). The rest of the stage stays on the CPU; the GPU's scores
    agree with the CPU's to float rounding (``edgerecon.dense.gpu``)."""

    # ------------------------------------------------- precision filters (dense.filters)
    consistent_view_share: float = 0.0
    """A depth also needs this share of the other views that could have confirmed it (its
    place in their image, not hidden behind what they measured) to agree: more agreement
    where more views see the place; 0 = only ``min_consistent_views``."""
    max_conflict_share: float = 0.67
    """Depths that more than this share of the agreeing + contradicting views contradict
    (the point floats in space a view sees through) are dropped; 1 = no free-space test
    (with 4 or fewer cameras 0.67 never fires). With ``depth_edge_rel`` 0.1, measured against
    neither (bench_precision, one process): object preset mean/median accuracy 7.1 -> 2.8,
    P@0.1 % +4.8 points, recall -0.9 %; arc7 P@1cm +0.7 points, recall -0.2 %. 0.5 gained
    more precision but lost over 2 % of the object's recall at 0.1 %."""
    min_weak_ncc: float = -1.0
    """Depths confirmed by fewer than two other views need at least this matching score
    (NCC); -1 = no extra test."""
    depth_edge_rel: float = 0.1
    """Depths with an 8-neighbour nearer by more than this share of the depth (the far side
    of a depth discontinuity, where windows mix the near surface in, and the steps of streaks
    bridging one) are dropped; 0 = off. 0.02 buys more precision (demo P@1cm +2 points) for
    1.9 % of its recall at 2 cm."""
    max_grazing_deg: float = 90.0
    """Points whose surface normal is more than this angle from their view's ray are
    dropped; 90 = off."""
    outlier_k: int = 0
    """Statistical outlier pass on the fused cloud with this many neighbours; 0 = off."""
    outlier_std: float = 2.0
    """... dropping points whose mean k-NN distance exceeds the mean by this many standard
    deviations."""

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise ValueError(f"DenseConfig.{name} must be {what}, got {getattr(self, name)!r}")

        need(0 <= self.resolution_level <= 4, "resolution_level", "in 0..4")
        need(self.min_resolution_px >= 0, "min_resolution_px", ">= 0")
        need(self.consistency_px >= 0, "consistency_px", ">= 0")
        need(0 <= self.coarse_levels <= 4, "coarse_levels", "in 0..4")
        need(self.sweep_min_side_px >= 16, "sweep_min_side_px", ">= 16")
        need(self.max_source_views >= 1, "max_source_views", ">= 1")
        need(self.min_source_views >= 1, "min_source_views", ">= 1")
        need(0.0 <= self.min_source_gain < 1.0, "min_source_gain", "in [0, 1)")
        need(0.0 <= self.min_source_angle_deg < 180.0, "min_source_angle_deg", "in [0, 180)")
        need(
            self.min_source_angle_deg < self.max_source_angle_deg <= 180.0,
            "max_source_angle_deg",
            "in (min_source_angle_deg, 180]",
        )
        need(1 <= self.window_radius <= 15, "window_radius", "in 1..15")
        need(self.ncc_top_k >= 1, "ncc_top_k", ">= 1")
        need(self.ncc_top_gap >= 0, "ncc_top_gap", ">= 0")
        need(
            len(self.sweep_families) > 0
            and all(f in SWEEP_FAMILIES for f in self.sweep_families)
            and len(set(self.sweep_families)) == len(self.sweep_families),
            "sweep_families",
            f"a non-empty tuple of distinct names from {SWEEP_FAMILIES}",
        )
        need(
            len(self.vertical_sweep_deg) > 0
            and all(0.0 < a < 80.0 for a in self.vertical_sweep_deg),
            "vertical_sweep_deg",
            "a non-empty tuple of angles in (0, 80) degrees",
        )
        need(0.0 < self.plane_step_px <= 16.0, "plane_step_px", "in (0, 16]")
        need(self.max_planes >= 4, "max_planes", ">= 4")
        need(self.ground_level_cell >= 0.0, "ground_level_cell", ">= 0")
        need(self.ground_level_min_points >= 1, "ground_level_min_points", ">= 1")
        need(0 <= self.refine_radius <= 8, "refine_radius", "in 0..8")
        need(0.0 < self.refine_step_px <= 8.0, "refine_step_px", "in (0, 8]")
        need(self.refine_median_px in (0, 3, 5), "refine_median_px", "0, 3 or 5")
        need(0.0 < self.refine_median_rel < 1.0, "refine_median_rel", "in (0, 1)")
        need(1 <= self.refine_passes <= 4, "refine_passes", "in 1..4")
        need(0 <= self.propagation_iterations <= 8, "propagation_iterations", "in 0..8")
        need(-1.0 <= self.min_ncc < 1.0, "min_ncc", "in [-1, 1)")
        need(self.ncc_min_snr >= 1.0, "ncc_min_snr", ">= 1")
        need(self.min_texture >= 0.0, "min_texture", ">= 0")
        need(self.min_epipolar_texture >= 0.0, "min_epipolar_texture", ">= 0")
        need(0.0 <= self.min_epipolar_share < 1.0, "min_epipolar_share", "in [0, 1)")
        need(0.0 < self.consistency_rel_depth < 1.0, "consistency_rel_depth", "in (0, 1)")
        need(self.consistency_noise_factor >= 0, "consistency_noise_factor", ">= 0")
        need(0.0 < self.consistency_rel_depth_min < 1.0, "consistency_rel_depth_min", "in (0, 1)")
        need(self.min_consistent_views >= 0, "min_consistent_views", ">= 0")
        need(
            self.voxel_size is None or (self.voxel_size > 0 and math.isfinite(self.voxel_size)),
            "voxel_size",
            "None or a positive length",
        )
        need(self.ground_color_tol > 0, "ground_color_tol", "> 0")
        need(self.ground_max_texture > 0, "ground_max_texture", "> 0")
        need(-1.0 <= self.ground_min_ncc <= 1.0, "ground_min_ncc", "in [-1, 1]")
        need(self.ground_min_support >= 3, "ground_min_support", ">= 3")
        need(0.1 <= self.voxel_rel <= 20.0, "voxel_rel", "in [0.1, 20]")
        need(self.max_depth_rel_scene > 0, "max_depth_rel_scene", "> 0")
        need(0.0 <= self.range_margin_rel < 1.0, "range_margin_rel", "in [0, 1)")
        need(self.min_sparse_points >= 1, "min_sparse_points", ">= 1")
        need(self.roi_margin_px >= 0, "roi_margin_px", ">= 0")
        need(self.num_threads >= 1, "num_threads", ">= 1")
        need(self.device in ("cpu", "cuda", "auto"), "device", '"cpu", "cuda" or "auto"')
        need(0.0 <= self.consistent_view_share <= 1.0, "consistent_view_share", "in [0, 1]")
        need(0.0 <= self.max_conflict_share <= 1.0, "max_conflict_share", "in [0, 1]")
        need(-1.0 <= self.min_weak_ncc < 1.0, "min_weak_ncc", "in [-1, 1)")
        need(self.depth_edge_rel >= 0.0, "depth_edge_rel", ">= 0")
        need(0.0 < self.max_grazing_deg <= 90.0, "max_grazing_deg", "in (0, 90]")
        need(self.outlier_k >= 0, "outlier_k", ">= 0")
        need(self.outlier_std > 0, "outlier_std", "> 0")

    @property
    def working_scale(self) -> float:
        """Scale of the depth maps relative to the view images at ``resolution_level`` (see
        ``level_for`` for the level a view actually gets)."""
        return 0.5**self.resolution_level

    def level_for(self, frame_size: tuple[int, int]) -> int:
        """The resolution level for a camera whose frames are ``frame_size`` (w, h) pixels:
        ``resolution_level``, lowered while the larger side at that level would be under
        ``min_resolution_px``."""
        level = self.resolution_level
        side = max(frame_size)
        while level > 0 and side * 0.5**level < self.min_resolution_px:
            level -= 1
        return level
