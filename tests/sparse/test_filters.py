"""The two-view confirmation filter (a view between the two observing views must agree)."""

import numpy as np

from edgerecon.geometry import Camera, look_at
from edgerecon.sparse.reconstruction import _has_view_between
from edgerecon.views import View


def arc_views(angles_deg, radius=4.0, mask_out=None):
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    views = []
    for i, a in enumerate(np.radians(angles_deg)):
        R, t = look_at((radius * np.cos(a), radius * np.sin(a), 1.0), (0, 0, 1.0))
        cam = Camera(name=f"c{i}", width=640, height=480, K=K, R=R, t=t)
        mask = None
        if mask_out == i:
            mask = np.zeros((480, 640), bool)
        views.append(
            View(camera_id=i, camera=cam, image=np.zeros((480, 640, 3), np.uint8), mask=mask)
        )
    return views


def between(views, observed_by=(0, 2), max_angle=40.0):
    X = np.array([[0.0, 0.0, 1.0]])
    obs = np.zeros((1, len(views)), bool)
    obs[0, list(observed_by)] = True
    cams = [v.camera for v in views]
    return bool(_has_view_between(views, cams, X, obs, np.array([True]), max_angle)[0])


def test_view_between_two_observers_must_confirm():
    assert between(arc_views([0, 15, 30]))  # view 1 sits between views 0 and 2


def test_no_rejection_when_the_middle_view_is_too_different_or_absent():
    assert not between(arc_views([0, 15, 30]), max_angle=10.0)  # 15 deg from each: too far
    assert not between(arc_views([0, 60, 30]))  # view 1 is outside the pair
    assert not between(arc_views([0, 15, 30]), observed_by=(0, 1))  # neighbours: nothing between


def test_view_that_cannot_see_the_point_does_not_count():
    assert not between(arc_views([0, 15, 30], mask_out=1))  # masked out
    views = arc_views([0, 15, 30])
    # turn view 1 away from the point
    R, t = look_at((4 * np.cos(np.radians(15)), 4 * np.sin(np.radians(15)), 1.0), (8, 8, 1.0))
    cam = Camera(name="away", width=640, height=480, K=views[1].camera.K, R=R, t=t)
    views[1] = View(camera_id=1, camera=cam, image=views[1].image)
    assert not between(views)
