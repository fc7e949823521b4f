"""SIFT features of one view: the feature budget on low-contrast images."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.sparse import SparseConfig
from edgerecon.sparse.features import extract_features
from edgerecon.views import View
from tests.conftest import ring_rig
from tests.sparse.scenes import texture


def low_contrast_view(contrast: float, mask: bool = False) -> View:
    """A textured 640x480 image whose contrast around its mean is scaled by ``contrast``."""
    cam = ring_rig(3).cameras[0]
    img = texture(3)[:480, :640].astype(np.float32)
    img = np.clip(img.mean() + (img - img.mean()) * contrast, 0, 255).round().astype(np.uint8)
    m = None
    if mask:
        m = np.zeros((480, 640), bool)
        m[:, :320] = True
    return View(camera_id=0, camera=cam, image=img, mask=m)


def test_budget_raises_the_keypoint_count_on_a_low_contrast_image():
    view = low_contrast_view(0.08)
    without = extract_features(view, SparseConfig(min_features=0))
    with_budget = extract_features(view, SparseConfig(min_features=400))
    assert len(without) < 200
    assert len(with_budget) >= 400
    assert len(with_budget) > 3 * len(without)


def test_budget_changes_nothing_on_a_well_contrasted_image():
    view = low_contrast_view(1.0)
    a = extract_features(view, SparseConfig(min_features=0))
    b = extract_features(view, SparseConfig(min_features=400))
    assert len(a) >= 400
    np.testing.assert_array_equal(a.points2D, b.points2D)


def test_budget_is_scaled_by_the_mask_share():
    # Half the image masked: the budget is halved, so a budget of 2x the count on the whole
    # image is met by the masked half at the same threshold when texture is uniform.
    view = low_contrast_view(1.0, mask=True)
    full = extract_features(low_contrast_view(1.0), SparseConfig(min_features=0))
    half = extract_features(view, SparseConfig(min_features=0))
    budget = extract_features(view, SparseConfig(min_features=int(1.5 * len(full))))
    assert len(half) < len(full)
    assert len(budget) > len(half)  # 0.75 x full > half: lowered
    same = extract_features(view, SparseConfig(min_features=len(half)))
    np.testing.assert_array_equal(same.points2D, half.points2D)


@pytest.mark.parametrize(
    ("field", "value"), [("min_features", -1), ("contrast_step", 1.0), ("contrast_steps", 9)]
)
def test_budget_config_validation(field, value):
    with pytest.raises(ValueError, match=field):
        SparseConfig(**{field: value})
