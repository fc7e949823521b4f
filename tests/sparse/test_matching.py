import numpy as np
import pytest

from edgerecon.geometry import Camera, fundamental_matrix, look_at
from edgerecon.sparse import SparseConfig
from edgerecon.sparse.features import Features
from edgerecon.sparse.matching import epipolar_candidates, match_pair, two_view_depths
from edgerecon.sparse.triangulation import project_all
from tests.conftest import ring_rig


def unit(rng, n):
    d = np.abs(rng.standard_normal((n, 128))).astype(np.float32)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def make_features(points2D, descriptors):
    pts = np.asarray(points2D, float)
    return Features(
        points2D=pts,
        descriptors=np.asarray(descriptors, np.float32),
        sizes_px=np.full(len(pts), 4.0, np.float32),
        location=np.arange(len(pts)),
        location_points2D=pts,
    )


def line_distance(F, a, b):
    """Symmetric epipolar distances (both directions), brute force."""
    ha = np.hstack([a, np.ones((len(a), 1))])
    hb = np.hstack([b, np.ones((len(b), 1))])
    lb = ha @ F.T
    la = hb @ F
    db = np.abs(lb @ hb.T) / np.hypot(lb[:, :1], lb[:, 1:2])
    da = (np.abs(la @ ha.T) / np.hypot(la[:, :1], la[:, 1:2])).T
    return np.maximum(da, db)


def camera_pair(kind):
    """Two cameras whose epipoles are outside the images, inside them, or at infinity."""
    rig = ring_rig(3)
    if kind == "ring":
        return rig[0], rig[1]
    K = rig[0].K
    if kind == "facing":  # b looks at a from across the room: epipoles inside both images
        Ra, ta = look_at((0, 0, 1.5), (4, 0.5, 1.4))
        Rb, tb = look_at((4, 0.5, 1.4), (0, 0, 1.5))
    elif kind == "parallel":  # rectified stereo: epipoles at infinity
        Ra, ta = look_at((0, 0, 1.5), (0, 4, 1.5))
        Rb, tb = look_at((0.5, 0, 1.5), (0.5, 4, 1.5))
    else:  # forward motion: epipoles at the image centres
        Ra, ta = look_at((0, 0, 1.5), (0, 4, 1.5))
        Rb, tb = look_at((0, 1, 1.5), (0, 5, 1.5))
    mk = lambda n, R, t: Camera(name=n, width=640, height=480, K=K, R=R, t=t)  # noqa: E731
    return mk("a", Ra, ta), mk("b", Rb, tb)


@pytest.mark.parametrize("kind", ["ring", "facing", "parallel", "forward"])
@pytest.mark.parametrize("threshold", [0.7, 2.5])
def test_epipolar_candidates_equal_brute_force(kind, threshold):
    cam_a, cam_b = camera_pair(kind)
    rng = np.random.default_rng(0)
    a = rng.uniform([0, 0], [640, 480], (700, 2))
    b = rng.uniform([0, 0], [640, 480], (900, 2))
    F = fundamental_matrix(cam_a, cam_b)
    ia, ib = epipolar_candidates(a, b, F, threshold)
    got = list(zip(ia.tolist(), ib.tolist(), strict=True))
    assert len(got) == len(set(got))  # no duplicates
    want = set(zip(*np.nonzero(line_distance(F, a, b) <= threshold), strict=True))
    assert set(got) == {(int(i), int(j)) for i, j in want}
    assert len(got) > 30


def test_two_view_depths_exact_and_negative_behind():
    rig = ring_rig(3)
    rng = np.random.default_rng(1)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (50, 3))
    uv, z = project_all([rig[0], rig[1]], X)
    sa, sb = two_view_depths(rig[0], rig[1], uv[:, 0], uv[:, 1])
    assert np.allclose(sa, z[:, 0]) and np.allclose(sb, z[:, 1])


def synthetic_pair(n=300, seed=0):
    """Two views of random 3D points with shared descriptors (+ small noise)."""
    rig = ring_rig(4)
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1.5, -1.5, 0], [1.5, 1.5, 2], (n, 3))
    uv, _ = project_all([rig[0], rig[1]], X)
    desc = unit(rng, n)
    noisy = desc + rng.normal(0, 0.01, desc.shape).astype(np.float32)
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    return rig, X, uv, desc, noisy


def test_match_pair_finds_true_correspondences_on_epipolar_lines():
    rig, X, uv, desc, noisy = synthetic_pair()
    perm = np.random.default_rng(3).permutation(len(X))
    fa = make_features(uv[:, 0], desc)
    fb = make_features(uv[perm, 1], noisy[perm])
    m = match_pair(fa, fb, rig[0], rig[1], SparseConfig())
    assert len(m) >= 0.95 * len(X)
    assert np.array_equal(perm[m.location_b], m.location_a)  # every match is right
    F = fundamental_matrix(rig[0], rig[1])
    d = line_distance(F, fa.points2D[m.location_a], fb.points2D[m.location_b]).diagonal()
    assert d.max() <= SparseConfig().epipolar_threshold_px
    assert np.all(m.ratio < SparseConfig().ratio)


def test_identical_descriptor_off_the_epipolar_line_is_ignored():
    # The epipolar constraint makes matching immune to look-alikes elsewhere in the image.
    rig, _X, uv, desc, noisy = synthetic_pair(n=50, seed=4)
    fa = make_features(uv[:, 0], desc)
    decoy = uv[:, 1] + [0.0, 40.0]  # same descriptor, 40 px away from the true match
    fb = make_features(np.vstack([decoy, uv[:, 1]]), np.vstack([desc, noisy]))
    F = fundamental_matrix(rig[0], rig[1])
    off_line = line_distance(F, uv[:, 0], decoy).diagonal() > 5
    m = match_pair(fa, fb, rig[0], rig[1], SparseConfig())
    matched = dict(zip(m.location_a.tolist(), m.location_b.tolist(), strict=True))
    for k in np.flatnonzero(off_line):
        assert matched.get(int(k)) == 50 + k


def test_ambiguous_candidates_on_one_epipolar_line_are_rejected():
    rig, X, uv, desc, noisy = synthetic_pair(n=1, seed=5)
    fa = make_features(uv[:, 0], desc)
    # A second identical-looking point on the same epipolar line (another depth).
    other = X[0] + 0.3 * (X[0] - rig[0].center)
    uv2, _ = project_all([rig[1]], other[None])
    fb = make_features(np.vstack([uv[:, 1], uv2[:, 0]]), np.vstack([noisy, noisy]))
    m = match_pair(fa, fb, rig[0], rig[1], SparseConfig())
    assert len(m) == 0
    # Without the look-alike the match is found.
    m = match_pair(fa, make_features(uv[:, 1], noisy), rig[0], rig[1], SparseConfig())
    assert len(m) == 1


def pinhole(cam, X):
    """Projective pixel of X, also for points behind the camera (no cheirality)."""
    Xc = X @ cam.R.T + cam.t
    h = Xc @ cam.K.T
    return h[:, :2] / h[:, 2:]


def test_points_behind_a_camera_and_outside_the_depth_range_are_not_matched():
    rig, X, uv, desc, noisy = synthetic_pair(n=40, seed=6)
    fa = make_features(uv[:, 0], desc)
    fb = make_features(uv[:, 1], noisy)
    m = match_pair(fa, fb, rig[0], rig[1], SparseConfig())
    assert len(m) >= 38
    # A depth range that excludes the scene (beyond 20 m) leaves nothing.
    assert len(match_pair(fa, fb, rig[0], rig[1], SparseConfig(min_depth=20.0))) == 0
    assert len(match_pair(fa, fb, rig[0], rig[1], SparseConfig(max_depth=1.0))) == 0
    # Pixel pairs that satisfy the epipolar constraint but meet behind camera a.
    ca = rig[0].center
    behind = ca - 0.5 * (X - ca)
    pa, pb = pinhole(rig[0], behind), pinhole(rig[1], behind)
    assert np.all((behind - rig[1].center) @ rig[1].viewing_direction > 0)  # in front of b
    m = match_pair(make_features(pa, desc), make_features(pb, noisy), rig[0], rig[1])
    assert len(m) == 0


def test_empty_features_give_empty_matches():
    rig = ring_rig(3)
    m = match_pair(Features.empty(), Features.empty(), rig[0], rig[1])
    assert len(m) == 0 and m.ratio.shape == (0,)


@pytest.mark.parametrize(
    ("field", "value"),
    [("ratio", 1.5), ("epipolar_threshold_px", 0.0), ("max_depth", -1.0), ("num_threads", 0)],
)
def test_config_validation_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        SparseConfig(**{field: value})


def test_look_alike_next_to_the_match_makes_it_ambiguous():
    # A feature on a seam: its epipolar line holds one candidate, but the seam's next
    # keypoint (off the line, 8 px away) looks the same.
    rig, _X, uv, desc, noisy = synthetic_pair(n=1, seed=7)
    fa = make_features(uv[:, 0], desc)
    F = fundamental_matrix(rig[0], rig[1])
    line = F @ np.append(uv[0, 0], 1.0)
    normal = line[:2] / np.hypot(*line[:2])
    beside = uv[:, 1] + 8.0 * normal  # off the epipolar line
    fb = make_features(np.vstack([uv[:, 1], beside]), np.vstack([noisy, noisy]))
    assert len(match_pair(fa, fb, rig[0], rig[1], SparseConfig())) == 0
    m = match_pair(fa, fb, rig[0], rig[1], SparseConfig(neighbour_competitors=0))
    assert len(m) == 1 and m.location_b[0] == 0
    # A different-looking neighbour does not hurt.
    other = unit(np.random.default_rng(8), 1)
    fb = make_features(np.vstack([uv[:, 1], beside]), np.vstack([noisy, other]))
    assert len(match_pair(fa, fb, rig[0], rig[1], SparseConfig())) == 1
