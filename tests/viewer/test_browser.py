"""The viewer in a real browser: headless Chromium opens it and draws the points."""

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("viser")

from edgerecon.viewer.layout import ViewPose, initial_view
from edgerecon.viewer.server import RunViewer, ViewerConfig
from tests.conftest import ring_rig
from tests.viewer._browser import Browser, chromium_or_skip
from tests.viewer._runs import scene_cloud, write_run

W, H = 1280, 800


def project(points: np.ndarray, view: ViewPose) -> np.ndarray:
    """Pixel coordinates of ``points`` in the browser's first view (pinhole, W x H)."""
    f = view.look_at - view.position
    f /= np.linalg.norm(f)
    r = np.cross(f, view.up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d = points - view.position
    z = d @ f
    focal = (H / 2) / np.tan(np.radians(view.fov_deg) / 2)
    return np.column_stack([W / 2 + focal * (d @ r) / z, H / 2 - focal * (d @ u) / z])


def red_mask(image: np.ndarray) -> np.ndarray:
    b, g, r = (image[..., i].astype(int) for i in range(3))
    return (r > 150) & (g < 90) & (b < 90)


def blue_mask(image: np.ndarray) -> np.ndarray:
    b, g, r = (image[..., i].astype(int) for i in range(3))
    return (b > 150) & (r < 100) & (g < 120)


@pytest.mark.slow
def test_chromium_draws_the_newest_cloud_where_the_scene_is(tmp_path):
    binary = chromium_or_skip()
    run = write_run(tmp_path / "run", num_tasks=3)
    # Where the newest task's foreground (a red box) must appear in the first view.
    view = initial_view(ring_rig(5))
    cloud = scene_cloud(shift=0.2)
    uv = project(cloud.points3D[cloud.labels == 1], view)
    x0, y0 = np.floor(uv.min(axis=0)).astype(int)
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int)
    assert 0 < x0 < x1 < W and 0 < y0 < y1 < H
    box = np.zeros((H, W), bool)
    box[y0 : y1 + 1, x0 : x1 + 1] = True
    margin = np.zeros((H, W), bool)
    margin[max(y0 - 12, 0) : y1 + 13, max(x0 - 12, 0) : x1 + 13] = True

    def drawn(image: np.ndarray) -> bool:
        red = red_mask(image)
        return red[box].mean() > 0.3

    with (
        RunViewer(run, ViewerConfig(port=0)) as viewer,
        Browser(binary, viewer.url, W, H) as browser,
    ):
        image = browser.wait_for(drawn, timeout_s=90)
    out = Path(os.environ.get("EDGERECON_SCREENSHOT_DIR", tmp_path))
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / "viewer.png"), image)
    red = red_mask(image)
    # The foreground is drawn, densely, where it projects, and nowhere else.
    assert red[box].mean() > 0.3, f"only {red[box].mean():.1%} of the box is red"
    assert red[~margin].sum() < 0.05 * red[box].sum()
    # The background (blue floor) is drawn around it.
    assert blue_mask(image).sum() > 2000
