import numpy as np

from edgerecon.sparse.matching import PairMatches
from edgerecon.sparse.tracks import build_tracks


def pm(a, b, la, lb, ratio=None):
    la, lb = np.asarray(la, np.int64), np.asarray(lb, np.int64)
    r = np.zeros(len(la), np.float32) if ratio is None else np.asarray(ratio, np.float32)
    return PairMatches(
        view_a=a,
        view_b=b,
        location_a=la,
        location_b=lb,
        distance=np.zeros(len(la), np.float32),
        ratio=r,
    )


def rows(tracks):
    return sorted(map(tuple, tracks.locations.tolist()))


def test_chains_of_pairwise_matches_form_multi_view_tracks():
    matches = [pm(0, 1, [0, 1], [5, 6]), pm(1, 2, [5], [2]), pm(0, 2, [3], [4])]
    t = build_tracks([4, 7, 5], matches)
    assert rows(t) == sorted([(0, 5, 2), (1, 6, -1), (3, -1, 4)])
    assert t.num_conflicting == 0


def test_track_with_two_locations_in_one_view_is_rejected():
    # 0:0 - 1:0 - 2:0 - 0:1 : view 0 appears twice.
    matches = [pm(0, 1, [0], [0]), pm(1, 2, [0], [0]), pm(0, 2, [1], [0]), pm(0, 1, [2], [1])]
    t = build_tracks([3, 2, 1], matches)
    assert rows(t) == [(2, 1, -1)]
    assert t.num_conflicting == 1


def test_inconsistent_component_is_split_on_its_distinctive_matches():
    matches = [
        pm(0, 1, [0], [0], ratio=[0.5]),
        pm(1, 2, [0], [0], ratio=[0.6]),
        pm(0, 2, [1], [0], ratio=[0.84]),  # the weak, wrong match
    ]
    t = build_tracks([2, 1, 1], matches, strict_ratio=0.75)
    assert rows(t) == [(0, 0, 0)]
    assert t.num_conflicting == 1 and t.num_recovered == 1
    assert t.ratio is not None and t.ratio[0] == np.float32(0.5)


def test_no_matches_no_tracks():
    t = build_tracks([3, 3], [pm(0, 1, [], [])])
    assert t.locations.shape == (0, 2)
