"""Compiled (numba) inner loop of the photo check (:mod:`edgerecon.scene.ghosts`).

Per judged point the check compares its colour in one camera with its colour in every other
camera that holds it: the per-pair colour ratio, the largest channel difference, the
chromaticity and brightness test and the local-contrast test, then the smallest difference,
whether another camera vouches for the point and whether one sees its tint at another
brightness. In NumPy that is ~40 passes over (3, N) temporaries per camera pair; fused here
into one pass per point. The arithmetic is NumPy's: float32 throughout, constants as float32,
no reordering (no fastmath), so the results are the NumPy code's bit for bit.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

_INF = np.float32(np.inf)


@nb.njit(nogil=True, cache=True)
def judge_points(
    c: int,
    idx: NDArray[np.intp],
    colours: NDArray[np.float32],
    contrasts: NDArray[np.float32],
    has_contrast: bool,
    inside: NDArray[np.bool_],
    alone: NDArray[np.bool_],
    valid: NDArray[np.bool_],
    ratios: NDArray[np.float32],
    has_ratio: NDArray[np.bool_],
    max_chroma: np.float32,
    max_ratio: np.float32,
    texture_tol: np.float32,
    dist: NDArray[np.float32],
    vouch: NDArray[np.bool_],
    tinted: NDArray[np.bool_],
) -> None:
    """Camera ``c``'s judgement of the points ``idx`` against every other ``valid`` camera.

    ``colours`` (n, 3, N) BGR per camera and point, ``contrasts`` (n, N) local contrasts
    (used when ``has_contrast``), ``inside`` / ``alone`` (n, N) as ``ghosts._View``,
    ``ratios`` (n, n, 3) the colour ratio of camera o's colours to c's (applied when
    ``has_ratio[c, o]``). Writes per judged point: ``dist`` the smallest largest-channel
    difference over the cameras that hold it (inf: none, or no contrast alike), ``vouch``
    whether some other camera holds it alone, ``tinted`` whether one holds it in the same
    tint."""
    n = colours.shape[0]
    one = np.float32(1.0)
    two_thirds = np.float32(2.0 / 3.0)
    for k in range(idx.shape[0]):
        p = idx[k]
        a0 = colours[c, 0, p]
        a1 = colours[c, 1, p]
        a2 = colours[c, 2, p]
        sa = a0 + a1 + a2 + one
        ia = one / sa
        best = _INF
        v = False
        t = False
        for o in range(n):
            if o == c or not valid[o]:
                continue
            if alone[o, p]:
                v = True
            if not inside[o, p]:
                continue
            b0 = colours[o, 0, p]
            b1 = colours[o, 1, p]
            b2 = colours[o, 2, p]
            if has_ratio[c, o]:
                b0 = b0 * ratios[c, o, 0]
                b1 = b1 * ratios[c, o, 1]
                b2 = b2 * ratios[c, o, 2]
            sb = b0 + b1 + b2 + one
            ib = one / sb
            chroma = abs(a0 * ia - b0 * ib) + abs(a1 * ia - b1 * ib) + abs(a2 * ia - b2 * ib)
            ratio = sa * ib
            alike = (chroma < max_chroma) and (ratio < max_ratio) and (ratio * max_ratio > one)
            d = max(max(abs(a0 - b0), abs(a1 - b1)), abs(a2 - b2))
            if has_contrast:
                ca = contrasts[c, p]
                cb = contrasts[o, p]
                if not (abs(ca - cb) <= max(texture_tol, two_thirds * max(ca, cb))):
                    d = _INF
                    alike = False
            if alike:
                t = True
            if d < best:
                best = d
        dist[k] = best
        vouch[k] = v
        tinted[k] = t


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels on tiny inputs, so that the first
    task's scene stage does not pay for it (~1 s on these machines)."""
    n, num = 2, 4
    judge_points(
        0,
        np.arange(num, dtype=np.intp),
        np.ones((n, 3, num), np.float32),
        np.ones((n, num), np.float32),
        True,
        np.ones((n, num), bool),
        np.ones((n, num), bool),
        np.ones(n, bool),
        np.ones((n, n, 3), np.float32),
        np.zeros((n, n), bool),
        np.float32(0.03),
        np.float32(1.6),
        np.float32(10.0),
        np.zeros(num, np.float32),
        np.zeros(num, bool),
        np.zeros(num, bool),
    )
