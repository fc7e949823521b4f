"""Sparse foreground/background split by voting over the masks."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.geometry import Rig
from edgerecon.scene.split import SplitConfig, split_sparse
from edgerecon.types import BACKGROUND_LABEL, UNKNOWN_LABEL, DataError
from tests.scene._scenes import box_silhouette, box_surface_points, ring_with_top

BOX_A = (np.array([-0.8, -0.2, 0.5]), np.array([-0.3, 0.2, 1.5]))
BOX_B = (np.array([0.4, -0.2, 0.5]), np.array([0.8, 0.2, 1.3]))


@pytest.fixture(scope="module")
def rig() -> Rig:
    return ring_with_top(6)


def _segment_hits_box(
    origin: np.ndarray, points: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """(N,) whether the open segment origin -> point crosses the box (slab method)."""
    d = points - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / d
        t2 = (hi - origin) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tmax >= tmin) & (tmin < 1.0 - 1e-9) & (tmax > 0.0)


def _scene(rig: Rig) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """Points on two boxes (objects) and on the floor/walls (background), their true labels,
    a visibility matrix (each point seen by the cameras facing it) and label masks."""
    rng = np.random.default_rng(0)
    fg_a = box_surface_points(*BOX_A, 8)
    fg_b = box_surface_points(*BOX_B, 8)
    floor = np.column_stack([rng.uniform(-2.5, 2.5, (400, 2)), np.zeros(400)])
    floor = floor[np.linalg.norm(floor[:, :2], axis=1) > 1.2]
    pts = np.vstack([fg_a, fg_b, floor])
    truth = np.concatenate([np.full(len(fg_a), 1), np.full(len(fg_b), 2), np.zeros(len(floor))])
    centre = {1: BOX_A[0] / 2 + BOX_A[1] / 2, 2: BOX_B[0] / 2 + BOX_B[1] / 2}
    vis = np.zeros((len(pts), len(rig)), bool)
    for c, cam in enumerate(rig):
        to_cam = cam.center - pts
        normal = np.zeros_like(pts)
        normal[truth == 0] = [0, 0, 1]
        for k in (1, 2):
            d = pts[truth == k] - centre[k]
            normal[truth == k] = d / np.linalg.norm(d, axis=1, keepdims=True)
        facing = np.einsum("ij,ij->i", normal, to_cam) > 0
        by_a = _segment_hits_box(cam.center, pts, *BOX_A) & (truth != 1)
        by_b = _segment_hits_box(cam.center, pts, *BOX_B) & (truth != 2)
        vis[:, c] = facing & ~by_a & ~by_b
    # Per-image labels: ids differ between cameras (object 2 is id 1 in odd cameras).
    masks = []
    for c, cam in enumerate(rig):
        a = box_silhouette(cam, *BOX_A)
        b = box_silhouette(cam, *BOX_B)
        lab = np.zeros((cam.height, cam.width), np.int32)
        ia, ib = (1, 2) if c % 2 == 0 else (2, 1)
        # Paint the farther box first: the nearer one hides it.
        far_a = np.linalg.norm(cam.center - centre[1]) > np.linalg.norm(cam.center - centre[2])
        for m, i in [(a, ia), (b, ib)] if far_a else [(b, ib), (a, ia)]:
            lab[m] = i
        masks.append(lab)
    return pts, truth.astype(int), vis, masks


def test_split_labels_and_consistent_object_ids(rig: Rig) -> None:
    pts, truth, vis, masks = _scene(rig)
    res = split_sparse(pts, vis, rig.cameras, masks)
    fg = truth > 0
    assert (res.labels[~fg] == BACKGROUND_LABEL).mean() > 0.97
    assert (res.labels[fg] > 0).all()
    assert res.num_objects == 2
    # Global ids are consistent across cameras: every box gets one id.
    for k in (1, 2):
        ids = np.unique(res.labels[truth == k])
        assert len(ids) == 1
    assert res.labels[truth == 1][0] != res.labels[truth == 2][0]
    # Nodes map each camera's local id of box A to the same global id.
    ga = res.labels[truth == 1][0]
    assert res.object_nodes[(0, 1)] == ga and res.object_nodes[(1, 2)] == ga
    assert res.counts()["foreground"] == int(fg.sum())


@pytest.mark.parametrize("corruption", ["empty", "full", "shifted"])
def test_one_bad_mask_is_outvoted(rig: Rig, corruption: str) -> None:
    pts, truth, vis, masks = _scene(rig)
    bad = [m.copy() for m in masks]
    if corruption == "empty":
        bad[0][:] = 0
    elif corruption == "full":
        bad[0][:] = 1
    else:
        bad[0] = np.roll(bad[0], 60, axis=1)
    res = split_sparse(pts, vis, rig.cameras, bad)
    fg = truth > 0
    acc = np.mean((res.labels > 0) == fg)
    assert acc > 0.97, acc


def test_without_tie_breaking_votes_a_two_view_point_with_one_bad_mask_stays_foreground(
    rig: Rig,
) -> None:
    pts, truth, _, masks = _scene(rig)
    p = pts[truth == 1][:1]
    v = np.zeros((1, len(rig)), bool)
    v[0, [0, 1]] = True
    bad = [m.copy() for m in masks]
    bad[0][:] = 0
    res = split_sparse(p, v, rig.cameras, bad, SplitConfig(unobserving_weight=0.0))
    assert res.labels[0] > 0  # tie -> foreground
    # With the other cameras' (weaker) votes the tie is broken by evidence.
    res = split_sparse(p, v, rig.cameras, bad)
    assert res.labels[0] > 0 and res.fg_votes[0] > res.bg_votes[0]


def test_boolean_masks_lists_and_missing_masks(rig: Rig) -> None:
    pts, truth, vis, masks = _scene(rig)
    bool_masks: list[np.ndarray | None] = [m > 0 for m in masks]
    bool_masks[2] = None
    lists = [list(np.flatnonzero(row)) for row in vis]
    res = split_sparse(pts, lists, rig.cameras, bool_masks)
    assert np.mean((res.labels > 0) == (truth > 0)) > 0.97
    # Boolean masks carry no per-image ids, but the two boxes never share a point: ids follow
    # the connected groups of (camera, id 1) nodes, which all link: one object.
    assert set(np.unique(res.labels[truth > 0])) == {1}


def test_points_no_camera_sees_are_unknown(rig: Rig) -> None:
    pts = np.array([[0.0, 0.0, 100.0], [-0.5, 0.0, 1.0]])  # far above every camera
    vis = np.ones((2, len(rig)), bool)
    masks = [box_silhouette(c, *BOX_A) for c in rig]
    res = split_sparse(pts, vis, rig.cameras, masks)
    assert res.labels[0] == UNKNOWN_LABEL
    assert res.labels[1] == 1


def test_empty_input(rig: Rig) -> None:
    masks = [np.zeros((c.height, c.width), bool) for c in rig]
    res = split_sparse(np.zeros((0, 3)), np.zeros((0, len(rig)), bool), rig.cameras, masks)
    assert res.labels.shape == (0,) and res.num_objects == 0


def test_bad_input_names_the_problem(rig: Rig) -> None:
    pts = np.zeros((2, 3))
    with pytest.raises(DataError, match=r"\(2, 6\)"):
        split_sparse(pts, np.zeros((2, 3), bool), rig.cameras, [None] * 6)
    with pytest.raises(DataError, match="cam1"):
        split_sparse(
            pts, np.zeros((2, 6), bool), rig.cameras, [None, np.zeros((5, 5), bool)] + [None] * 4
        )
    with pytest.raises(DataError, match="5 masks"):
        split_sparse(pts, np.zeros((2, 6), bool), rig.cameras, [None] * 5)


def test_the_compiled_vote_is_the_numpy_mode_bit_for_bit() -> None:
    # ``_associate_objects``' per-point vote (the component most of a point's nodes belong
    # to, ties to the first node's) against the NumPy version it replaced.
    from edgerecon.scene._kernels import mode_component, shared_points

    rng = np.random.default_rng(2)
    num_cams, stride = 6, 4
    node = rng.integers(0, stride, (5000, num_cams))
    node = np.where(node > 0, np.arange(num_cams)[None, :] * stride + node, -1).astype(np.int64)
    node[:50] = -1  # points without a node
    comp = rng.integers(0, 5, num_cams * stride).astype(np.int32)
    valid = node >= 0
    pt_comp = np.where(valid, comp[np.maximum(node, 0)], -1)
    support = np.full(node.shape, -1, np.int32)
    for j in range(num_cams):
        same = (pt_comp == pt_comp[:, j : j + 1]) & valid
        support[:, j] = np.where(valid[:, j], np.count_nonzero(same, axis=1), -1)
    ref = pt_comp[np.arange(len(node)), np.argmax(support, axis=1)]
    got = mode_component(node, comp)
    np.testing.assert_array_equal(got, ref)
    assert (got == -1).sum() >= 50 and len(np.unique(got)) == 6
    # Shared points: the pairs of a lower and a higher camera's nodes on one point.
    shared = shared_points(node, num_cams * stride)
    expected = np.zeros_like(shared)
    for a in range(num_cams):
        for b in range(a + 1, num_cams):
            both = valid[:, a] & valid[:, b]
            np.add.at(expected, (node[both, a], node[both, b]), 1)
    np.testing.assert_array_equal(shared, expected)


@pytest.mark.parametrize("reduced", [False, True])
def test_the_compiled_camera_votes_are_the_numpy_votes_bit_for_bit(rig: Rig, reduced: bool) -> None:
    # One camera's votes (``_kernels.camera_votes``) against the NumPy version they
    # replaced: points all around the rig, some observing cameras, a label image at the
    # camera's resolution or at a third of it, an unobserving weight of 0.5.
    import cv2

    from edgerecon.scene._kernels import camera_votes

    rng = np.random.default_rng(4)
    pts = rng.normal(0, 2.0, (20000, 3)) + [0, 0, 1]
    vis = rng.random((len(pts), len(rig))) < 0.5
    for c, cam in enumerate(rig):
        lab = (box_silhouette(cam, *BOX_A) * 1 + box_silhouette(cam, *BOX_B) * 2).astype(np.uint8)
        if reduced:
            lab = cv2.resize(
                lab, (cam.width // 3, cam.height // 3), interpolation=cv2.INTER_NEAREST
            )
        got = [np.zeros(len(pts), np.float32) for _ in range(2)]
        got += [np.zeros((len(pts), len(rig)), np.int32) for _ in range(2)]
        uv, depth = cam.project(pts)
        camera_votes(
            c, uv, depth, cam.width, cam.height, lab.shape[1] / cam.width,
            lab.shape[0] / cam.height, reduced, lab, vis, np.float32(0.5), *got,
        )  # fmt: skip
        ref = [np.zeros(len(pts), np.float32) for _ in range(2)]
        ref += [np.zeros((len(pts), len(rig)), np.int32) for _ in range(2)]
        fg_w, bg_w, local, local_any = ref
        inside = (depth > 0) & cam.in_image(uv)
        if reduced:
            uv = (uv + 0.5) * np.array([lab.shape[1] / cam.width, lab.shape[0] / cam.height]) - 0.5
        weight = np.where(vis[:, c], 1.0, 0.5).astype(np.float32)
        idx = np.flatnonzero(inside & (weight > 0))
        u = np.clip(np.rint(uv[idx, 0]).astype(np.intp), 0, lab.shape[1] - 1)
        v = np.clip(np.rint(uv[idx, 1]).astype(np.intp), 0, lab.shape[0] - 1)
        hit = lab[v, u]
        fg = hit > 0
        fg_w[idx[fg]] += weight[idx[fg]]
        bg_w[idx[~fg]] += weight[idx[~fg]]
        obs = vis[idx, c] & fg
        local[idx[obs], c] = hit[obs]
        local_any[idx[fg], c] = hit[fg]
        for a, b in zip(got, ref, strict=True):
            np.testing.assert_array_equal(a, b)
        assert fg.any() and (~fg).any() and (local > 0).any() and (local_any > local).any()
