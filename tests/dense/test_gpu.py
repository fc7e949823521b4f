"""The GPU path of the dense stage: its kernels against the CPU kernels (in numba's CUDA
simulator here, on the device where there is one) and the hand-over to the CPU when the
GPU fails."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from edgerecon.dense import gpu
from edgerecon.dense.config import DenseConfig
from edgerecon.views import View

ROOT = Path(__file__).resolve().parents[2]


def _check(*args: str, simulate: bool) -> dict:
    env = dict(os.environ)
    env["NUMBA_ENABLE_CUDASIM"] = "1" if simulate else "0"
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "src"), env.get("PYTHONPATH", "")])
    out = subprocess.run(
        [sys.executable, "-m", "tests.dense.gpu_check", "--json", *args],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600, check=True,
    )  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def _assert_same(res: dict, tol: float) -> None:
    assert res["evaluate_scored"] > 0
    assert res["evaluate_unscored_same"]
    assert res["evaluate_max_diff"] < tol
    assert res["sweep_best_max_diff"] < tol
    # Winners differ only where two planes tie within rounding.
    assert res["sweep_idx_differs"] < 0.01
    assert res["sweep_neighbours_max_diff"] < tol


def test_cuda_kernels_match_the_cpu_kernels_in_the_simulator():
    """Masked pixels, masked sources, samples outside the sources, planes outside the
    bounds: the same scores as the CPU kernels (numba's CUDA simulator runs the kernels)."""
    res = _check("--size", "40", "30", "--sources", "4", simulate=True)
    assert res["device"] == "numba's CUDA simulator"
    _assert_same(res, 1e-4)


@pytest.mark.skipif(
    not gpu.cuda_status()[0] or gpu.simulated(), reason="no CUDA GPU on this machine"
)
def test_cuda_kernels_match_the_cpu_kernels_on_the_gpu():
    """On an H200 (2026-12-04): max differences 2.0e-3 over 445 k scored pixels, winners
    differing at 0.4 % of the pixels. The CPU kernels' float32 products are the looser side:
    against float64 sums they are off by up to 4.9e-4 on 338 sampled pixels of this level
    (median 4e-5); the GPU threads sum in float64."""
    res = _check("--size", "960", "540", "--sources", "4", "--planes", "32", simulate=False)
    _assert_same(res, 5e-3)


def test_device_setting_is_validated_and_cpu_never_probes():
    with pytest.raises(ValueError, match="device"):
        DenseConfig(device="gpu")
    assert gpu.use_gpu("cpu") is False


def test_cuda_requested_without_a_gpu_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(gpu, "cuda_status", lambda: (False, "no CUDA GPU (test)"))
    with pytest.raises(RuntimeError, match="no CUDA GPU"):
        gpu.use_gpu("cuda")
    assert gpu.use_gpu("auto") is False


@pytest.fixture(scope="module")
def box_views():
    """Three views of the rendered box scene and their dense cloud by the CPU kernels on one
    thread (then they score whole levels, as the GPU does: row bands sum in another order,
    the same scores to rounding, not to the bit)."""
    from edgerecon.dense import reconstruct_dense
    from tests.dense.scene import box_scene, render
    from tests.dense.test_reconstruct import IDS, RIG

    rects = box_scene()
    views = [View(camera_id=i, camera=RIG[i], image=render(RIG[i], rects)[0]) for i in IDS[:3]]
    config = DenseConfig(num_threads=1, device="cpu")
    cpu = reconstruct_dense(views, config, up=(0, 0, 1))
    assert len(cpu.cloud) > 1000
    return views, config, cpu


@pytest.fixture
def found_gpu(monkeypatch):
    """A process that found a GPU ("test GPU") and has seen no failure yet."""
    monkeypatch.setattr(gpu, "_status", (True, "test GPU"))
    monkeypatch.setattr(gpu, "_failed", None)


def _dense(views, config, device):
    from edgerecon.dense import reconstruct_dense

    return reconstruct_dense(views, dataclasses.replace(config, device=device), up=(0, 0, 1))


def test_a_failing_gpu_hands_over_to_the_cpu_with_the_same_cloud(
    box_views, found_gpu, monkeypatch, caplog
):
    """A GPU whose kernels fail (here: every call raises) is reported once, and the dense
    cloud is the CPU kernels' own."""
    views, config, cpu = box_views

    class Broken:
        def __init__(self, *args: object, **kwargs: object) -> None:
            pass

        def sweep(self, *args: object) -> None:
            raise RuntimeError("CUDA_ERROR_LAUNCH_FAILED (test)")

        def evaluate(self, *args: object) -> None:
            raise RuntimeError("CUDA_ERROR_LAUNCH_FAILED (test)")

    monkeypatch.setattr(gpu, "CudaScorer", Broken)
    with caplog.at_level(logging.WARNING, logger="edgerecon.dense.gpu"):
        out = _dense(views, config, "auto")
        again = _dense(views, config, "auto")
    ok, why = gpu.cuda_status()
    assert not ok and "CUDA_ERROR_LAUNCH_FAILED" in why
    assert sum("the GPU failed" in r.message for r in caplog.records) == 1
    for res in (out, again):
        assert np.array_equal(res.cloud.points3D, cpu.cloud.points3D)


class _KernelScorer:
    """``gpu.CudaScorer``'s contract (its constructor, ``sweep`` and ``evaluate``) kept by the
    CPU kernels: the GPU kernels are checked against these in ``gpu_check``; here the depth
    maps are checked to use the contract as the CPU path uses the kernels."""

    def __init__(self, ref, mean, var, count, srcs, sizes, src_ok, active, radius, a, b):
        self.args = (ref, mean, var, count, srcs, sizes, src_ok, active)
        self.radius, self.a, self.b = radius, a, b

    def sweep(self, Hs, lams, nray, usable, w_lo, w_hi, top_k, top_gap, best, idx, prev, nxt):
        from edgerecon.dense import kernels

        _KernelScorer.used += 1
        h = self.args[0].shape[0]
        kernels.sweep(
            *self.args, Hs, lams, nray, usable, w_lo, w_hi, self.radius, top_k, top_gap,
            best, idx, prev, nxt, 0, h,
        )  # fmt: skip

    def evaluate(self, inv, w_lo, w_hi, top_k, top_gap):
        from edgerecon.dense import kernels

        _KernelScorer.used += 1
        out = np.empty(inv.shape, np.float32)
        kernels.evaluate(
            *self.args, self.a, self.b, inv, w_lo, w_hi, self.radius, top_k, top_gap, out, 0,
            inv.shape[0],
        )  # fmt: skip
        return out

    used = 0


def test_the_depth_maps_score_through_the_gpu_scorer_as_through_the_cpu_kernels(
    box_views, found_gpu, monkeypatch
):
    """With a GPU (here: a scorer that keeps ``CudaScorer``'s contract with the CPU kernels)
    every sweep and score of the depth maps goes through the scorer, and the cloud is the CPU
    path's to the point."""
    views, config, cpu = box_views
    monkeypatch.setattr(gpu, "CudaScorer", _KernelScorer)
    monkeypatch.setattr(_KernelScorer, "used", 0)
    out = _dense(views, config, "cuda")
    assert _KernelScorer.used > 50
    assert out.stats["scoring"] == "cuda (test GPU)"
    assert np.array_equal(out.cloud.points3D, cpu.cloud.points3D)
    for k, depth in cpu.depth_maps.items():
        assert np.array_equal(out.depth_maps[k], depth)


def test_more_sources_than_a_gpu_thread_keeps_score_on_the_cpu(box_views, found_gpu, monkeypatch):
    """A level with more sources than ``gpu.MAX_SOURCES`` is scored by the CPU kernels and
    the GPU stays in use for the others (it is not reported as failed)."""
    views, config, cpu = box_views
    monkeypatch.setattr(gpu, "CudaScorer", _KernelScorer)
    monkeypatch.setattr(gpu, "MAX_SOURCES", 1)  # every view here has two sources
    monkeypatch.setattr(_KernelScorer, "used", 0)
    out = _dense(views, config, "cuda")
    assert _KernelScorer.used == 0
    assert gpu.cuda_status() == (True, "test GPU")
    assert np.array_equal(out.cloud.points3D, cpu.cloud.points3D)
