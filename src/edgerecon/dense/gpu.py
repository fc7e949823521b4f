"""The plane sweep and the hypothesis scoring on a CUDA GPU (numba.cuda).

The same arithmetic as :func:`edgerecon.dense.kernels.sweep` and
:func:`~edgerecon.dense.kernels.evaluate`, written for one GPU thread per output pixel:
each thread sums its own ``(2 r + 1)^2`` window of resampled source pixels directly (the CPU
kernels share the resampling between neighbouring windows with running sums, which a
thread-per-pixel layout does not need: the GPU has the arithmetic and the samples come from
its caches). Scores agree with the CPU kernels to float rounding (the sums run in another
order); the sweep's winner can differ where two planes score within that rounding.

:class:`CudaScorer` holds one pyramid level's reference statistics and sources on the
device, so that the many scoring calls of the refinement move only the hypothesis map.

Where the GPU path runs is :attr:`DenseConfig.device`: ``"auto"`` (the default) takes a CUDA
GPU when numba finds one and the CPU kernels otherwise; a GPU that fails (a kernel that does
not compile, a launch that fails) is reported once and the CPU kernels take over for the
rest of the process, with the same results. Setting ``NUMBA_ENABLE_CUDASIM=1`` runs these
kernels in numba's CUDA simulator (the tests do, on tiny images): correct but very slow.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

logger = logging.getLogger(__name__)

F32 = NDArray[np.float32]

#: Most source views one reference can score against (``_cuda_kernels.MAX_SOURCES``).
MAX_SOURCES = 16
#: Threads per block (x, y): a warp along a row reads consecutive pixels.
_BLOCK = (32, 4)

_lock = threading.Lock()
_status: tuple[bool, str] | None = None
_failed: str | None = None
_kernels: dict[str, Any] | None = None


def simulated() -> bool:
    """Whether numba's CUDA simulator stands in for a GPU (``NUMBA_ENABLE_CUDASIM=1``)."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM", "0") not in ("", "0")


def cuda_status() -> tuple[bool, str]:
    """(whether a CUDA GPU can run the dense kernels, the device's name or why not).
    Probed once per process."""
    global _status
    with _lock:
        if _status is None:
            _status = _probe()
        if _failed is not None:
            return False, _failed
        return _status


def _numpy_compat() -> None:
    """Some numba-cuda releases register an overload of ``np.row_stack``, which NumPy 2.5
    removed: their compiler fails to load there unless the name exists (``np.vstack``; seen
    on the H200 machine with NumPy 2.5.2). Only where the kernels compile (a GPU is there):
    finding the device works without it."""
    if "row_stack" not in np.__dict__:
        np.row_stack = np.vstack  # noqa: NPY201


def _probe() -> tuple[bool, str]:
    try:
        from numba import cuda
    except Exception as exc:  # numba built without its CUDA target, a broken install
        return False, f"numba.cuda cannot be imported ({exc})"
    try:
        if not cuda.is_available():
            return False, "no CUDA GPU (numba.cuda finds no driver or device)"
        if simulated():
            return True, "numba's CUDA simulator"
        name = cuda.get_current_device().name
        return True, name.decode() if isinstance(name, bytes) else str(name)
    except Exception as exc:
        return False, f"CUDA GPU not usable ({exc})"


def use_gpu(device: str) -> bool:
    """Whether the dense stage should run its kernels on the GPU for ``DenseConfig.device``
    (``"cpu"``, ``"cuda"`` or ``"auto"``). ``"cuda"`` without a usable GPU is an error."""
    if device == "cpu":
        return False
    ok, why = cuda_status()
    if device == "cuda" and not ok:
        raise RuntimeError(f"dense.device = 'cuda' but {why}")
    return ok


def scoring_device(device: str) -> str:
    """Where ``DenseConfig.device`` has the NCC scoring run now, in words (for the stats):
    "cpu", "cuda (NAME)", or "cpu (...)" with the reason a GPU is not used."""
    if device == "cpu":
        return "cpu"
    ok, why = cuda_status()
    return f"cuda ({why})" if ok else f"cpu ({why})"


def report_failure(exc: BaseException) -> None:
    """A GPU kernel failed: say so once; :func:`cuda_status` is False from now on."""
    global _failed
    with _lock:
        first = _failed is None
        if first:
            _failed = f"the GPU failed ({type(exc).__name__}: {exc}); the CPU kernels run"
    if first:
        logger.warning("dense stage: %s", _failed)


def _compile() -> dict[str, Any]:
    """The CUDA kernels, compiled on first use (numba.cuda is imported only then)."""
    global _kernels
    with _lock:
        if _kernels is None:
            _numpy_compat()
            from numba import cuda

            from edgerecon.dense import _cuda_kernels as k

            _kernels = {
                "sweep": k.sweep,
                "evaluate": k.evaluate,
                # Arguments of the mode a kernel does not use.
                "a": cuda.to_device(np.zeros((1, 3, 1, 1), np.float32)),
                "b": cuda.to_device(np.zeros((1, 3), np.float32)),
                "inv": cuda.to_device(np.zeros((1, 1), np.float32)),
                "H": cuda.to_device(np.zeros((1, 1, 3, 3), np.float64)),
            }
        return _kernels


def _spans(active: NDArray[np.bool_]) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """Per row, the first and one past the last active column (lo >= hi: none)."""
    w = active.shape[1]
    any_row = active.any(axis=1)
    lo = np.where(any_row, np.argmax(active, axis=1), w).astype(np.int32)
    hi = np.where(any_row, w - np.argmax(active[:, ::-1], axis=1), 0).astype(np.int32)
    return lo, hi


@dataclass(eq=False)
class CudaScorer:
    """One pyramid level of one reference view on the GPU: its statistics, source images,
    per-pixel projection terms and masks are copied once; :meth:`sweep` and
    :meth:`evaluate` then move only what changes. Each scorer has its own CUDA stream, so
    the dense stage's threads (one view each) overlap their copies and kernels."""

    ref: F32
    mean: F32
    var: F32
    count: F32
    srcs: F32
    sizes: NDArray[np.int64]
    src_ok: NDArray[np.bool_]
    active: NDArray[np.bool_]
    radius: int
    a: F32 | None = None
    b: NDArray[np.float32] | None = None

    def __post_init__(self) -> None:
        from numba import cuda

        if self.srcs.shape[0] > MAX_SOURCES:
            raise ValueError(f"at most {MAX_SOURCES} source views on the GPU")
        self._k = _compile()
        self._stream = cuda.stream()
        st = self._stream
        lo, hi = _spans(self.active)
        put = lambda x: cuda.to_device(np.ascontiguousarray(x), stream=st)  # noqa: E731
        self._d = {
            "ref": put(self.ref),
            "mean": put(self.mean),
            "var": put(self.var),
            "count": put(self.count),
            "srcs": put(self.srcs),
            "sizes": put(self.sizes),
            "src_ok": put(self.src_ok),
            "active": put(self.active),
            "lo": put(lo),
            "hi": put(hi),
        }
        self._cache: dict[int, tuple[Any, Any]] = {}
        self._put = put
        h, w = self.ref.shape
        self._grid = ((w + _BLOCK[0] - 1) // _BLOCK[0], (h + _BLOCK[1] - 1) // _BLOCK[1])

    def _dev(self, arr: NDArray[Any]) -> Any:
        """Device copy of an array that stays the same over many calls (bounds, masks),
        cached by identity (the cache holds the array, so the id stays its own)."""
        hit = self._cache.get(id(arr))
        if hit is None or hit[0] is not arr:
            hit = (arr, self._put(arr))
            self._cache[id(arr)] = hit
        return hit[1]

    def sweep(
        self,
        homographies: NDArray[np.float64],
        lams: NDArray[np.float64],
        nray: F32,
        usable: NDArray[np.bool_],
        w_lo: F32,
        w_hi: F32,
        top_k: int,
        top_gap: float,
        best: F32,
        best_idx: NDArray[np.int32],
        prev: F32,
        nxt: F32,
    ) -> None:
        """``kernels.sweep`` over all rows; updates best / best_idx / prev / nxt in place, all
        of them or (on an error) none."""
        d = self._d
        st = self._stream
        outs = [self._put(x) for x in (best, best_idx, prev, nxt)]
        self._k["sweep"][self._grid, _BLOCK, st](
            d["ref"], d["mean"], d["var"], d["count"], d["srcs"], d["sizes"], d["src_ok"],
            d["active"], d["lo"], d["hi"], self._put(np.ascontiguousarray(homographies)),
            self._put(np.ascontiguousarray(lams, np.float64)), self._put(nray),
            self._put(usable), self._dev(w_lo), self._dev(w_hi), self.radius, top_k,
            float(top_gap), self._k["a"], self._k["b"], self._k["inv"], *outs,
        )  # fmt: skip
        done = [dev.copy_to_host(stream=st) for dev in outs]
        st.synchronize()
        # Only now, with the whole family scored: a failure above leaves the inputs as they were.
        for host, new in zip((best, best_idx, prev, nxt), done, strict=True):
            host[...] = new

    def evaluate(self, inv: F32, w_lo: F32, w_hi: F32, top_k: int, top_gap: float) -> F32:
        """``kernels.evaluate`` over all rows: the aggregated NCC of ``inv``."""
        if self.a is None or self.b is None:
            raise ValueError("this scorer has no per-pixel projection terms")
        d = self._d
        st = self._stream
        if "a" not in d:
            d["a"] = self._put(np.ascontiguousarray(self.a, np.float32))
            d["b"] = self._put(np.ascontiguousarray(self.b, np.float32))
        out = np.empty(inv.shape, np.float32)
        d_out = self._put(out)
        self._k["evaluate"][self._grid, _BLOCK, st](
            d["ref"], d["mean"], d["var"], d["count"], d["srcs"], d["sizes"], d["src_ok"],
            d["active"], d["lo"], d["hi"], self._k["H"], d["a"], d["b"],
            self._put(np.ascontiguousarray(inv, np.float32)), self._dev(w_lo), self._dev(w_hi),
            self.radius, top_k, float(top_gap), d_out,
        )  # fmt: skip
        d_out.copy_to_host(out, stream=st)
        st.synchronize()
        return out
