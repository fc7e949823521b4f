import numpy as np
import pytest

from edgerecon.geometry import Camera
from edgerecon.quality.masks import labels_to_view, mask_iou, score_mask_set, score_masks


def test_mask_iou_known_answer():
    a = np.zeros((10, 10), bool)
    b = np.zeros((10, 10), bool)
    a[:, :5] = True  # 50 px
    b[:, 3:8] = True  # 50 px, 20 shared
    assert mask_iou(a, b) == pytest.approx(20 / 80)
    assert mask_iou(a, a) == 1.0
    assert mask_iou(np.zeros((3, 3)), np.zeros((3, 3))) == 1.0
    with pytest.raises(ValueError, match="shapes differ"):
        mask_iou(a, b[:5])


def test_objects_are_matched_whatever_their_numbers():
    gt = np.zeros((20, 20), np.uint8)
    gt[2:8, 2:8] = 1  # 36 px
    gt[10:18, 10:18] = 2  # 64 px
    pred = np.zeros((20, 20), np.int32)
    pred[2:8, 2:8] = 7  # object 1, exactly
    pred[10:18, 10:14] = 3  # half of object 2
    pred[0, 0] = -1  # unknown counts as background
    s = score_masks(pred, gt)
    assert s.matching == {1: 7, 2: 3}
    assert s.object_iou[1] == 1.0
    assert s.object_iou[2] == pytest.approx(0.5)
    assert s.mean_object_iou == pytest.approx(0.75)
    assert s.foreground_iou == pytest.approx(68 / 100)
    assert s.precision == 1.0 and s.recall == pytest.approx(0.68)
    # Identity matching compares equal ids: nothing matches here.
    ident = score_masks(pred, gt, match="identity")
    assert ident.object_iou == {1: 0.0, 2: 0.0}
    # A boolean prediction has one object: it goes to the better-overlapping GT object.
    b = score_masks(pred > 0, gt)
    assert b.matching == {1: 1} and b.object_iou[2] == 0.0
    assert b.foreground_iou == s.foreground_iou


def test_summed_over_images():
    gt = np.zeros((4, 4), np.uint8)
    gt[:2] = 1
    empty = np.zeros((4, 4), np.uint8)
    s = score_mask_set([gt, empty], [gt, gt])
    assert s.foreground_iou == pytest.approx(8 / 16)
    assert s.object_iou == {1: pytest.approx(0.5)} and s.num_images == 2
    assert score_masks(empty, empty).foreground_iou == 1.0
    assert score_masks(empty, empty).mean_object_iou == 1.0
    with pytest.raises(ValueError, match="no masks"):
        score_mask_set([], [])


def test_labels_to_view_keeps_ids():
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]])
    cam = Camera(name="c", width=100, height=80, K=K, R=np.eye(3), t=np.zeros(3))
    lab = np.zeros((80, 100), np.uint8)
    lab[20:60, 30:70] = 2
    half = labels_to_view(cam, lab, 0.5)
    assert half.shape == (40, 50) and set(np.unique(half)) == {0, 2}
    assert abs(int((half == 2).sum()) - 400) <= 40
    dist = Camera(
        name="d",
        width=100,
        height=80,
        K=K,
        R=np.eye(3),
        t=np.zeros(3),
        dist=np.array([-0.2, 0.05, 0, 0, 0]),
    )
    und = labels_to_view(dist, lab, 1.0)
    assert set(np.unique(und)) == {0, 2}
    with pytest.raises(ValueError, match="frames are"):
        labels_to_view(cam, lab[:10], 1.0)
