"""Real data: the person of utrecht4cam is segmented in all four views."""

from __future__ import annotations

import pytest

from edgerecon.io.dataset import open_dataset
from edgerecon.scene import BackgroundConfig, ForegroundConfig, RigForeground, hull_silhouette
from tests.conftest import shared_data

pytestmark = pytest.mark.shared_data


@pytest.fixture(scope="module")
def result():  # type: ignore[no-untyped-def]
    ds = open_dataset(shared_data("utrecht4cam"))
    with ds.open_background() as bg:  # type: ignore[union-attr]
        clip = list(bg.iter_frames(0, None, 4))
    config = ForegroundConfig(background=BackgroundConfig(max_learning_frames=20))
    fg = RigForeground.learn_from_framesets(ds.rig, clip, config)
    with ds.open_frames() as src:
        for t in range(197, 200):
            fg.update(src.read(t))
        frames = src.read(200)
    return ds, fg.segment(frames)


def test_person_is_segmented_in_all_four_views(result) -> None:  # type: ignore[no-untyped-def]
    ds, res = result
    for cam, seg in zip(ds.rig, res.objects, strict=True):
        assert seg is not None and seg.num_objects >= 1, cam.name
        person = seg.objects[0]
        share = person.area_px / seg.labels.size  # masks are at the working resolution
        # A seated person (with the chair) covers 2.5-6 % of these 644x486 views.
        assert 0.02 < share < 0.07, (cam.name, share)
        # Compact: the object fills a good part of its box (not scattered noise).
        _, _, w, h = person.bbox
        assert person.area_px / (w * h) > 0.35, cam.name
        assert 1.5 < h / w < 3.5, (cam.name, w, h)


def test_the_hull_is_one_seated_person_on_the_floor(result) -> None:  # type: ignore[no-untyped-def]
    ds, res = result
    hull = res.hull
    assert hull is not None and hull.status == "ok"
    assert hull.num_objects >= 1
    lo, hi = hull.object_bounds()[1]  # millimetres, up = -Z, floor at z = 0
    height = -lo[2]  # top of the head above the floor
    assert 1200 < height < 2000, height
    assert -300 < hi[2] < 300  # reaches the floor
    footprint = hi[:2] - lo[:2]
    assert (footprint > 300).all() and (footprint < 1600).all(), footprint
    # Every camera's person region is explained by the hull (silhouette consistency).
    for cam in res.cameras:  # the rig's cameras at the masks' working resolution
        sil = hull_silhouette(hull, cam)
        person = res.objects[ds.rig.index(cam.name)].object_mask(1)
        assert (sil & person).sum() / person.sum() > 0.97, cam.name
