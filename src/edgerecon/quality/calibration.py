"""Does the calibration fit the frames? A camera knocked after it was calibrated (a tripod
bumped at a site), two videos given to the wrong cameras, or a calibration of another setup
leave every later stage quietly wrong: the sparse stage matches along the wrong epipolar
lines and finds little, the visual hull carves the people away, the dense stage fuses
nothing. This check finds it from the frames alone, before any of that:

1. SIFT features of every camera's undistorted frame (the sparse stage's, with its simulated
   tilts on wide-baseline rigs);
2. per pair of cameras, matches found *without* the calibration (nearest neighbours, ratio
   test, both ways), then kept when a fundamental matrix estimated from the matches
   themselves (MAGSAC) explains them: correspondences of the scene, whatever the calibration
   says;
3. their distance to the epipolar lines the calibration predicts (pixels of the frames): a
   pair that fits has a median of about a pixel, a camera that turned by a degree tens;
   a pair is judged only when its matches beat chance: the fundamental matrix explains
   ``chance_ratio`` times as many of them as one explains of the same points paired at random
   (wrong matches between cameras that share little are explained in part too);
4. pairs of cameras more than ``max_angle_deg`` apart are not judged (they face each other
   and share only wrong matches); weighted by their inliers, a camera is *off* when its own
   pairs mostly miss while the pairs without it mostly fit (then again without its pairs,
   for a second one); a pair with many inliers that misses while no camera is named means
   a camera turned that the pairs cannot name; when no pair fits, the calibration as a whole
   does not fit the frames (videos swapped, another setup's file).

For a camera that is off, :func:`estimate_rotation` finds how it is turned now (its centre
kept): the rotation that brings its matches with the other cameras back onto their epipolar
lines; :func:`estimate_pose` finds its centre too (a tripod kicked to another place);
:func:`repair` re-aims the cameras one at a time, and only where that is the one turn that
makes the pairs fit, placing the first one again where a move explains its matches clearly
better than a turn and the matches can tell the move (``edgerecon calib --write`` stores
it).

Measured on the datasets here: see docs/BENCHMARKS.md ("A camera that moved after its
calibration").
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig, fundamental_matrix, rotation_angle_deg
from edgerecon.sparse.config import SparseConfig
from edgerecon.sparse.features import Features, extract_all
from edgerecon.types import DataError, FrameSet
from edgerecon.views import prepare_views

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CalibrationCheckConfig:
    """Parameters of :func:`check_calibration`."""

    max_side_px: int = 1920
    """Frames are checked at a scale that brings their larger side to at most this (errors
    are still reported in pixels of the frames)."""
    ratio: float = 0.8
    """Lowe's ratio of the matches found without the calibration."""
    ransac_px: float = 1.5
    """The fundamental matrix's inlier threshold, in pixels of a 1000-pixel-wide frame (scaled
    with the frame's larger side)."""
    max_angle_deg: float = 120.0
    """Pairs whose optical axes are farther apart than this are not judged: cameras that
    face each other see opposite sides of the scene, and the few matches they share are
    mostly wrong (hd4's opposite cameras: 13-41 matches a fundamental matrix explains, 28-400
    px from the calibration's lines)."""
    min_inliers: int = 15
    """A pair with fewer matches that a fundamental matrix explains is not checked (the two
    cameras see too little in common)."""
    chance_ratio: float = 1.5
    """A pair is checked only when a fundamental matrix explains at least this many times as
    many of its matches as it explains of the same points paired at random (the most over
    ``chance_draws`` shuffles; pairs with ``chance_below`` inliers or more are not shuffled):
    wrong matches between two cameras that share little are explained in part by some
    fundamental matrix too (caliscope_charuco's cam_0-cam_1 over five frame sets of the
    seated person: 15 of 58 matches explained, 11-13 of them shuffled, 160 px off a
    calibration that fits, named cam_1 moved). Weak pairs of real correspondences lie near
    the limit (caliscope_charuco's cam_1-cam_3: 17 against 12; utrecht4cam's cam1-cam4: 24
    against 15)."""
    chance_draws: int = 3
    """Shuffles of a pair's matches that measure what chance explains."""
    chance_below: int = 100
    """Pairs with at least this many inliers are not tested against chance (what shuffled
    matches give grows slowly with their number: 27-42 of 363 on caliscope_charuco)."""
    max_error_px: float = 8.0
    """A pair is off when the median distance of its matches to the calibration's epipolar
    lines exceeds this many pixels of a 1000-pixel-wide frame (scaled with the frame's larger
    side: 10.2 px at 1280x720, 15.4 px at 1920x1080). Real calibrations that serve well lie
    within 6 (caliscope_charuco's 4 webcams: 0.6-5.5 px at 1280x720, their board corners 0.9
    px: the room behind, where no board was, fits less; utrecht4cam 2.7-3.9 px at 644x486);
    a camera turned by a degree about an axis across its epipolar lines moves the scene by
    about its focal length / 57 pixels there."""
    max_move: float = 0.5
    """A camera found at a new place (:func:`estimate_pose`) is re-posed only when it moved
    less than this share of the distance to its nearest other camera: farther, the frames
    are more likely another camera's (videos swapped) than a tripod's knock."""
    move_gain: float = 0.75
    """A camera re-aimed by a turn is re-posed instead when its new place and orientation
    bring its matches this much closer to their epipolar lines (median over all its checked
    matches): a camera turned about its centre keeps its centre."""
    move_certainty: float = 3.0
    """A camera is placed again only when it moved at least this many times as far as its
    matches can tell (:attr:`PoseEstimate.uncertainty`: how far the centre found moves with
    the matches it came from); a smaller move is the matches' noise, and a turn is kept."""
    pose_chance_ratio: float = 2.0
    """A camera is re-aimed or placed again (:func:`estimate_pose`) only when two or more of
    its pairs hold at least this many times the inliers that chance explains (pairs not
    shuffled, ``chance_below``, count), and a turn is found from those pairs alone (its other
    pairs neither pose it nor have to fit after): with more of the inliers possibly wrong
    matches than right ones, the robust fit can follow the wrong ones (caliscope_charuco's
    cam_1 tilted 2 degrees, pairs of 20 and 18 inliers against 13 and 11 by chance: placed
    5 cm away and turned 4.1 degrees; utrecht4cam's cam2 tilted 1 degree, with a pair of 15
    against 10 that lies 115 px off its own calibration: turned by 11 degrees). A move is
    fitted to every checked pair, and all of them have to fit after it."""
    turn_prior_deg: float = 0.1
    """A turn found again (:func:`estimate_pose`) holds each of its three angles to the
    calibration with this prior (degrees, against the matches' pixel of noise), so that the
    angle the matches barely see stays as it was: a pan along a level ring's epipolar lines
    (utrecht4cam's cam2 tilted 1 degree, re-aimed from an empty frame and a later one by
    1.74 degrees, 1.53 from its calibration, the pan fitted to noise). Angles the matches see
    move as they say (0.8 % of a tilt held back)."""
    rival_ratio: float = 3.0
    """Another camera whose change makes the pairs fit as well is a rival (the pairs cannot
    tell which one moved: neither is changed) unless its matches then lie more than this many
    times as far from their lines (median) as the chosen one's: hd4's cam1 moved 0.3 m
    forward, its turn leaves them 0.72 px away, cam2's 3.24 px; site's cam1 panned 3
    degrees, 0.39 and 2.89 px; caliscope_charuco's rivals lie 1.1-2.2 times as far (the
    room's matches fit its board calibration to a few pixels: they stay rivals)."""
    sparse: SparseConfig = field(default_factory=SparseConfig)
    """The features' settings (the sparse stage's)."""

    def __post_init__(self) -> None:
        if self.max_side_px < 64:
            raise ValueError(
                f"CalibrationCheckConfig.max_side_px must be >= 64, got {self.max_side_px}"
            )
        if not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"CalibrationCheckConfig.ratio must be in (0, 1], got {self.ratio}")
        for name in ("ransac_px", "max_error_px"):
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"CalibrationCheckConfig.{name} must be > 0, got {getattr(self, name)}"
                )
        if not 0.0 < self.max_move:
            raise ValueError(f"CalibrationCheckConfig.max_move must be > 0, got {self.max_move}")
        if not self.rival_ratio >= 1.0:
            raise ValueError(
                f"CalibrationCheckConfig.rival_ratio must be >= 1, got {self.rival_ratio}"
            )
        if not self.pose_chance_ratio >= 1.0:
            raise ValueError(
                "CalibrationCheckConfig.pose_chance_ratio must be >= 1, got "
                f"{self.pose_chance_ratio}"
            )
        if not self.turn_prior_deg > 0.0:
            raise ValueError(
                f"CalibrationCheckConfig.turn_prior_deg must be > 0, got {self.turn_prior_deg}"
            )
        if not self.move_certainty > 0.0:
            raise ValueError(
                f"CalibrationCheckConfig.move_certainty must be > 0, got {self.move_certainty}"
            )
        if not 0.0 < self.move_gain <= 1.0:
            raise ValueError(
                f"CalibrationCheckConfig.move_gain must be in (0, 1], got {self.move_gain}"
            )
        if self.min_inliers < 8:
            raise ValueError(
                f"CalibrationCheckConfig.min_inliers must be >= 8, got {self.min_inliers}"
            )
        if not self.chance_ratio >= 1.0 or self.chance_draws < 0:
            raise ValueError(
                "CalibrationCheckConfig.chance_ratio must be >= 1 and chance_draws >= 0, got "
                f"{self.chance_ratio} and {self.chance_draws}"
            )


@dataclass(frozen=True, kw_only=True)
class PairCheck:
    """One pair of cameras (indices into the rig)."""

    a: int
    b: int
    matches: int
    """Matches found without the calibration (ratio test, both ways)."""
    inliers: int
    """Those a fundamental matrix estimated from them explains."""
    median_px: float | None
    """Median distance of the inliers to the calibration's epipolar lines (pixels of the
    frames, the mean of both images' distances); None: not checked."""
    p90_px: float | None
    """Their 90th percentile."""
    limit_px: float
    """The largest median that fits (``max_error_px`` at this pair's frame size)."""
    angle_deg: float = 0.0
    """Angle between the two cameras' optical axes (beyond ``max_angle_deg``: not judged)."""
    chance: int | None = None
    """Of the same matches paired at random, the most a fundamental matrix explains (None:
    not tested, ``chance_below``); a pair with fewer than ``chance_ratio`` times as many
    inliers is not checked."""

    @property
    def checked(self) -> bool:
        return self.median_px is not None

    @property
    def fits(self) -> bool:
        return self.median_px is not None and self.median_px <= self.limit_px


@dataclass(frozen=True, kw_only=True)
class CameraVerdict:
    camera: int
    name: str
    status: str
    """``ok`` (a checked pair with it fits), ``off`` (every checked pair with it is off while
    another pair fits; one weak pair alone does not name it: :func:`_verdicts`) or
    ``unchecked`` (no pair with it could be checked, or none fits)."""
    median_px: float | None
    """``ok``: the smallest median of its pairs that fit; else the median of its checked
    pairs' medians (None: none checked)."""


@dataclass(frozen=True, kw_only=True)
class CalibrationCheck:
    """What :func:`check_calibration` found."""

    time_index: int
    pairs: tuple[PairCheck, ...]
    cameras: tuple[CameraVerdict, ...]
    fits: bool | None
    """True: some checked pair fits and no camera is off; False: a camera is off, or pairs
    were checked and none fits; None: no pair could be checked."""
    times: tuple[int, ...] = ()
    """The time indices of the frame sets whose matches were pooled (``time_index``: the
    newest)."""
    frame_sets: int = 1
    """How many frame sets' matches were pooled."""
    seconds: float = 0.0
    observed: _Observed | None = field(default=None, repr=False, compare=False)
    """The features and matches (what :func:`estimate_rotation` starts from)."""

    @property
    def off(self) -> list[int]:
        """The cameras that do not fit the others."""
        return [v.camera for v in self.cameras if v.status == "off"]

    @property
    def message(self) -> str:
        """One line for a person."""
        checked = [p for p in self.pairs if p.checked]
        fit = [p for p in checked if p.fits]
        where = ("times " if len(self.times) > 1 else "time ") + (
            ", ".join(str(t) for t in self.times) or str(self.time_index)
        )
        if self.fits is None:
            return f"calibration not checked: no two cameras share enough features ({where})"
        if self.off:
            worst = ", ".join(
                f"{v.name} {v.median_px:.1f} px" for v in self.cameras if v.status == "off"
            )
            return (
                f"calibration: {', '.join(self.off_names)} moved since it was calibrated, or "
                f"is not the camera calibrated: the scene lies {worst} from the calibration's "
                f"epipolar lines, {max(p.median_px or 0.0 for p in fit):.1f} px at most "
                f"between the other cameras ({where})"
            )
        strong = _strong_misfits(self.pairs)
        if not self.fits and fit and strong:
            pair_list = ", ".join(
                f"{self.cameras[p.a].name}-{self.cameras[p.b].name} {p.median_px:.1f} px"
                for p in strong
            )
            return (
                f"calibration: {pair_list} from its epipolar lines (limit "
                f"{strong[0].limit_px:.1f} px) while other pairs fit: a camera turned, and the "
                f"pairs cannot tell which ({where})"
            )
        if not self.fits:
            return (
                "calibration does not fit the frames: no pair of cameras agrees with it "
                f"({min(p.median_px or 0.0 for p in checked):.1f} px from its epipolar lines "
                "at best): another setup's calibration, or the videos given to the wrong "
                f"cameras? ({where})"
            )
        unchecked = [v.name for v in self.cameras if v.status == "unchecked"]
        return (
            f"calibration fits the frames: {len(fit)} of {len(self.pairs)} camera pairs agree "
            f"with it ({max(p.median_px or 0.0 for p in fit):.1f} px from its epipolar lines "
            "at most), "
            + (
                f"{', '.join(unchecked)} not checked (too few features shared with the others)"
                if unchecked
                else "every camera in one of them"
            )
            + f" ({where})"
        )

    @property
    def short(self) -> str:
        """A few words: ``fits``, ``off: CAM``, ``pair A-B off, which camera not told``,
        ``does not fit at all``, ``not checked``."""
        if self.fits is None:
            return "not checked"
        if self.off:
            return "off: " + ", ".join(self.off_names)
        if self.fits:
            return "fits"
        strong = _strong_misfits(self.pairs)
        if strong and any(p.fits for p in self.pairs):
            names = ", ".join(f"{self.cameras[p.a].name}-{self.cameras[p.b].name}" for p in strong)
            return f"pair {names} off, which camera not told"
        return "does not fit at all"

    @property
    def off_names(self) -> list[str]:
        return [v.name for v in self.cameras if v.status == "off"]

    def to_dict(self) -> dict[str, Any]:
        return {
            "time": self.time_index,
            "times": list(self.times),
            "frame_sets": self.frame_sets,
            "fits": self.fits,
            "off": self.off,
            "message": self.message,
            "seconds": round(self.seconds, 3),
            "cameras": [dataclasses.asdict(v) for v in self.cameras],
            "pairs": [
                {
                    **dataclasses.asdict(p),
                    "checked": p.checked,
                    "fits": p.fits,
                }
                for p in self.pairs
            ],
        }


def _scale(rig: Rig, config: CalibrationCheckConfig) -> float:
    side = max(max(c.size) for c in rig)
    return min(1.0, config.max_side_px / side)


def _unit(view: _Seen) -> float:
    """Pixels of the view per "pixel of a 1000-pixel-wide frame" (``max_error_px``'s unit)."""
    return max(view.camera.size) / 1000.0


def _mutual_matches(fa: Features, fb: Features, ratio: float) -> NDArray[np.int64]:
    """(M, 2) location indices of a and b whose keypoints are each other's nearest neighbour
    and pass the ratio test both ways (one match per pair of locations)."""
    if len(fa) < 2 or len(fb) < 2:
        return np.zeros((0, 2), np.int64)
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})  # k-d trees

    def best(d1: NDArray[np.float32], d2: NDArray[np.float32]) -> NDArray[np.int64]:
        out = np.full(len(d1), -1, np.int64)
        for m in flann.knnMatch(d1, d2, k=2):
            if len(m) == 2 and m[0].distance < ratio * m[1].distance:
                out[m[0].queryIdx] = m[0].trainIdx
        return out

    ab = best(fa.descriptors, fb.descriptors)
    ba = best(fb.descriptors, fa.descriptors)
    ia = np.nonzero(ab >= 0)[0]
    ia = ia[ba[ab[ia]] == ia]
    loc = np.stack([fa.location[ia], fb.location[ab[ia]]], axis=1)
    return np.unique(loc, axis=0) if len(loc) else np.zeros((0, 2), np.int64)


def epipolar_distances(
    cam_a: Camera, cam_b: Camera, pa: NDArray[np.float64], pb: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(N,) mean of the distances of ``pb`` to the epipolar lines of ``pa`` and of ``pa`` to
    those of ``pb`` (undistorted pixels of the two cameras)."""
    F = fundamental_matrix(cam_a, cam_b)
    ha = np.column_stack([pa, np.ones(len(pa))])
    hb = np.column_stack([pb, np.ones(len(pb))])
    lb = ha @ F.T  # lines in b
    la = hb @ F  # lines in a
    r = np.abs(np.einsum("ij,ij->i", hb, lb))
    db = r / np.maximum(np.hypot(lb[:, 0], lb[:, 1]), 1e-300)
    da = r / np.maximum(np.hypot(la[:, 0], la[:, 1]), 1e-300)
    return np.asarray(0.5 * (da + db), np.float64)


@dataclass(frozen=True)
class _Seen:
    """A camera as the check sees it: undistorted, at the check's scale of its frames."""

    camera: Camera
    scale: float


@dataclass
class _Observed:
    """What the check keeps of its frame sets (no images, no descriptors: matches are found
    within a frame set, so a later check pools onto these without reading them again)."""

    times: list[int]
    """Per frame set: its time index."""
    seen: dict[int, _Seen]
    """Camera -> as the check sees it."""
    locations: list[dict[int, NDArray[np.float64]]]
    """Per frame set: camera -> its features' unique locations (view pixels)."""
    matches: dict[tuple[int, int], list[tuple[int, NDArray[np.int64]]]]
    """(a, b) -> [(frame set, (M, 2) location indices)]."""
    explained: dict[
        tuple[int, int], tuple[int, NDArray[np.float64], NDArray[np.float64], int | None]
    ] = field(default_factory=dict)
    """(a, b) -> ``_explained``'s answer, once computed."""

    def points(self, s: int, cam: int, loc: NDArray[np.int64]) -> NDArray[np.float64]:
        return self.locations[s][cam][loc]

    def view(self, cam: int) -> _Seen:
        return self.seen[cam]

    def subset(self, sets: Sequence[int]) -> _Observed:
        """These frame sets only (indices, in this order): what a check of them alone
        would have observed."""
        new = {old: s for s, old in enumerate(sets)}
        matches: dict[tuple[int, int], list[tuple[int, NDArray[np.int64]]]] = {}
        for key, parts in self.matches.items():
            kept = [(new[s], m) for s, m in parts if s in new]
            if kept:
                matches[key] = kept
        return _Observed(
            times=[self.times[s] for s in sets],
            seen=dict(self.seen),
            locations=[self.locations[s] for s in sets],
            matches=matches,
        )

    def camera(self, cam: int, rig: Rig) -> Camera:
        """Camera ``cam``'s view camera (undistorted, at the check's scale) posed as in
        ``rig`` (the features do not depend on the pose: one rig's observations check
        another)."""
        c = self.view(cam).camera
        return dataclasses.replace(c, R=rig[cam].R, t=rig[cam].t)


def _observe(
    sets: Sequence[FrameSet],
    rig: Rig,
    config: CalibrationCheckConfig,
    before: _Observed | None = None,
) -> _Observed:
    """The feature locations and pair matches of ``sets`` (after ``before``'s, which are
    kept as they are)."""
    times: list[int] = [] if before is None else list(before.times)
    seen: dict[int, _Seen] = {} if before is None else dict(before.seen)
    locations: list[dict[int, NDArray[np.float64]]] = (
        [] if before is None else list(before.locations)
    )
    matches: dict[tuple[int, int], list[tuple[int, NDArray[np.int64]]]] = (
        {} if before is None else {k: list(v) for k, v in before.matches.items()}
    )
    for s, fs in enumerate(sets, start=len(times)):
        vs = prepare_views(fs, rig, _scale(rig, config))
        fe = extract_all(vs, config.sparse)
        times.append(fs.time_index)
        for v in vs:
            seen.setdefault(v.camera_id, _Seen(v.camera, v.scale))
        locations.append(
            {
                v.camera_id: np.asarray(f.location_points2D, np.float64)
                for v, f in zip(vs, fe, strict=True)
            }
        )
        for i, j in combinations(range(len(vs)), 2):
            m = _mutual_matches(fe[i], fe[j], config.ratio)
            matches.setdefault((vs[i].camera_id, vs[j].camera_id), []).append((s, m))
    return _Observed(times, seen, locations, matches)


def _fundamental_inliers(
    pa: NDArray[np.float64], pb: NDArray[np.float64], threshold: float
) -> NDArray[np.bool_]:
    """Which matches a fundamental matrix estimated from them (MAGSAC) explains."""
    try:
        F, inl = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, threshold, 0.999, 10_000)
    except cv2.error:  # no model (degenerate matches: all on a line)
        F, inl = None, None
    if F is None or inl is None:
        return np.zeros(len(pa), bool)
    return np.asarray(inl.ravel().astype(bool))


def _chance(pa: NDArray[np.float64], pb: NDArray[np.float64], threshold: float, draws: int) -> int:
    """The most matches a fundamental matrix explains over ``draws`` random pairings of the
    same points (each image's points keep where they are, clusters included)."""
    rng = np.random.default_rng(len(pa))
    return max(
        (int(_fundamental_inliers(pa, pb[rng.permutation(len(pb))], threshold).sum())
         for _ in range(draws)),
        default=0,
    )  # fmt: skip


def _explained(
    obs: _Observed, a: int, b: int, config: CalibrationCheckConfig
) -> tuple[int, NDArray[np.float64], NDArray[np.float64], int | None]:
    """(matches, and those a fundamental matrix estimated from them explains, view pixels of
    a and b, how many it explains of them paired at random: ``CalibrationCheckConfig.
    chance_ratio``) of one pair, pooled over the frame sets (a static point's match repeats
    in each and counts once). It does not depend on the poses: computed once per check."""
    key = (a, b)
    if key not in obs.explained:
        unit = max(_unit(obs.view(a)), _unit(obs.view(b)))
        parts = obs.matches.get(key, [])
        pa = np.concatenate([obs.points(s, a, m[:, 0]) for s, m in parts] or [np.zeros((0, 2))])
        pb = np.concatenate([obs.points(s, b, m[:, 1]) for s, m in parts] or [np.zeros((0, 2))])
        _, first = np.unique(np.round(np.hstack([pa, pb]), 0), axis=0, return_index=True)
        pa, pb = pa[first], pb[first]
        keep = np.zeros(len(pa), bool)
        chance = None
        threshold = config.ransac_px * unit
        if len(pa) >= config.min_inliers:
            keep = _fundamental_inliers(pa, pb, threshold)
            if config.min_inliers <= keep.sum() < config.chance_below and config.chance_draws:
                chance = _chance(pa, pb, threshold, config.chance_draws)
        obs.explained[key] = (len(pa), pa[keep], pb[keep], chance)
    return obs.explained[key]


def _pair_inliers(
    obs: _Observed, a: int, b: int, config: CalibrationCheckConfig, rig: Rig
) -> tuple[PairCheck, NDArray[np.float64], NDArray[np.float64]]:
    """The check of one pair against ``rig``, and the matches it judged (view pixels)."""
    va = obs.view(a)
    unit = max(_unit(va), _unit(obs.view(b)))
    limit = config.max_error_px * unit / va.scale
    cos = float(np.clip(rig[a].R[2] @ rig[b].R[2], -1.0, 1.0))
    angle = round(float(np.degrees(np.arccos(cos))), 1)
    if angle > config.max_angle_deg:
        facing = PairCheck(
            a=a, b=b, matches=0, inliers=0, median_px=None, p90_px=None,
            limit_px=round(limit, 2), angle_deg=angle,
        )  # fmt: skip
        return facing, np.zeros((0, 2)), np.zeros((0, 2))
    matches, pa, pb, chance = _explained(obs, a, b, config)
    if len(pa) < max(config.min_inliers, config.chance_ratio * (chance or 0)):
        none = PairCheck(
            a=a, b=b, matches=matches, inliers=len(pa), median_px=None, p90_px=None,
            limit_px=round(limit, 2), angle_deg=angle, chance=chance,
        )  # fmt: skip
        return none, np.zeros((0, 2)), np.zeros((0, 2))
    d = epipolar_distances(obs.camera(a, rig), obs.camera(b, rig), pa, pb) / va.scale
    check = PairCheck(
        a=a,
        b=b,
        matches=matches,
        inliers=len(pa),
        median_px=round(float(np.median(d)), 2),
        p90_px=round(float(np.percentile(d, 90)), 2),
        limit_px=round(limit, 2),
        angle_deg=angle,
        chance=chance,
    )
    return check, pa, pb


def _verdicts(
    rig: Rig, pairs: Sequence[PairCheck], suspects: Collection[int] = ()
) -> tuple[list[CameraVerdict], bool | None]:
    """Which cameras are off. Each checked pair fits or not; weighted by their inliers, a
    camera's pairs mostly fit when it is right. One that turned has its own pairs mostly off
    while the pairs without it mostly fit: the camera with the largest such contrast is off
    (when its own pairs fit less than half and the others more than half), its pairs are set
    aside and the rest judged again, for a second one. A single pair that does not fit says
    little alone: two cameras facing each other share few features and match wrongly. A
    second camera is named only when its own pairs that miss hold as many inliers as a
    strong misfit (:func:`_strong_misfits`): with the first one's pairs set aside few are
    left, and a weak pair that missed before the knock named a camera that had not moved
    (utrecht4cam's cam1-cam4, 24 inliers 6 px off its calibration, when cam2 tilted).
    Nor is a camera named whose only checked pair is weak (fewer inliers than a strong
    misfit) unless it is one of ``suspects`` (its view was seen moving): wrong matches that
    a fundamental matrix explains in part lie anywhere (caliscope_charuco's cam_1-cam_2 over
    times 68, 77 and 96: 15 of 41 matches, 10 by chance, 337 px off a calibration that fits
    named cam_1 in a run where no view moved); it stays not checked."""
    checked = [p for p in pairs if p.checked]
    off: set[int] = set()

    while True:
        live = [p for p in checked if p.a not in off and p.b not in off]
        worst, contrast = None, 0.0
        for c in range(len(rig)):
            if c in off:
                continue
            own = [p for p in live if c in (p.a, p.b)]
            mine = _fit_share(own)
            rest = _fit_share([p for p in live if c not in (p.a, p.b)])
            if mine is None or rest is None or not (mine < 0.5 <= rest):
                continue
            if len(own) == 1 and own[0].inliers < _STRONG_INLIERS and c not in suspects:
                continue  # one weak pair alone: wrong matches can miss by hundreds of px
            missing = sum(p.inliers for p in live if c in (p.a, p.b) and not p.fits)
            if off and missing < _STRONG_INLIERS:
                continue  # a second camera on weak evidence
            if rest - mine > contrast:
                worst, contrast = c, rest - mine
        if worst is None:
            break
        off.add(worst)
    live = [p for p in checked if p.a not in off and p.b not in off]
    out = []
    for c in range(len(rig)):
        mine_live = [p for p in live if c in (p.a, p.b)]
        medians = [p.median_px for p in checked if c in (p.a, p.b) and p.median_px is not None]
        px: float | None
        if c in off:
            status = "off"
            px = float(np.median(medians))
        elif mine_live and (_fit_share(mine_live) or 0.0) >= 0.5:
            status = "ok"
            px = min(
                (p.median_px for p in mine_live if p.fits and p.median_px is not None), default=None
            )
        else:
            status = "unchecked"
            px = float(np.median(medians)) if medians else None
        out.append(CameraVerdict(camera=c, name=rig[c].name, status=status, median_px=px))
    if not checked:
        return out, None
    fits = any(p.fits for p in checked) and not off and not _strong_misfits(pairs)
    return out, fits


def _fit_share(pairs: Sequence[PairCheck]) -> float | None:
    """The share of the checked pairs' inliers in pairs that fit (None: no inliers)."""
    total = sum(p.inliers for p in pairs if p.checked)
    return None if total == 0 else sum(p.inliers for p in pairs if p.fits) / total


#: Inliers of a pair that does not fit, or of a camera's pairs that do not fit, that are too
#: many to be wrong matches.
_STRONG_INLIERS = 30


def _strong_misfits(
    pairs: Sequence[PairCheck], min_inliers: int = _STRONG_INLIERS
) -> list[PairCheck]:
    """Checked pairs with at least ``min_inliers`` inliers that do not fit: too many matches
    to be wrong ones (pairs with fewer can be: utrecht4cam's two cameras 105 degrees apart
    share 15, 115 px off the lines of a calibration that serves)."""
    return [p for p in pairs if p.checked and not p.fits and p.inliers >= min_inliers]


def check_calibration(
    frames: FrameSet | Sequence[FrameSet],
    rig: Rig,
    config: CalibrationCheckConfig | None = None,
    *,
    previous: CalibrationCheck | None = None,
) -> CalibrationCheck:
    """Whether the calibration fits the frames (see the module docstring): one frame set, or
    several whose matches are pooled per pair of cameras (people who move give new
    correspondences in each; the static scene's repeat and count once). ``previous``: a
    check of other frame sets of the same rig, whose features and matches join these (its
    frame sets are not read again)."""
    config = config or CalibrationCheckConfig()
    t0 = time.perf_counter()
    sets = [frames] if isinstance(frames, FrameSet) else list(frames)
    if not sets:
        raise DataError("calibration check: no frames")
    before = None if previous is None else previous.observed
    if previous is not None and before is None:
        raise DataError("calibration check: the previous check kept no matches")
    # FLANN's trees and MAGSAC draw from OpenCV's generator: seeded, one answer per input.
    cv2.setRNGSeed(0)
    obs = _observe(sets, rig, config, before)
    check = _judged(obs, rig, config)
    seconds = time.perf_counter() - t0 + (0.0 if previous is None else previous.seconds)
    check = dataclasses.replace(check, seconds=seconds)
    logger.info("%s", check.message)
    return check


def _judged(
    obs: _Observed, rig: Rig, config: CalibrationCheckConfig, suspects: Collection[int] = ()
) -> CalibrationCheck:
    times = tuple(sorted(obs.times))
    pairs = [_pair_inliers(obs, a, b, config, rig)[0] for a, b in sorted(obs.matches)]
    cameras, fits = _verdicts(rig, pairs, suspects)
    return CalibrationCheck(
        time_index=times[-1],
        times=times,
        pairs=tuple(pairs),
        cameras=tuple(cameras),
        fits=fits,
        frame_sets=len(times),
        observed=obs,
    )


def recheck(
    check: CalibrationCheck, rig: Rig, config: CalibrationCheckConfig | None = None
) -> CalibrationCheck:
    """``check``'s matches judged against another rig (the same cameras, other poses)."""
    if check.observed is None:
        raise DataError("recheck: the check kept no matches")
    return _judged(check.observed, rig, config or CalibrationCheckConfig())


@dataclass(frozen=True, kw_only=True)
class Repair:
    """What :func:`repair` did."""

    rig: Rig
    """The rig with the cameras it re-aimed or placed again."""
    applied: tuple[PoseEstimate, ...]
    """Their estimates, in order (``moved`` > 0: placed again)."""
    check: CalibrationCheck
    """The matches judged against ``rig``."""
    ambiguous: tuple[int, ...] = ()
    """Cameras of which any one, re-aimed, would make the pairs fit: the pairs cannot tell
    which turned (nothing was re-aimed then)."""


_Trial = tuple[float, "PoseEstimate", Rig, CalibrationCheck]


def _trial(
    check: CalibrationCheck, rig: Rig, camera: int, config: CalibrationCheckConfig, move: bool
) -> _Trial | None:
    """``camera`` posed again (:func:`estimate_pose`), when that brings its matches at least
    3 times closer to their lines, within ``max_move`` of where it was, and all its own
    pairs fit then: (the share of inliers fitting, the estimate, the rig, its check)."""
    est = estimate_pose(check, rig, camera, config, move=move)
    if est is None or est.after_px > est.before_px / 3:
        return None
    if move:
        centre = rig[camera].center
        nearest = min(
            float(np.linalg.norm(rig[o].center - centre)) for o in range(len(rig)) if o != camera
        )
        if est.moved > config.max_move * nearest:
            return None
        if est.moved < config.move_certainty * est.uncertainty:
            return None  # a move within the noise of the matches it came from
    posed = with_pose(rig, est)
    judged = recheck(check, posed, config)
    # Its pairs fit then (a turn: those of mostly right matches, which alone posed it).
    if not all(
        p.fits
        for p in judged.pairs
        if camera in (p.a, p.b) and (_sure(p, config) if not move else p.checked)
    ):
        return None
    return (_fit_share(judged.pairs) or 0.0, est, posed, judged)


def repair(
    check: CalibrationCheck,
    rig: Rig,
    config: CalibrationCheckConfig | None = None,
    *,
    suspects: Collection[int] = (),
) -> Repair:
    """Re-aim the cameras that turned, one at a time, against the pairs that fit (none fit:
    nothing is re-aimed). A camera in every pair that does not fit is a candidate (when
    there is none, every camera of such a pair): its
    orientation is found again (:func:`estimate_rotation`, at least 3 times closer to the
    lines) and the matches judged against the rig with it; it counts when all its own pairs
    fit then. The candidate that leaves the most inliers fitting is re-aimed, unless another
    one makes the pairs fit as well and leaves its matches no more than ``rival_ratio``
    times as far from their lines (then the pairs cannot tell which camera turned: nothing
    is re-aimed and both are named); then again, for a second camera.

    A turn is the commoner knock and the fewer change, so it names the camera; that camera
    is then placed again with its centre free (:func:`estimate_pose`) when that brings its
    matches ``move_gain`` closer to their lines (a small move is explained almost as well
    by a turn, with the wrong orientation), unless the turn already leaves them closer to
    their lines than the other cameras' pairs lie to theirs (the rest the matches cannot
    tell from the calibration's own error). When no turn of any candidate makes every pair
    fit, the candidates are also placed again with their centres free, and one that leaves
    more inliers fitting than any turn is taken, under the same rules.

    ``suspects``: the only cameras that can have moved, when known (a run whose check fit,
    then saw these cameras' views move: ``quality.frames.MovedCameras``): those of them in a
    pair that misses are the only candidates, so a camera whose view did not move is no
    rival (utrecht4cam's cam2 rolled 3 degrees, which cam4's turn explains 3.0 times less
    well: "cam2 or cam4" without them)."""
    config = config or CalibrationCheckConfig()
    applied: list[PoseEstimate] = []
    for _ in range(len(rig)):
        if check.fits is not False or not any(p.fits for p in check.pairs):
            break  # fits, or nothing to re-aim against (a swap, another setup's file)
        bad = [p for p in check.pairs if p.checked and not p.fits]
        # One camera that moved is in every pair that misses: when one is, only such are
        # candidates (a neighbour's turn can absorb one of its pairs); else any camera of a
        # pair that misses (two moved).
        common = set.intersection(*({p.a, p.b} for p in bad)) if bad else set()
        candidates = sorted(common or {p.a for p in bad} | {p.b for p in bad})
        seen = ({p.a for p in bad} | {p.b for p in bad}) & set(suspects)
        if seen:
            candidates = sorted(seen)
        trials = [t for c in candidates if (t := _trial(check, rig, c, config, False))]
        placements: dict[int, _Trial | None] = {}  # each camera placed once (a jackknife)
        if max((t[0] for t in trials), default=0.0) < 1.0:
            # No turn makes every pair fit: a camera moved? It is placed again when that
            # leaves more pairs fitting than any turn (a neighbour's turn can absorb most of
            # a moved camera's error on a pair they share).
            placements = {c: _trial(check, rig, c, config, True) for c in candidates}
            placed = [t for t in placements.values() if t]
            best = max((t[0] for t in trials), default=0.0)
            if any(t[0] > best + 0.02 for t in placed):
                trials = trials + placed  # a turn first among equals
        if not trials:
            break
        # The most inliers fitting first; among equals a turn, then the camera whose matches
        # it brings closest to their lines.
        spread = {id(t): _camera_median(check, t[2], t[1].camera, config) for t in trials}
        trials.sort(key=lambda t: (-t[0], t[1].moved > 0, spread[id(t)]))
        share, est, posed, judged = trials[0]
        best_px = spread[id(trials[0])]
        if share <= (_fit_share(check.pairs) or 0.0):
            break
        rivals = [
            t
            for t in trials[1:]
            if t[1].camera != est.camera
            and t[3].fits
            and t[0] >= share - 0.05
            and spread[id(t)] <= config.rival_ratio * best_px
        ]
        # A camera the check named whose matches cannot pose it at all (one pair with the
        # others that fit: caliscope_charuco's cam_1) is not ruled out by another camera's
        # turn that makes its one pair fit (cam_1 moved 5 cm: cam_0 turned 0.3 degrees).
        unposed = (
            [
                c
                for c in check.off
                if c != est.camera
                and (not suspects or c in suspects)
                and estimate_pose(check, rig, c, config, move=False) is None
            ]
            if judged.fits
            else []
        )
        if judged.fits and (rivals or unposed):
            return Repair(
                rig=rig,
                applied=tuple(applied),
                check=check,
                ambiguous=tuple(sorted({est.camera, *(t[1].camera for t in rivals), *unposed})),
            )
        # The other cameras' agreement: a turn that leaves this camera's matches closer to
        # their lines than the other pairs lie to theirs leaves a move nothing the matches
        # can tell from the calibration's own error (utrecht4cam's cam2 tilted 1 degree,
        # turned back to 0.8 px where its other pairs lie 3 px off: placed 1 m away).
        level = [
            p.median_px
            for p in check.pairs
            if p.median_px is not None and p.fits and est.camera not in (p.a, p.b)
        ]
        if est.moved == 0.0 and best_px > float(np.median(level) if level else 0.0):
            # Turned, or moved, which a turn explains less well.
            refined = (
                placements[est.camera]
                if est.camera in placements
                else _trial(check, rig, est.camera, config, True)
            )
            if (
                refined is not None
                and refined[0] >= share
                and _camera_median(check, refined[2], est.camera, config)
                <= config.move_gain * best_px
            ):
                share, est, posed, judged = refined
        rig, check = posed, judged
        applied.append(est)
    return Repair(rig=rig, applied=tuple(applied), check=check)


@dataclass(frozen=True, kw_only=True)
class PoseEstimate:
    """A camera's pose found from the scene (:func:`estimate_rotation`,
    :func:`estimate_pose`)."""

    camera: int
    R: NDArray[np.float64]
    """(3, 3) its ``cam_from_world`` rotation now."""
    t: NDArray[np.float64]
    """(3,) its translation (``-R @ centre``)."""
    pairs: int
    """Camera pairs whose matches placed it."""
    matches: int
    """Their matches."""
    before_px: float
    """Median distance of those matches to the epipolar lines with the calibrated pose ..."""
    after_px: float
    """... and with this one (pixels of the frames)."""
    rotation_deg: float
    """Angle between the calibrated orientation and this one."""
    moved: float = 0.0
    """Distance between the calibrated centre and this one (rig units; 0: the centre was
    kept)."""
    uncertainty: float = 0.0
    """How far off the centre could be (rig units; 0: kept): how far it moves with the
    matches it came from (the jackknife's standard error over five parts of them)."""


_Data = list[tuple[Camera, NDArray[np.float64], NDArray[np.float64]]]
"""(the other camera, this camera's points, the other's points) per pair."""


def _sure(pair: PairCheck, config: CalibrationCheckConfig) -> bool:
    """Whether a pair's inliers are mostly right matches (``pose_chance_ratio``)."""
    return pair.checked and (
        pair.chance is None or pair.inliers >= config.pose_chance_ratio * pair.chance
    )


def _camera_data(
    obs: _Observed, rig: Rig, camera: int, config: CalibrationCheckConfig, sure: bool = False
) -> _Data:
    """(the other camera, ``camera``'s points, the other's points) of each checked pair of
    ``camera`` (``sure``: of those whose inliers are mostly right matches, :func:`_sure`)."""
    data = []
    for a, b in sorted(ab for ab in obs.matches if camera in ab):
        pair, pa, pb = _pair_inliers(obs, a, b, config, rig)
        if not (_sure(pair, config) if sure else pair.checked):
            continue
        mine, theirs = (pa, pb) if a == camera else (pb, pa)
        data.append((obs.camera(b if a == camera else a, rig), mine, theirs))
    return data


def _camera_median(
    check: CalibrationCheck, rig: Rig, camera: int, config: CalibrationCheckConfig
) -> float:
    """Median distance of all ``camera``'s checked matches to their epipolar lines with the
    poses of ``rig`` (pixels of the frames; inf without any)."""
    obs = check.observed
    if obs is None:
        return float("inf")
    cam = obs.camera(camera, rig)
    d = [epipolar_distances(cam, o, m, t) for o, m, t in _camera_data(obs, rig, camera, config)]
    if not d:
        return float("inf")
    return float(np.median(np.concatenate(d))) / obs.view(camera).scale


def _jackknife(
    x: NDArray[np.float64],
    data: _Data,
    solve: Callable[[NDArray[np.float64], _Data], NDArray[np.float64]],
    cam_at: Callable[[NDArray[np.float64]], Camera],
    folds: int = 5,
) -> float:
    """How far the centre found moves with the matches it came from: the jackknife's
    standard error over ``folds`` parts of every pair's matches (rig units)."""
    rng = np.random.default_rng(0)
    labels = [rng.permutation(len(mine)) % folds for _, mine, _ in data]
    centres = []
    for k in range(folds):
        part = [(o, m[f != k], t[f != k]) for (o, m, t), f in zip(data, labels, strict=True)]
        centres.append(cam_at(solve(x, part)).center)
    spread = np.asarray(centres) - np.mean(centres, axis=0)
    return float(np.sqrt((folds - 1) / folds * np.sum(spread**2)))


def estimate_rotation(
    check: CalibrationCheck,
    rig: Rig,
    camera: int,
    config: CalibrationCheckConfig | None = None,
) -> PoseEstimate | None:
    """The orientation of ``camera`` now, its centre kept (a camera turned on its tripod or
    mount: the usual knock), from the matches ``check`` found: the rotation that brings its
    matches with the other cameras closest to their epipolar lines (robust least squares
    over the three angles, then without the matches that still miss: a pair with a camera
    that is off too keeps few). Two pairs with different baselines fix all three angles;
    None with fewer, or without the check's matches."""
    return estimate_pose(check, rig, camera, config, move=False)


def estimate_pose(
    check: CalibrationCheck,
    rig: Rig,
    camera: int,
    config: CalibrationCheckConfig | None = None,
    *,
    move: bool = True,
) -> PoseEstimate | None:
    """The pose of ``camera`` now, from the matches ``check`` found: first the turn about its
    calibrated centre (:func:`estimate_rotation`), then, with ``move``, its centre free too
    (a tripod kicked to another place): the six parameters that bring its matches with the
    other cameras closest to their epipolar lines. Each pair's lines fix the direction from
    the other camera to this one, so two pairs whose cameras do not lie on one line with it
    place its centre (a turn alone explains a small sideways move almost as well, with the
    wrong orientation: hd4, 1 m sideways at 4.6 m from the neighbours was explained by a
    16.5-degree turn to 0.64 px; placed again, 0.03 degrees and 7 mm from the truth).
    Least squares with a loss that gives wrong matches no weight (Cauchy's), tightened in
    steps; ``uncertainty`` says how far off the centre could be. None with fewer than two
    pairs of mostly right matches (``pose_chance_ratio``: a turn is found from those alone),
    when the turn's matches that come back to their lines lie in one pair, or without the
    check's matches."""
    from scipy.optimize import least_squares

    config = config or CalibrationCheckConfig()
    obs = check.observed
    if obs is None:
        return None
    # A turn from the pairs of mostly right matches; a move (the bolder claim) from every
    # checked pair, and only when two of them are such pairs.
    if sum(1 for p in check.pairs if camera in (p.a, p.b) and _sure(p, config)) < 2:
        return None
    data = _camera_data(obs, rig, camera, config, sure=not move)
    view = obs.view(camera)
    cam0 = obs.camera(camera, rig)
    centre = cam0.center
    # The centre's parameters in units of the distance to the other cameras (the angles are
    # in radians: both of order one for the solver).
    span = float(np.median([np.linalg.norm(other.center - centre) for other, _, _ in data]))

    def cam_at(x: NDArray[np.float64]) -> Camera:
        R = np.asarray(cv2.Rodrigues(x[:3])[0], np.float64) @ cam0.R
        return dataclasses.replace(cam0, R=R, t=-R @ (centre + x[3:] * span))

    def residuals(x: NDArray[np.float64], d: _Data | None = None) -> NDArray[np.float64]:
        c = cam_at(x)
        return np.concatenate(
            [epipolar_distances(c, other, mine, theirs) for other, mine, theirs in d or data]
        )

    # A turn about an axis the matches barely see (a pan along a level ring's epipolar
    # lines) stays near the calibration: a prior of ``turn_prior_deg`` on each angle against
    # the matches' pixel of noise (view pixels).
    prior = _unit(obs.view(camera)) / np.radians(config.turn_prior_deg)

    def turn(x: NDArray[np.float64], f_scale: float) -> NDArray[np.float64]:
        w = least_squares(
            lambda w: np.r_[residuals(np.r_[w, x[3:]]), prior * w],
            x[:3],
            loss="soft_l1",
            f_scale=f_scale,
        ).x
        return np.r_[w, x[3:]]

    def place(x: NDArray[np.float64], d: _Data, scales: Sequence[float]) -> NDArray[np.float64]:
        for f_scale in scales:
            x = np.asarray(
                least_squares(lambda v: residuals(v, d), x, loss="cauchy", f_scale=f_scale).x
            )
        return x

    limit = config.max_error_px * _unit(view)
    zero = np.zeros(6)
    x = turn(zero, limit / 4)
    if move:
        # The centre free too, from the turn: a loss that gives wrong matches no weight,
        # tightened in steps, over all the matches (left out by a pose still off, the right
        # matches went first and the fit locked in: hd4's cam1 placed 10 cm off; 7 mm so).
        x = place(x, data, (limit / 4, limit / 8, limit / 16))
    else:
        # The matches that still miss their lines are left out (wrong matches: two cameras
        # far apart share few features), tighter each round, and a pair left with fewer
        # than 8 matches with them.
        for tol in (limit, limit / 2, limit / 4):
            c = cam_at(x)
            trimmed = []
            for other, mine, theirs in data:
                ok = epipolar_distances(c, other, mine, theirs) <= tol
                if ok.sum() >= 8:
                    trimmed.append((other, mine[ok], theirs[ok]))
            if len(trimmed) < 2:
                # The matches a turn brings back lie in one pair: one pair of a few matches
                # is fitted by a wrong turn too (caliscope_charuco's cam_1 tilted 2 degrees,
                # 14 matches left with cam_0: re-aimed by 12.3 degrees, "fits").
                return None
            data = trimmed
            x = turn(x, tol / 4)
    c = cam_at(x)
    after = float(np.median(residuals(x))) / view.scale
    uncertainty = 0.0
    if move:
        uncertainty = _jackknife(x, data, lambda x, d: place(x, d, (limit / 16,)), cam_at)
    return PoseEstimate(
        camera=camera,
        R=np.asarray(c.R, np.float64),
        t=np.asarray(c.t, np.float64),
        pairs=len(data),
        matches=sum(len(m) for _, m, _ in data),
        before_px=float(np.median(residuals(zero))) / view.scale,
        after_px=after,
        rotation_deg=rotation_angle_deg(c.R, cam0.R),
        moved=float(np.linalg.norm(c.center - centre)) if move else 0.0,
        uncertainty=uncertainty,
    )


def with_pose(rig: Rig, estimate: PoseEstimate) -> Rig:
    """The rig with ``estimate``'s camera at its new pose."""
    cams = list(rig)
    cams[estimate.camera] = dataclasses.replace(
        cams[estimate.camera], R=estimate.R.copy(), t=estimate.t.copy()
    )
    return dataclasses.replace(rig, cameras=tuple(cams))


def knocked(rig: Rig, camera: int, shift: Sequence[float], degrees: Sequence[float]) -> Rig:
    """``rig`` with one camera moved by ``shift`` along its own axes (x right, y down, z
    forward; rig units) and turned by ``degrees`` about them: a knock simulated
    (``benchmarks/bench_calib.py``, the tests)."""
    c = rig[camera]
    R = np.asarray(cv2.Rodrigues(np.radians(np.asarray(degrees, float)))[0], np.float64) @ c.R
    centre = c.center + c.R.T @ np.asarray(shift, float)
    cams = list(rig)
    cams[camera] = dataclasses.replace(c, R=R, t=-R @ centre)
    return dataclasses.replace(rig, cameras=tuple(cams))


def try_repair(check: CalibrationCheck, rig: Rig, suspects: Collection[int] = ()) -> Repair | None:
    """:func:`repair` when the calibration does not fit the frames; None when it fits, or
    when the repair raises (said once: the check stands without it)."""
    if check.fits is not False:
        return None
    try:
        return repair(check, rig, suspects=suspects)
    except Exception as exc:
        logger.warning("calibration: the repair could not be worked out: %s", exc)
        return None


def repair_summary(fix: Repair, rig: Rig) -> str:
    """What :func:`repair` did, in a line: the cameras re-aimed or placed again and whether
    every pair fits then, the cameras it could not tell between, or that nothing did."""
    names = rig.names
    if fix.applied:
        done = "; ".join(
            f"{names[e.camera]} placed again ({e.moved:.3g} {rig.unit} from its calibration, "
            f"turned {e.rotation_deg:.2f} degrees)"
            if e.moved
            else f"{names[e.camera]} re-aimed by {e.rotation_deg:.2f} degrees"
            for e in fix.applied
        )
        after = "the calibration then fits" if fix.check.fits else "still does not fit"
        return f"{done}: {after}"
    if fix.ambiguous:
        return (
            "re-aiming any of "
            + " or ".join(names[c] for c in fix.ambiguous)
            + " makes the pairs fit: which one moved is not told"
        )
    return "no turn or move of one camera makes the pairs fit: calibrate again"


def calibration_verdict(rig: Rig, frames: FrameSet | Sequence[FrameSet]) -> dict[str, Any]:
    """``check_calibration``'s answer as a small dict (what a run's back-end sends on):
    ``time``, ``fits``, ``off`` (camera names), ``message``; when it does not fit, also
    ``repair``: what ``edgerecon calib --write`` would do (:func:`repair_summary`), and when
    that makes the calibration fit, ``repaired_rig``: that rig in world coordinates (rig
    JSON, ``Rig.to_dict``; a run writes it as ``rig.repaired.json``)."""
    return _verdict(check_calibration(frames, rig), rig)


def _verdict(check: CalibrationCheck, rig: Rig, suspects: Collection[int] = ()) -> dict[str, Any]:
    verdict = {
        "time": check.time_index,
        "times": list(check.times),
        "fits": check.fits,
        "off": check.off_names,
        "unchecked": [v.name for v in check.cameras if v.status == "unchecked"],
        "short": check.short,
        "message": check.message,
    }
    fix = try_repair(check, rig, suspects)
    if fix is not None:
        verdict["repair"] = repair_summary(fix, rig)
        if fix.applied and fix.check.fits:
            verdict["repaired_rig"] = fix.rig.in_world().to_dict()
    return verdict


@dataclass(frozen=True)
class CheckPool:
    """The matches a run's calibration checks keep between them (:func:`pooled_verdict`):
    feature locations and matches of up to ``keep`` frame sets, no images (a few MB)."""

    observed: _Observed

    @property
    def times(self) -> tuple[int, ...]:
        return tuple(sorted(self.observed.times))


#: Frame sets a check pools for a camera that 3 cannot check (``edgerecon calib`` reads that
#: many spread over the stream; a run's checks keep that many of their newest).
POOLED_FRAME_SETS = 7


def pooled_verdict(
    rig: Rig,
    frames: Sequence[FrameSet],
    pool: CheckPool | None = None,
    *,
    keep: int = POOLED_FRAME_SETS,
    config: CalibrationCheckConfig | None = None,
    suspects: Sequence[str] = (),
) -> tuple[dict[str, Any], CheckPool]:
    """A run's check (:func:`calibration_verdict`'s answer) of ``frames``, its newest frame
    sets, with the matches of the earlier checks (``pool``; the frame sets it holds are not
    read again) and the pool to keep: the newest ``keep`` frame sets.

    The verdict is that of ``frames`` alone when they name a camera, find that nothing fits
    or check every camera: a camera knocked during the run is told at once, not outvoted by
    the frame sets before the knock. Otherwise (a camera that shares few features with the
    others in these frames: a person's few matches) it is that of the whole pool, as
    ``edgerecon calib`` reads more frame sets for a camera that 3 cannot check.
    ``suspects``: the only cameras that can have moved, when the run knows them
    (:func:`repair`)."""
    config = config or CalibrationCheckConfig()
    if not frames:
        raise DataError("calibration check: no frames")
    before = None if pool is None else pool.observed
    known = set() if before is None else set(before.times)
    new = [fs for fs in frames if fs.time_index not in known]
    t0 = time.perf_counter()
    cv2.setRNGSeed(0)
    obs = _observe(new, rig, config, before) if new or before is None else before
    newest = sorted(range(len(obs.times)), key=lambda s: obs.times[s])[-keep:]
    obs = obs.subset(newest)
    mine = {fs.time_index for fs in frames}
    fresh = [s for s, t in enumerate(obs.times) if t in mine]
    moved = [rig.names.index(n) for n in suspects if n in rig.names]
    these = obs.subset(fresh) if len(fresh) < len(obs.times) else obs
    check = _judged(these, rig, config, moved)
    unchecked = any(v.status == "unchecked" for v in check.cameras)
    if check.fits is not False and unchecked and len(fresh) < len(obs.times):
        check = _judged(obs, rig, config, moved)
    check = dataclasses.replace(check, seconds=time.perf_counter() - t0)
    logger.info("%s", check.message)
    verdict = _verdict(check, rig, moved)
    verdict["seconds"] = round(check.seconds, 2)
    return verdict, CheckPool(obs.subset(range(len(obs.times))))


def verdict_row(verdict: dict[str, Any]) -> tuple[str, str]:
    """A summary table's row of a :func:`calibration_verdict` (a run's, a report's)."""
    value = str(verdict.get("short"))
    if verdict.get("repair"):
        # A run's repair is in its folder; a report's verdict says what calib would write.
        where = verdict.get("repaired_rig_file")
        value += f"; {where}: " if where else "; calib --write: "
        value += str(verdict["repair"])
    t = verdict.get("time")
    return ("calibration" if t is None else f"calibration against the frames (time {t})", value)
