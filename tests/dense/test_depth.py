"""Pieces of the per-view depth estimation (``edgerecon.dense.depth``)."""

from __future__ import annotations

import cv2
import numpy as np

from edgerecon.dense.depth import Roi, _block, _bounds_at
from edgerecon.geometry import Camera


def test_level_bounds_from_a_crop_equal_the_whole_image_resampled():
    """``_bounds_at`` erodes / dilates only around the working pixels a level crop samples:
    the same values as the whole working image eroded, dilated and resized (nearest)."""

    def whole(near, far, roi, cam0, cam):
        ker = _block(cam0, cam)
        nz = np.where(near > 0, near, np.inf).astype(np.float32)
        n = cv2.erode(nz, ker)
        n = np.where(np.isfinite(n), n, 0).astype(np.float32)
        f = cv2.dilate(far, ker)
        n = cv2.resize(n, cam.size, interpolation=cv2.INTER_NEAREST)
        f = cv2.resize(f, cam.size, interpolation=cv2.INTER_NEAREST)
        return n[roi.y0 : roi.y1, roi.x0 : roi.x1], f[roi.y0 : roi.y1, roi.x0 : roi.x1]

    rng = np.random.default_rng(1)
    for _ in range(60):
        W0, H0 = int(rng.integers(40, 400)), int(rng.integers(30, 300))
        div = float(rng.choice([2, 4, 8, 3.3, 5.7]))
        Wl, Hl = max(1, int(W0 / div)), max(1, int(H0 / div))
        K = np.array([[100.0, 0, W0 / 2], [0, 100, H0 / 2], [0, 0, 1]])
        cam0 = Camera(name="w", K=K, width=W0, height=H0, R=np.eye(3), t=np.zeros(3))
        cam = Camera(name="l", K=K, width=Wl, height=Hl, R=np.eye(3), t=np.zeros(3))
        near = np.where(rng.random((H0, W0)) < 0.3, 0, rng.uniform(1, 5, (H0, W0)))
        near = near.astype(np.float32)
        far = np.where(near > 0, near + rng.uniform(0, 2, (H0, W0)), 0).astype(np.float32)
        x0, y0 = int(rng.integers(0, Wl)), int(rng.integers(0, Hl))
        roi = Roi(x0, y0, int(rng.integers(x0, Wl + 1)), int(rng.integers(y0, Hl + 1)))
        for got, want in zip(
            _bounds_at(near, far, roi, cam0, cam), whole(near, far, roi, cam0, cam), strict=True
        ):
            assert got.shape == want.shape and np.array_equal(got, want)
