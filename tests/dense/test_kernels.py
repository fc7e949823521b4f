"""Known-answer tests of the compiled kernels and the NumPy reference they replace."""

from __future__ import annotations

import cv2
import numpy as np

from edgerecon.dense import kernels
from edgerecon.dense.cost import aggregate, ncc, window_stats
from edgerecon.dense.fusion import ViewPoints, voxel_merge
from edgerecon.geometry import Camera, look_at

R0 = 3


def _images(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ref = (rng.random((40, 50)) * 200 - 100).astype(np.float32)
    src = (0.5 * ref + 20 + rng.normal(0, 10, ref.shape)).astype(np.float32)
    return ref, src


def test_window_stats_match_box_filters_inside():
    ref, _ = _images()
    mean, var, count = kernels.window_stats(ref, R0)
    st = window_stats(ref, R0)
    inner = np.s_[R0:-R0, R0:-R0]
    assert np.allclose(mean[inner], st.mean[inner], atol=1e-3)
    assert np.allclose(var[inner] - kernels.VAR_EPS, st.std[inner] ** 2, rtol=1e-3, atol=1e-2)
    assert count[0, 0] == (R0 + 1) ** 2 and count[20, 20] == (2 * R0 + 1) ** 2


def test_identity_homography_ncc_equals_numpy_reference():
    ref, src = _images()
    h, w = ref.shape
    mean, var, count = kernels.window_stats(ref, R0)
    srcs = src[None].copy()
    sizes = np.array([[w, h]], np.int64)
    ok = np.ones((1, h, w), bool)
    best = np.full((h, w), -np.inf, np.float32)
    idx = np.zeros((h, w), np.int32)
    prev = np.full((h, w), -1.0, np.float32)
    nxt = np.full((h, w), -1.0, np.float32)
    H = np.eye(3)[None, None].repeat(1, axis=0)  # one plane, one source
    kernels.sweep(
        ref, mean, var, count, srcs, sizes, ok, np.ones((h, w), bool), H, np.array([1.0]),
        np.ones((h, w), np.float32), np.ones((h, w), bool),
        np.zeros((h, w), np.float32), np.full((h, w), np.inf, np.float32), R0, 1, np.inf,
        best, idx, prev, nxt, 0, h,
    )  # fmt: skip
    expected = ncc(window_stats(ref, R0), src)
    # The last row/column samples exactly on the image border and is valid in both.
    inner = np.s_[R0:-R0, R0:-R0]
    assert np.allclose(best[inner], expected[inner], atol=2e-4)
    assert np.all(best[inner] > 0.5)  # the source is a noisy copy of the reference


def test_windows_touching_missing_samples_have_no_score():
    ref, src = _images()
    h, w = ref.shape
    mean, var, count = kernels.window_stats(ref, R0)
    a = np.zeros((1, 3, h, w), np.float32)
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    a[0, 0], a[0, 1], a[0, 2] = u + 10.0, v, 1.0  # shifted 10 px right: last columns fall out
    out = np.empty((h, w), np.float32)
    kernels.evaluate(
        ref, mean, var, count, src[None].copy(), np.array([[w, h]], np.int64),
        np.ones((1, h, w), bool), np.ones((h, w), bool), a, np.zeros((1, 3), np.float32),
        np.ones((h, w), np.float32), np.zeros((h, w), np.float32),
        np.full((h, w), np.inf, np.float32), R0, 1, np.inf, out, 0, h,
    )  # fmt: skip
    full = out.copy()
    # Samples beyond x = w - 1 are missing: windows reaching x >= w - 10 have no score (-1).
    assert np.all(out[:, w - 10 - R0 :] == -1.0)
    assert np.all(out[:, : w - 11 - R0] > -1.0)
    # A source marked unusable gives no score either.
    kernels.evaluate(
        ref, mean, var, count, src[None].copy(), np.array([[w, h]], np.int64),
        np.zeros((1, h, w), bool), np.ones((h, w), bool), a, np.zeros((1, 3), np.float32),
        np.ones((h, w), np.float32), np.zeros((h, w), np.float32),
        np.full((h, w), np.inf, np.float32), R0, 1, np.inf, out, 0, h,
    )  # fmt: skip
    assert np.all(out == -1.0)
    # Sampling only an active block: windows inside it score exactly as before, windows
    # reaching outside it have no score.
    active = np.zeros((h, w), bool)
    active[10:30, 5:25] = True
    kernels.evaluate(
        ref, mean, var, count, src[None].copy(), np.array([[w, h]], np.int64),
        np.ones((1, h, w), bool), active, a, np.zeros((1, 3), np.float32),
        np.ones((h, w), np.float32), np.zeros((h, w), np.float32),
        np.full((h, w), np.inf, np.float32), R0, 1, np.inf, out, 0, h,
    )  # fmt: skip
    inner = np.s_[10 + R0 : 30 - R0, 5 + R0 : 25 - R0]
    assert np.allclose(out[inner], full[inner], atol=1e-5)  # running sums: rounding only
    outside = np.ones((h, w), bool)
    outside[10 - R0 : 30 + R0, 5 - R0 : 25 + R0] = False
    assert np.all(out[outside] == -1.0)


def test_aggregate_takes_the_mean_of_the_best_sources():
    a = np.array([[0.9, np.nan]], np.float32)
    b = np.array([[0.5, 0.2]], np.float32)
    c = np.array([[0.7, np.nan]], np.float32)
    assert np.allclose(aggregate([a, b, c], 1), [[0.9, 0.2]])
    assert np.allclose(aggregate([a, b, c], 2), [[0.8, 0.2]])
    assert np.allclose(aggregate([a, b, c], 3), [[0.7, 0.2]])
    assert np.allclose(aggregate([np.full((1, 1), np.nan, np.float32)], 1), [[-1.0]])


def test_aggregate_bounds_what_a_worse_source_takes_off():
    a = np.array([[0.9, 0.9]], np.float32)
    b = np.array([[0.8, 0.1]], np.float32)  # sees the pixel / does not (an occlusion)
    assert np.allclose(aggregate([a, b], 2, top_gap=0.2), [[0.85, 0.8]])
    assert np.allclose(aggregate([a, b], 2, top_gap=0.0), [[0.9, 0.9]])
    assert np.allclose(aggregate([a, b], 2, top_gap=np.inf), aggregate([a, b], 2))


def test_scores_aggregate_sources_as_the_numpy_reference():
    ref, src = _images()
    h, w = ref.shape
    noise = np.random.default_rng(1).normal(0, 50, ref.shape).astype(np.float32)
    srcs = np.stack([src, noise])  # a noisy copy, and a source that sees something else
    mean, var, count = kernels.window_stats(ref, R0)
    a = np.zeros((2, 3, h, w), np.float32)
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    a[:, 0], a[:, 1], a[:, 2] = u, v, 1.0  # identity mapping into both sources

    def scores(pick: list[int], k: int, gap: float) -> np.ndarray:
        out = np.empty((h, w), np.float32)
        kernels.evaluate(
            ref, mean, var, count, srcs[pick].copy(), np.array([[w, h]] * len(pick), np.int64),
            np.ones((len(pick), h, w), bool), np.ones((h, w), bool), a[pick].copy(),
            np.zeros((len(pick), 3), np.float32), np.ones((h, w), np.float32),
            np.zeros((h, w), np.float32), np.full((h, w), np.inf, np.float32), R0, k, gap, out,
            0, h,
        )  # fmt: skip
        return out

    one = [scores([s], 1, np.inf) for s in (0, 1)]
    inner = np.s_[R0:-R0, R0:-R0]
    for k, gap in ((1, np.inf), (2, np.inf), (2, 0.2), (2, 0.0)):
        assert np.allclose(scores([0, 1], k, gap)[inner], aggregate(one, k, gap)[inner], atol=1e-5)
    soft = scores([0, 1], 2, 0.2)[inner]
    assert np.all(soft >= scores([0, 1], 2, np.inf)[inner] - 1e-6)
    assert np.all(soft >= one[0][inner] - 0.1 - 1e-5)  # the worse source takes off <= 0.1


def test_view_points_backproject_exactly_with_normals_facing_the_camera():
    R, t = look_at((0, -3, 0), (0, 0, 0), (0, 0, 1))
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    cam = Camera(name="c", width=64, height=48, K=K, R=R, t=t)
    depth = np.full((48, 64), 3.0, np.float32)  # the plane y = 0, facing the camera
    keep = np.ones_like(depth, bool)
    pts, nrm, idx = kernels.view_points(depth, keep, np.linalg.inv(K), R, t, 2, 0.05)
    assert len(pts) == 64 * 48 and np.array_equal(idx, np.arange(64 * 48))
    assert np.allclose(pts[:, 1], 0.0, atol=1e-9)
    uv, z = cam.project(pts)
    rows, cols = np.divmod(idx, 64)
    assert np.allclose(uv[:, 0], cols, atol=1e-6) and np.allclose(uv[:, 1], rows, atol=1e-6)
    assert np.allclose(z, 3.0)
    assert np.allclose(nrm, [0.0, -1.0, 0.0], atol=1e-5)  # towards the camera at y = -3


def _part(points, views, cid=0):
    n = len(points)
    return ViewPoints(
        camera_id=cid,
        points3D=np.asarray(points, float),
        colors=np.full((n, 3), 100, np.uint8),
        normals=np.tile(np.float32([0, 0, 1]), (n, 1)),
        num_views=np.asarray(views, np.int16),
        score=np.full(n, 0.8, np.float32),
    )


def test_voxel_merge_deduplicates_and_keeps_the_best_support():
    a = _part([[0.001, 0.001, 0.001], [1.0, 1.0, 1.0]], [2, 2], 0)
    b = _part([[0.003, 0.002, 0.004], [2.0, 2.0, 2.0]], [3, 2], 1)
    cloud = voxel_merge([a, b], 0.01)
    assert len(cloud) == 3
    first = np.argmin(np.linalg.norm(cloud.points3D, axis=1))
    assert np.allclose(cloud.points3D[first], [0.002, 0.0015, 0.0025])
    assert cloud.attributes["num_views"][first] == 3
    assert np.allclose(np.linalg.norm(cloud.normals, axis=1), 1.0)
    assert len(voxel_merge([], 0.01)) == 0


def test_row_bands_score_like_one_call():
    """The kernels are row-separable: bands (as RowBands runs them on idle threads) give the
    scores of one call over all rows, up to the rounding of the running sums."""
    ref, src = _images(3)
    h, w = ref.shape
    mean, var, count = kernels.window_stats(ref, R0)
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    a = np.zeros((1, 3, h, w), np.float32)
    a[0, 0], a[0, 1], a[0, 2] = u + 0.3 * v, v, 1.0
    active = np.ones((h, w), bool)
    active[5:12, 8:30] = False
    args = (
        ref, mean, var, count, src[None].copy(), np.array([[w, h]], np.int64),
        np.ones((1, h, w), bool), active, a, np.zeros((1, 3), np.float32),
        np.ones((h, w), np.float32), np.zeros((h, w), np.float32),
        np.full((h, w), np.inf, np.float32), R0, 1, np.inf,
    )  # fmt: skip
    whole = np.empty((h, w), np.float32)
    kernels.evaluate(*args, whole, 0, h)
    banded = np.full((h, w), np.nan, np.float32)
    for row0, row1 in [(0, 7), (7, 8), (8, 25), (25, h)]:
        kernels.evaluate(*args, banded, row0, row1)
    assert np.allclose(banded, whole, atol=1e-5)
    # The sweep likewise, bands writing only their rows of the winner maps.
    H = np.stack([np.eye(3), np.array([[1.0, 0, 1.5], [0, 1, 0], [0, 0, 1]])])[:, None]
    maps = []
    for bands in ([(0, h)], [(0, 13), (13, 14), (14, h)]):
        best = np.full((h, w), -np.inf, np.float32)
        out = (best, np.zeros((h, w), np.int32), np.full((h, w), -1.0, np.float32))
        nxt = np.full((h, w), -1.0, np.float32)
        for row0, row1 in bands:
            kernels.sweep(
                ref, mean, var, count, src[None].copy(), np.array([[w, h]], np.int64),
                np.ones((1, h, w), bool), active, H, np.array([1.0, 2.0]),
                np.ones((h, w), np.float32), np.ones((h, w), bool),
                np.zeros((h, w), np.float32), np.full((h, w), np.inf, np.float32), R0, 1,
                np.inf, *out, nxt, row0, row1,
            )  # fmt: skip
        maps.append((*out, nxt))
    for one, split in zip(*maps, strict=True):
        assert np.allclose(one, split, atol=1e-5)


def test_row_bands_lend_idle_threads():
    import threading

    from edgerecon.dense.threads import RowBands

    seen: list[tuple[int, int, str]] = []
    me = threading.current_thread().name

    def kernel(row0: int, row1: int) -> None:
        seen.append((row0, row1, threading.current_thread().name))

    bands = RowBands(2)
    bands.run(kernel, 100)  # nobody idle: the same bands, one after the other here
    assert seen == [(0, 50, me), (50, 100, me)]
    seen.clear()
    bands.lend()
    bands.run(kernel, 100)  # an idle thread: the second band on the helper
    assert sorted(s[:2] for s in seen) == [(0, 50), (50, 100)]
    assert {s[2] for s in seen if s[0] == 50} != {me}
    seen.clear()
    bands.run(kernel, 40)  # too few rows to split
    assert [s[:2] for s in seen] == [(0, 40)]
    bands = RowBands(1)
    bands.lend()
    seen.clear()
    bands.run(kernel, 100)
    assert seen == [(0, 100, me)]


def test_run_jobs_lends_the_threads_without_a_job_and_raises_after_all():
    import threading

    import pytest

    from edgerecon.dense.threads import RowBands, run_jobs

    seen: list[tuple[int, int, str]] = []

    def kernel(row0: int, row1: int) -> None:
        seen.append((row0, row1, threading.current_thread().name))

    bands = RowBands(2)

    def job(x: int) -> int:
        bands.run(kernel, 100)
        return 2 * x

    # One job for two threads: the idle one takes half of its rows.
    assert run_jobs(job, [3], 2, bands, "test") == [6]
    assert sorted(s[:2] for s in seen) == [(0, 50), (50, 100)]
    assert len({s[2] for s in seen}) == 2

    done: list[int] = []

    def failing(x: int) -> int:
        if x == 2:
            raise ValueError("job 2")
        done.append(x)
        return x

    bands = RowBands(2)
    with pytest.raises(ValueError, match="job 2"):
        run_jobs(failing, [1, 2, 3, 4], 2, bands, "test")
    assert sorted(done) == [1, 3, 4]  # the other jobs still ran


def test_local_search_base_is_the_median_away_from_depth_edges():
    from edgerecon.dense.depth import _median_base

    rng = np.random.default_rng(0)
    # Inverse depth of two surfaces (a step at column 20) with 0.5 % noise.
    clean = np.where(np.arange(40)[None, :] < 20, 0.5, 0.25).astype(np.float32).repeat(30, 0)
    noisy = (clean * (1 + 0.005 * rng.standard_normal(clean.shape))).astype(np.float32)
    base = _median_base(noisy, 5, 0.05)
    inner = np.s_[2:-2, 2:17]
    # The noise is cut where the neighbourhood is one surface ...
    assert np.std(base[inner] - clean[inner]) < 0.6 * np.std(noisy[inner] - clean[inner])
    # ... and no pixel moves by more than the tolerance: the edge keeps both depths.
    assert np.all(np.abs(base - noisy) <= 0.05 * noisy + 1e-7)
    assert np.all(np.abs(base[:, 18:22] - clean[:, 18:22]) < 0.02 * clean[:, 18:22])
    # Kernel 0: the map itself (no copy).
    assert _median_base(noisy, 0, 0.05) is noisy


def test_windows_inside_the_active_pixels_score_as_with_every_pixel_active():
    """A row whose active span starts beyond the window radius, next to rows active further
    left: the running sums of that row must start from its own windows (they subtracted a
    column they never added, which gave NCCs far outside [-1, 1] along the whole row)."""
    ref, src = _images()
    h, w = ref.shape
    mean, var, count = kernels.window_stats(ref, R0)
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    a = np.zeros((1, 3, h, w), np.float32)
    a[0, 0], a[0, 1], a[0, 2] = u + 0.3, v - 0.2, 1.0
    active = np.ones((h, w), bool)
    active[:12, :15] = False  # rows 0-11 start at x = 15, rows below at x = 0
    args = (ref, mean, var, count, src[None].copy(), np.array([[w, h]], np.int64))

    def scores(act: np.ndarray) -> np.ndarray:
        out = np.empty((h, w), np.float32)
        kernels.evaluate(
            *args, np.ones((1, h, w), bool), act, a, np.zeros((1, 3), np.float32),
            np.ones((h, w), np.float32), np.zeros((h, w), np.float32),
            np.full((h, w), np.inf, np.float32), R0, 1, np.inf, out, 0, h,
        )  # fmt: skip
        return out

    full, masked = scores(np.ones((h, w), bool)), scores(active)
    inside = cv2.erode(active.astype(np.uint8), np.ones((2 * R0 + 1,) * 2, np.uint8)) > 0
    inside &= full > -1
    assert inside[8:12, 20:40].all()  # the rows whose windows reach the rows active further left
    assert np.allclose(masked[inside], full[inside], atol=1e-4)
    assert np.abs(masked[masked > -1]).max() <= 1.0 + 1e-4
