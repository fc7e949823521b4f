"""Rendering: exact ground truth, determinism, realism, photo-consistency, features."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgerecon.synth import Renderer, build_scene, preset_config
from edgerecon.synth.render import pixel_grid_rays


def _reproject(renderer: Renderer, frame, i: int, j: int):
    """Back-project every pixel of camera i with its ground-truth depth, project it into
    camera j, read camera j's depth there (bilinear in inverse depth, exact on planes) and
    project that point back into camera i. Returns (pixel error, 3D error, selection) for
    correspondences that camera j sees, away from depth edges."""
    ci, cj = renderer.scene.rig[i], renderer.scene.rig[j]
    h, w = frame.depths[i].shape
    vv, uu = np.mgrid[0:h, 0:w]
    p = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    X = ci.backproject(p, frame.depths[i].ravel())
    q, z = cj.project(X)
    ok = cj.in_image(q, margin=1.0)
    q, z, X, p = q[ok], z[ok], X[ok], p[ok]
    label = frame.masks[i].ravel()[ok]
    u0 = np.floor(q[:, 0]).astype(int)
    v0 = np.floor(q[:, 1]).astype(int)
    a, b = q[:, 0] - u0, q[:, 1] - v0
    D, M = frame.depths[j], frame.masks[j]
    d4 = np.stack([D[v0, u0], D[v0, u0 + 1], D[v0 + 1, u0], D[v0 + 1, u0 + 1]], axis=1)
    m4 = np.stack([M[v0, u0], M[v0, u0 + 1], M[v0 + 1, u0], M[v0 + 1, u0 + 1]], axis=1)
    inv = 1.0 / d4
    inv_z = (1 - a) * (1 - b) * inv[:, 0] + a * (1 - b) * inv[:, 1]
    inv_z += (1 - a) * b * inv[:, 2] + a * b * inv[:, 3]
    zj = 1.0 / inv_z
    smooth = (d4.max(axis=1) - d4.min(axis=1)) < 0.01 * z
    sel = (m4 == label[:, None]).all(axis=1) & smooth & (np.abs(zj - z) < 0.005 * z)
    Xj = cj.backproject(q[sel], zj[sel])
    back, _ = ci.project(Xj)
    return np.linalg.norm(back - p[sel], axis=1), np.linalg.norm(Xj - X[sel], axis=1), sel, q, p


@pytest.mark.parametrize("which", ["pinhole", "distorted", "hd4"])
def test_ground_truth_depth_reprojects_to_the_same_surface_point(
    which, small_renderer, small_frame, distorted_renderer, hd4_renderer
):
    renderer = {"pinhole": small_renderer, "distorted": distorted_renderer, "hd4": hd4_renderer}[
        which
    ]
    # hd4: 4 cameras 90 degrees apart, phone-like distortion, all three actors, lights dimmed.
    frame = {"pinhole": small_frame, "distorted": distorted_renderer.render(2)}.get(
        which
    ) or hd4_renderer.render(212)
    assert renderer.scene.rig[0].has_distortion == (which != "pinhole")
    pairs = [(0, 1), (1, 2), (2, 3), (3, 0)] if which == "hd4" else [(0, 1), (1, 2), (3, 4)]
    for i, j in pairs:
        err_px, err_m, sel, _, _ = _reproject(renderer, frame, i, j)
        assert sel.sum() > 10_000  # neighbours share most of the scene
        assert np.median(err_px) < 1e-3
        # The check interpolates depth bilinearly (exact on planes only): the actors' curved
        # surfaces seen 90 degrees apart at 320x180 (hd4) reproject within ~0.3 px.
        assert np.percentile(err_px, 95) < (0.1 if which == "hd4" else 0.05)
        assert np.percentile(err_px, 99) < 0.5
        assert np.median(err_m) < 1e-5


def test_background_depth_is_exact_on_every_surface(small_renderer, small_scene):
    """Every background pixel back-projects onto the analytic surface it shows."""
    room = small_scene.room
    for k, cam in enumerate(small_scene.rig):
        depth = small_renderer.background_depth(k)
        labels = small_renderer.background_labels(k).ravel()
        h, w = depth.shape
        vv, uu = np.mgrid[0:h, 0:w]
        X = cam.backproject(np.stack([uu.ravel(), vv.ravel()], axis=1), depth.ravel())
        x, y, z = X[labels == 0].T
        planes = np.stack(
            [z, room.height - z, room.half_x - np.abs(x), room.half_y - np.abs(y)], axis=1
        )
        assert np.abs(planes).min(axis=1).max() < 5e-5  # on the floor, ceiling or a wall
        assert planes.min() > -5e-5  # and nothing outside the room
        assert (np.abs(z) < 5e-5).mean() > 0.2  # the floor fills a good part of the view
        for j, item in enumerate(small_scene.furniture, start=1):
            pts = X[labels == j]
            if len(pts) == 0:
                continue
            if hasattr(item, "half"):
                local = (pts - item.center) @ item.rotation
                on_face = (np.abs(local) / item.half).max(axis=1)
                np.testing.assert_allclose(on_face, 1.0, atol=5e-4)
            else:
                rho = np.hypot(pts[:, 0] - item.center_xy[0], pts[:, 1] - item.center_xy[1])
                side = np.abs(rho - item.radius)
                cap = np.minimum(np.abs(pts[:, 2] - item.z1), np.abs(pts[:, 2] - item.z0))
                assert np.minimum(side, cap).max() < 5e-5


@pytest.mark.parametrize("which", ["demo", "hd4"])
def test_masks_and_depth_agree(which, small_renderer, small_frame, hd4_renderer):
    renderer, frame, ids = small_renderer, small_frame, {0, 1, 2}
    if which == "hd4":  # the still actor, the seated one on its chair, the one who left
        renderer, frame, ids = hd4_renderer, hd4_renderer.render(100), {0, 1, 3}
    for k in range(len(frame.images)):
        mask, depth = frame.masks[k], frame.depths[k]
        bg = renderer.background_depth(k)
        fg = mask > 0
        assert fg.mean() > 0.005  # the actors are in view of every camera
        assert set(np.unique(mask)) == ids if which == "hd4" else set(np.unique(mask)) <= ids
        # Actors are in front of the background; elsewhere the depth is the background's.
        assert np.all(depth[fg] < bg[fg])
        assert np.array_equal(depth[~fg], bg[~fg])
        assert depth.dtype == np.float32 and np.all(np.isfinite(depth))


def test_rendering_is_deterministic(small_scene, small_frame):
    again = Renderer(small_scene, threads=1).render(2, clean=True)
    for a, b in zip(small_frame.images, again.images, strict=True):
        assert np.array_equal(a, b)
    for a, b in zip(small_frame.depths, again.depths, strict=True):
        assert np.array_equal(a, b)
    other = build_scene(preset_config("demo", num_frames=4, width=320, height=240, seed=9))
    assert not np.array_equal(Renderer(other).render(2).images[0], small_frame.images[0])


def test_noise_exposure_and_background_frames(small_renderer, small_scene, small_frame):
    # Background-clip frames (t < 0) show the empty scene; noise differs between frames.
    b0 = small_renderer.render(-2)
    b1 = small_renderer.render(-1)
    assert all(m.max() == 0 for m in b0.masks)
    diff = b0.images[0].astype(np.float32) - b1.images[0].astype(np.float32)
    sigma = small_scene.config.realism.noise_sigma
    # Two independent noise draws: std of the difference is sqrt(2) sigma (minus rounding).
    assert 0.8 * np.sqrt(2) * sigma < diff.std() < 1.3 * np.sqrt(2) * sigma
    # Cameras differ slightly in exposure: the same surface is not bit-identical in colour.
    gains = small_scene.camera_gains
    assert np.ptp(gains[:, 1]) > 0.005
    assert np.all(np.abs(gains - 1) < 0.1)


def test_photo_consistency_on_ground_truth_correspondences(small_renderer, small_frame):
    """Lambertian shading: the same surface point looks the same from two cameras (up to
    noise, exposure and interpolation)."""
    mad = {}
    for name, images in (("clean", small_frame.clean), ("final", small_frame.images)):
        diffs = []
        for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0)]:
            _, _, sel, q, p = _reproject(small_renderer, small_frame, i, j)
            qs = q[sel].astype(np.float32)
            ii = images[i][p[sel][:, 1].astype(int), p[sel][:, 0].astype(int)].astype(np.float32)
            jj = cv2.remap(images[j], qs[None, :4000, 0], qs[None, :4000, 1], cv2.INTER_LINEAR)
            diffs.append(np.abs(ii[:4000] - jj[0].astype(np.float32)).mean())
        mad[name] = float(np.mean(diffs))
    print(f"photo-consistency, mean |I_i - I_j| (grey levels): {mad}")
    assert mad["clean"] < 8.0
    assert mad["final"] < 10.0


def test_views_have_enough_sift_features(small_frame):
    sift = cv2.SIFT_create()
    counts = [len(sift.detect(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY))) for im in small_frame.images]
    print(f"SIFT keypoints per 320x240 view: {counts}")
    assert min(counts) > 200


def test_pixel_grid_rays_match_camera_pixel_rays(distorted_renderer):
    cam = distorted_renderer.scene.rig[1]
    xn, yn = pixel_grid_rays(cam)
    pix = np.array([[0, 0], [cam.width - 1, cam.height - 1], [100, 37]])
    ref = cam.pixel_rays(pix)
    got = np.stack([xn[pix[:, 1], pix[:, 0]], yn[pix[:, 1], pix[:, 0]]], axis=1)
    np.testing.assert_allclose(got, ref[:, :2], atol=1e-6)
    uv, _ = cam.project(np.concatenate([got, np.ones((3, 1))], axis=1) @ cam.R + cam.center)
    np.testing.assert_allclose(uv, pix, atol=1e-3)


def test_render_rejects_out_of_range_frames(small_renderer):
    with pytest.raises(ValueError, match="out of range"):
        small_renderer.render(4)
    with pytest.raises(ValueError, match="out of range"):
        small_renderer.render(-3)


def test_frame_equals_blurred_composite_with_gains():
    """The cached-background fast path gives the same frame as blurring the whole composite."""
    cfg = preset_config("demo", num_frames=3, width=200, height=150, noise_sigma=0.0)
    scene = build_scene(cfg)
    frame = Renderer(scene).render(1, clean=True)
    sigma = cfg.realism.blur_sigma_px
    assert sigma > 0
    for k, (image, clean) in enumerate(zip(frame.images, frame.clean, strict=True)):
        gain = scene.camera_gains[k] * scene.illumination(1)
        ref = cv2.GaussianBlur(clean.astype(np.float32) * gain, (0, 0), sigma)
        diff = np.abs(image.astype(np.float32) - np.clip(ref, 0, 255)).max(axis=2)
        # Saturated clean pixels lost their true value: leave out their neighbourhoods.
        saturated = cv2.dilate((clean.max(axis=2) == 255).astype(np.uint8), np.ones((5, 5)))
        assert saturated.mean() < 0.01
        # The clean image is rounded to 8 bits before blurring here: allow ~1 grey level.
        assert diff[saturated == 0].max() <= 1.6, (k, diff.max())
        assert frame.masks[k].any()


def test_contact_shadows_darken_only_the_floor_near_actors(
    small_renderer, small_scene, small_frame
):
    reach = small_scene.config.realism.contact_shadow_radius_m
    feet = [a.position(2.0) for a in small_scene.actors_at(2)]
    darker_total = 0
    for k, cam in enumerate(small_scene.rig):
        empty = small_renderer.background_clean(k).astype(int)
        now = small_frame.clean[k].astype(int)
        changed = (np.abs(now - empty).max(axis=2) > 1) & (small_frame.masks[k] == 0)
        if not changed.any():
            continue
        assert np.all(now[changed].sum(axis=1) < empty[changed].sum(axis=1))  # darker
        vv, uu = np.nonzero(changed)
        X = cam.backproject(np.stack([uu, vv], axis=1), small_frame.depths[k][vv, uu])
        assert np.abs(X[:, 2]).max() < 1e-3  # on the floor
        near = np.min([np.hypot(X[:, 0] - p[0], X[:, 1] - p[1]) for p in feet], axis=0)
        assert near.max() < reach + 0.01  # close to an actor
        darker_total += int(changed.sum())
    assert darker_total > 100
