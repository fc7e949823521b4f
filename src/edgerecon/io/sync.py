"""Synchronisation offsets from the videos themselves: cameras started at different moments.

Phones or action cameras started by hand begin recording up to seconds apart; a frame offset
per camera (``FrameSpec.offsets``: time index t is that camera's frame t + K) makes their
frames show the same moment. ``estimate_offsets`` finds the offsets from what every camera
sees: when people or things move, every camera that sees them sees motion at the same moments.

1. **Motion signal** per camera: each frame reduced to ``width_px`` pixels wide (grey, area
   averaging), the mean absolute difference from the previous frame after the difference's
   median is removed (a global brightness change, an exposure step, is not motion): one
   number per time index.
2. **Lag per pair** of cameras: the generalised cross-correlation with phase transform
   (GCC-PHAT, Knapp and Carter 1976) of the two signals up to ``max_offset_s``
   (``best_lag``): the cross-spectrum is whitened, so the peak is sharp however smooth the
   signals are, and two cameras that see different people most (each camera's signal is
   dominated by whoever is nearest) still agree on when things happen. The peak's height
   and the next peak's, as robust z-scores over the lags: a periodic motion gives several
   peaks, the margin tells how sure the best is. (Plain correlation of the signals found
   confident wrong lags on the ``hd4`` preset's four walking actors: docs/BENCHMARKS.md.)
3. **Offsets** from the confident pairs (peak >= ``min_peak`` and margin >= ``min_margin``)
   by least squares over the pairs' lags (``o_i - o_j = d_ij``), camera by camera from the
   best-linked one; a pair whose lag disagrees with the solution by more than a frame is
   dropped and the solve repeated. When the confident pairs link the cameras in separate
   groups, only the largest group's offsets are taken (the groups are on different clocks).
4. **Consensus**: a camera no confident pair links is matched once more, against the linked
   cameras' signals aligned by their offsets and averaged (what they all saw adds up, their
   own noise does not), with the same confidence test. (Counting the votes of its weak pairs
   instead joined a camera at a wrong lag: two weak pairs with linked cameras agree by
   construction when those cameras agree with each other.) Cameras still unlinked stay at
   the best-linked camera's time and are named.

The signals are read on the source's own time base, so videos paired by timestamps
(different or variable frame rates, ``VideoFrameSource``) are compared in time, and the
offsets are converted back to each camera's own frames.

What it cannot do: a capture with no motion in the window (an empty room), or motion seen
by one camera only, has nothing to align; a purely periodic motion (a metronome) is
ambiguous beyond its period (the margin says so and the offsets are not applied). Offsets
are whole frames: at 30 fps the cameras can still be up to 17 ms apart.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.io.frames import FrameSource
from edgerecon.progress import track
from edgerecon.types import DataError, Image


@dataclass(frozen=True, kw_only=True)
class SyncConfig:
    """Parameters of ``estimate_offsets``."""

    window_s: float = 30.0
    """Stream time read from the start (the whole stream when shorter): every frame of it is
    decoded (4 cameras at 1920x1080, H.264: 11 ms per time index, 10 s for 30 s at 30 fps)."""
    max_offset_s: float = 10.0
    """Largest offset between two cameras searched (seconds)."""
    width_px: int = 96
    """Frames are reduced to this width (aspect kept) for the motion signal."""
    max_share: float = 0.5
    """Lags are searched up to this share of the frames read (and ``max_offset_s``)."""
    min_peak: float = 4.0
    """A pair's correlation peak must stand this many robust standard deviations above the
    correlation's median over the lags ..."""
    min_margin: float = 1.5
    """... and this many above the next highest peak (a periodic motion has several)."""

    def __post_init__(self) -> None:
        for name in ("window_s", "max_offset_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SyncConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.width_px < 8:
            raise ValueError(f"SyncConfig.width_px must be >= 8, got {self.width_px}")
        if not 0 < self.max_share <= 1:
            raise ValueError(f"SyncConfig.max_share must be in (0, 1], got {self.max_share}")


@dataclass(frozen=True, kw_only=True)
class PairLag:
    """The lag between two cameras' motion signals: camera ``a``'s time index t + ``lag``
    shows what camera ``b`` shows at t."""

    a: str
    b: str
    lag: int
    peak: float
    """Height of the correlation peak at ``lag`` (robust z-score over the lags)."""
    second: float
    """Height of the next highest peak."""
    confident: bool
    used: bool = False
    """Whether the solution kept it."""


@dataclass(frozen=True, kw_only=True)
class SyncResult:
    """What ``estimate_offsets`` found."""

    offsets: dict[str, int]
    """Per camera, its offset in its own frames (>= 0; time index t is its frame t + K)."""
    lags: dict[str, int]
    """Per camera, its offset in time indices of the source (before conversion)."""
    unlinked: list[str]
    """Cameras neither a confident pair nor the consensus linked (offset 0)."""
    pairs: list[PairLag]
    joined: dict[str, tuple[int, float, float]] = field(default_factory=dict)
    """Cameras tried against the linked cameras' consensus: (lag, peak, second)."""
    frames_read: int
    fps: float | None
    seconds: float
    activity: dict[str, float] = field(default_factory=dict)
    """Per camera, the median of its motion signal (0: it saw nothing move)."""

    @property
    def ok(self) -> bool:
        """Every camera linked."""
        return not self.unlinked

    def to_dict(self) -> dict[str, Any]:
        return {
            "offsets": self.offsets,
            "lags": self.lags,
            "unlinked": self.unlinked,
            "pairs": [
                {**p.__dict__, "peak": _finite(p.peak), "second": _finite(p.second)}
                for p in self.pairs
            ],
            "joined": {
                n: [lag, _finite(peak), _finite(second)]
                for n, (lag, peak, second) in self.joined.items()
            },
            "frames_read": self.frames_read,
            "fps": self.fps,
            "seconds": self.seconds,
            "activity": self.activity,
        }


def _finite(x: float) -> float | None:
    """``x``, or None where it is NaN or infinite (JSON has neither)."""
    return float(x) if np.isfinite(x) else None


def _reduced(image: Image, width: int) -> NDArray[np.float32]:
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    h, w = grey.shape[:2]
    if w > width:
        grey = cv2.resize(grey, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    return np.asarray(grey, np.float32)


class _Motion:
    """One camera's motion signal, a frame at a time (only the last reduced frame is kept)."""

    def __init__(self, width_px: int) -> None:
        self.width_px = width_px
        self.values: list[float] = []
        self._prev: NDArray[np.float32] | None = None

    def add(self, image: Image | None) -> None:
        cur = None if image is None else _reduced(image, self.width_px)
        prev = self._prev
        if cur is None or prev is None or cur.shape != prev.shape:
            self.values.append(np.nan if self.values else 0.0)
        else:
            diff = cur - prev
            self.values.append(float(np.mean(np.abs(diff - np.median(diff)))))
        self._prev = cur

    def signal(self) -> NDArray[np.float64]:
        return np.asarray(self.values, np.float64)


def _local_maxima(values: NDArray[np.float64]) -> NDArray[np.intp]:
    """Indices of the local maxima of a 1-D array (plateaus count once), highest first."""
    v = np.asarray(values, np.float64)
    left = np.concatenate([[True], v[1:] > v[:-1]])
    right = np.concatenate([v[:-1] >= v[1:], [True]])
    idx = np.flatnonzero(left & right)
    return idx[np.argsort(-v[idx], kind="stable")]


def best_lag(
    a: NDArray[np.float64], b: NDArray[np.float64], max_lag: int
) -> tuple[int, float, float]:
    """(lag, peak, second): the lag d at which ``a[t + d]`` best matches ``b[t]`` by the
    generalised cross-correlation with phase transform (GCC-PHAT: the cross-spectrum
    whitened, so that a peak is sharp whatever the signals' own smoothness, and the cameras'
    different views of the same motion still agree on its timing), over |d| <= ``max_lag``;
    the peak's height and the next local maximum's, both as robust z-scores over the lags
    (median and MAD). NaN samples count as the signal's median."""
    n = min(len(a), len(b))
    if n < 4 or max_lag < 1:
        return 0, float("nan"), float("nan")
    a, b = _centred(a[:n]), _centred(b[:n])
    size = 2 * n
    cross = np.fft.rfft(a, size) * np.conj(np.fft.rfft(b, size))
    cross /= np.maximum(np.abs(cross), 1e-12)
    r = np.fft.irfft(cross, size)
    max_lag = min(max_lag, n - 1)
    lags = np.arange(-max_lag, max_lag + 1)
    values = r[lags % size]
    med = float(np.median(values))
    mad = 1.4826 * float(np.median(np.abs(values - med)))
    if not mad > 0:
        return 0, float("nan"), float("nan")
    z = (values - med) / mad
    peaks = _local_maxima(z)
    best = int(peaks[0])
    second = float(z[peaks[1]]) if len(peaks) > 1 else float("-inf")
    return int(lags[best]), float(z[best]), second


def _centred(x: NDArray[np.float64]) -> NDArray[np.float64]:
    x = np.asarray(x, np.float64).copy()
    ok = np.isfinite(x)
    x[~ok] = np.median(x[ok]) if ok.any() else 0.0
    if len(x):
        x[0] = np.median(x)  # the first sample has no previous frame
    return x - x.mean()


def _groups(names: list[str], links: list[tuple[str, str]]) -> dict[str, str]:
    """Per camera, a representative of its connected group under ``links``."""
    parent = {n: n for n in names}

    def root(n: str) -> str:
        while parent[n] != n:
            n = parent[n]
        return n

    for a, b in links:
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[ra] = rb
    return {n: root(n) for n in names}


def _solve(names: list[str], pairs: list[PairLag]) -> tuple[dict[str, int], list[str], set[int]]:
    """Offsets (time indices) from the confident pairs (step 3 of the module docstring): per
    connected group of cameras, weighted least squares with its best-linked camera at 0; the
    pair furthest off the solution, when more than one frame off, is dropped and the groups
    solved again. The largest group is the linked one (two groups' offsets are on different
    clocks). Returns the offsets, the unlinked cameras and the pairs kept."""
    active = {k for k, p in enumerate(pairs) if p.confident}
    while True:
        group = _groups(names, [(pairs[k].a, pairs[k].b) for k in active])
        lags = dict.fromkeys(names, 0.0)
        for rep in set(group.values()):
            members = [n for n in names if group[n] == rep]
            links = [k for k in active if group[pairs[k].a] == rep]
            if not links:
                continue
            degree = {n: sum(n in (pairs[k].a, pairs[k].b) for k in links) for n in members}
            anchor = max(members, key=lambda n: (degree[n], -names.index(n)))
            cols = [n for n in members if n != anchor]
            A = np.zeros((len(links), len(cols)))
            y = np.zeros(len(links))
            for row, k in enumerate(links):
                p, w = pairs[k], max(pairs[k].peak, 1e-3)
                if p.a != anchor:
                    A[row, cols.index(p.a)] = w
                if p.b != anchor:
                    A[row, cols.index(p.b)] = -w
                y[row] = w * p.lag
            for n, v in zip(cols, np.linalg.lstsq(A, y, rcond=None)[0], strict=True):
                lags[n] = float(v)
        off = {k: abs(lags[pairs[k].a] - lags[pairs[k].b] - pairs[k].lag) for k in active}
        worst = max(off, key=lambda k: off[k], default=None)
        if worst is None or off[worst] <= 1.0:
            break
        active.discard(worst)
    # Only one group's offsets are on one clock: the largest (then the strongest) one's.
    # Another group's cameras are unlinked (the consensus may still join them).
    strength: dict[str, tuple[int, float]] = {}
    for rep in set(group.values()):
        members = [n for n in names if group[n] == rep]
        weight = sum(pairs[k].peak for k in active if group[pairs[k].a] == rep)
        strength[rep] = (len(members) if weight > 0 else 0, weight)
    main = max(strength, key=lambda r: strength[r])
    kept = {k for k in active if group[pairs[k].a] == main}
    linked = {n for n in names if group[n] == main} if kept else set()
    return (
        {n: round(lags[n]) if n in linked else 0 for n in names},
        [n for n in names if n not in linked],
        kept,
    )


def _zscore(x: NDArray[np.float64]) -> NDArray[np.float64]:
    x = _centred(x)
    sd = float(x.std())
    return x / sd if sd > 0 else x


def _join_unlinked(
    signals: dict[str, NDArray[np.float64]],
    lags: dict[str, int],
    unlinked: list[str],
    max_lag: int,
    config: SyncConfig,
) -> tuple[dict[str, int], list[str], dict[str, tuple[int, float, float]]]:
    """Step 4 of the module docstring: each unlinked camera against the linked cameras'
    consensus (their normalised signals aligned by their offsets and averaged: the noise of
    each averages out, what they all saw stays), joined when that one peak is confident.
    Returns the offsets, the cameras still unlinked and, per camera tried, (lag, peak,
    second)."""
    linked = [n for n in lags if n not in unlinked]
    lags, still = dict(lags), list(unlinked)
    tried: dict[str, tuple[int, float, float]] = {}
    if len(linked) < 2:
        return lags, still, tried
    base = min(lags[n] for n in linked)
    shift = {n: lags[n] - base for n in linked}
    length = min(len(signals[n]) - shift[n] for n in linked)
    if length < 4:
        return lags, still, tried
    consensus = np.mean([_zscore(signals[n])[shift[n] : shift[n] + length] for n in linked], axis=0)
    for cam in unlinked:
        lag, peak, second = best_lag(signals[cam], consensus, max_lag)
        tried[cam] = (lag, peak, second)
        if np.isfinite(peak) and peak >= config.min_peak and peak - second >= config.min_margin:
            lags[cam] = lag + base
            still.remove(cam)
    return lags, still, tried


def estimate_offsets(
    source: FrameSource,
    config: SyncConfig | None = None,
    *,
    progress: bool = False,
) -> SyncResult:
    """Frame offsets that synchronise the cameras of ``source`` (see the module docstring);
    ``source`` is read without offsets of its own from its first frame."""
    config = config or SyncConfig()
    t0 = time.perf_counter()
    names = list(source.camera_names)
    if len(names) < 2:
        raise DataError("synchronising needs at least two cameras")
    fps = source.fps
    rate = fps if fps is not None and fps > 0 else 25.0
    n = min(source.num_frames, max(2, round(config.window_s * rate)))
    motions = [_Motion(config.width_px) for _ in names]
    steps = track(range(n), "reading frames for synchronisation") if progress else range(n)
    for t in steps:
        for motion, image in zip(motions, source.read(t).images, strict=True):
            motion.add(image)
    per_camera = [m.signal() for m in motions]
    activity = {
        name: float(np.nanmedian(s[1:])) if len(s) > 1 else 0.0
        for name, s in zip(names, per_camera, strict=True)
    }
    max_lag = min(round(config.max_share * n), round(config.max_offset_s * rate))
    pairs: list[PairLag] = []
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            lag, peak, second = best_lag(per_camera[i], per_camera[j], max_lag)
            confident = bool(
                np.isfinite(peak) and peak >= config.min_peak and peak - second >= config.min_margin
            )
            pairs.append(
                PairLag(
                    a=names[i], b=names[j], lag=lag, peak=peak, second=second, confident=confident
                )
            )
    lags, unlinked, used = _solve(names, pairs)
    signals = dict(zip(names, per_camera, strict=True))
    lags, unlinked, joined = _join_unlinked(signals, lags, unlinked, max_lag, config)
    pairs = [
        PairLag(a=p.a, b=p.b, lag=p.lag, peak=p.peak, second=p.second, confident=p.confident,
                used=k in used)
        for k, p in enumerate(pairs)
    ]  # fmt: skip
    low = min(lags.values())
    lags = {name: v - low for name, v in lags.items()}
    # Back to each camera's own frames (videos paired by timestamps run at their own rates).
    own = source.camera_fps
    offsets = {name: round(v * (own.get(name) or rate) / rate) for name, v in lags.items()}
    return SyncResult(
        offsets=offsets,
        lags=lags,
        unlinked=unlinked,
        pairs=pairs,
        joined=joined,
        frames_read=n,
        fps=fps,
        seconds=time.perf_counter() - t0,
        activity=activity,
    )
