"""Compiled (numba) inner loops of the scene stage: the photo check's judgement
(:mod:`edgerecon.scene.ghosts`), the visual hull's per-camera carving vote
(:func:`edgerecon.scene.hull.visual_hull`) and the objects' association across cameras
(:func:`edgerecon.scene.split.split_sparse`, which also labels each task's dense foreground).

Per judged point the check compares its colour in one camera with its colour in every other
camera that holds it: the per-pair colour ratio, the largest channel difference, the
chromaticity and brightness test and the local-contrast test, then the smallest difference,
whether another camera vouches for the point and whether one sees its tint at another
brightness. In NumPy that is ~40 passes over (3, N) temporaries per camera pair; fused here
into one pass per point. The arithmetic is NumPy's: float32 throughout, constants as float32,
no reordering (no fastmath), so the results are the NumPy code's bit for bit. The carving
projects each voxel, tests its footprint against three distance maps and votes, where NumPy
made ~30 passes over float32 temporaries per camera and level.
"""

from __future__ import annotations

import cv2
import numba as nb
import numpy as np
from numpy.typing import NDArray

_INF = np.float32(np.inf)


@nb.njit(nogil=True, cache=True)
def judge_points(
    c: int,
    idx: NDArray[np.intp],
    colours: NDArray[np.float32],
    contrasts: NDArray[np.float32],
    has_contrast: bool,
    inside: NDArray[np.bool_],
    alone: NDArray[np.bool_],
    valid: NDArray[np.bool_],
    ratios: NDArray[np.float32],
    has_ratio: NDArray[np.bool_],
    max_chroma: np.float32,
    max_ratio: np.float32,
    texture_tol: np.float32,
    dist: NDArray[np.float32],
    vouch: NDArray[np.bool_],
    tinted: NDArray[np.bool_],
) -> None:
    """Camera ``c``'s judgement of the points ``idx`` against every other ``valid`` camera.

    ``colours`` (n, 3, N) BGR per camera and point, ``contrasts`` (n, N) local contrasts
    (used when ``has_contrast``), ``inside`` / ``alone`` (n, N) as ``ghosts._View``,
    ``ratios`` (n, n, 3) the colour ratio of camera o's colours to c's (applied when
    ``has_ratio[c, o]``). Writes per judged point: ``dist`` the smallest largest-channel
    difference over the cameras that hold it (inf: none, or no contrast alike), ``vouch``
    whether some other camera holds it alone, ``tinted`` whether one holds it in the same
    tint."""
    n = colours.shape[0]
    one = np.float32(1.0)
    two_thirds = np.float32(2.0 / 3.0)
    for k in range(idx.shape[0]):
        p = idx[k]
        a0 = colours[c, 0, p]
        a1 = colours[c, 1, p]
        a2 = colours[c, 2, p]
        sa = a0 + a1 + a2 + one
        ia = one / sa
        best = _INF
        v = False
        t = False
        for o in range(n):
            if o == c or not valid[o]:
                continue
            if alone[o, p]:
                v = True
            if not inside[o, p]:
                continue
            b0 = colours[o, 0, p]
            b1 = colours[o, 1, p]
            b2 = colours[o, 2, p]
            if has_ratio[c, o]:
                b0 = b0 * ratios[c, o, 0]
                b1 = b1 * ratios[c, o, 1]
                b2 = b2 * ratios[c, o, 2]
            sb = b0 + b1 + b2 + one
            ib = one / sb
            chroma = abs(a0 * ia - b0 * ib) + abs(a1 * ia - b1 * ib) + abs(a2 * ia - b2 * ib)
            ratio = sa * ib
            alike = (chroma < max_chroma) and (ratio < max_ratio) and (ratio * max_ratio > one)
            d = max(max(abs(a0 - b0), abs(a1 - b1)), abs(a2 - b2))
            if has_contrast:
                ca = contrasts[c, p]
                cb = contrasts[o, p]
                if not (abs(ca - cb) <= max(texture_tol, two_thirds * max(ca, cb))):
                    d = _INF
                    alike = False
            if alike:
                t = True
            if d < best:
                best = d
        dist[k] = best
        vouch[k] = v
        tinted[k] = t


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels on tiny inputs, so that the first
    task's scene stage does not pay for it (~1 s on these machines)."""
    n, num = 2, 4
    judge_points(
        0,
        np.arange(num, dtype=np.intp),
        np.ones((n, 3, num), np.float32),
        np.ones((n, num), np.float32),
        True,
        np.ones((n, num), bool),
        np.ones((n, num), bool),
        np.ones(n, bool),
        np.ones((n, n, 3), np.float32),
        np.zeros((n, n), bool),
        np.float32(0.03),
        np.float32(1.6),
        np.float32(10.0),
        np.zeros(num, np.float32),
        np.zeros(num, bool),
        np.zeros(num, bool),
    )
    grid = np.ones((2, 2), np.float32)
    carve_camera(
        np.zeros((num, 3), np.int64),
        np.eye(3, dtype=np.float32),
        np.ones(3, np.float32),
        np.eye(3, dtype=np.float32),
        np.zeros(5, np.float32),
        True,
        2,
        2,
        np.float32(0.5),
        np.float32(1.0),
        np.float32(1.0),
        grid,
        grid,
        grid,
        grid,
        True,
        np.zeros(num, np.int32),
        np.zeros(num, np.int32),
        np.ones(num, bool),
    )
    nodes = np.zeros((num, 2), np.int64)
    mode_component(nodes, np.zeros(1, np.int32))
    shared_points(nodes, 1)
    gather_channels(np.ones((2, 2, 3), np.float32), np.zeros(1, np.intp), np.zeros(1, np.intp))
    surface_normals(np.zeros((3, 3, 3), bool), np.ones((1, 3), np.int64), np.eye(3, dtype=np.int64))
    table = disc_half_widths(1)
    ones = np.ones(1, np.int64)
    splat_discs(np.zeros((2, 2), np.uint8), ones, ones, ones, table, 0, 0, 2, 2)
    splat_min_discs(np.zeros((2, 2), np.float32), ones, ones, ones, np.ones(1, np.float32), table)
    outline_gaps(np.zeros((2, 2), np.int32), np.arange(2, dtype=np.int64), 2)
    disc_centres(np.zeros((1, 2)), np.ones(1), 2, 2, 1)
    # The projections' kernels as the scene stage calls them (``Camera.nearest_pixels``).
    from edgerecon.geometry.camera import Camera

    probe = Camera(name="warm-up", width=2, height=2, K=np.eye(3), R=np.eye(3), t=np.ones(3))
    probe.nearest_pixels(np.zeros((1, 3)))
    probe.backproject(np.zeros((1, 2)), np.ones(1))
    flags = np.zeros((num, 2), bool)
    votes = np.zeros((num, 2), np.int32)
    camera_votes(
        0,
        np.zeros((num, 2)),
        np.ones(num),
        2,
        2,
        1.0,
        1.0,
        False,
        np.ones((2, 2), np.uint8),
        flags,
        np.float32(1.0),
        np.zeros(num, np.float32),
        np.zeros(num, np.float32),
        votes,
        votes,
    )


@nb.njit(nogil=True, cache=True, error_model="numpy")
def carve_camera(
    idx: NDArray[np.int64],
    A: NDArray[np.float32],
    b: NDArray[np.float32],
    K: NDArray[np.float32],
    dist: NDArray[np.float32],
    distorted: bool,
    width: int,
    height: int,
    half_diag: np.float32,
    footprint: np.float32,
    tol: np.float32,
    to_fg: NDArray[np.float32],
    to_fg_or_border: NDArray[np.float32],
    inside_dist: NDArray[np.float32],
    wall: NDArray[np.float32],
    has_wall: bool,
    agree: NDArray[np.int32],
    missing: NDArray[np.int32],
    full: NDArray[np.bool_],
) -> None:
    """One camera's vote on the voxels ``idx`` of one level of ``hull.visual_hull``
    (``hull._carve_level``): the centre of voxel (i, j, k) in the camera frame is
    ``A @ (i, j, k) + b``, projected through ``dist`` and ``K``; its footprint radius is
    ``footprint / depth`` (``footprint`` = half diagonal x focal x slack). Adds to ``agree``
    (the footprint touches the silhouette: ``to_fg`` <= radius + ``tol``) and ``missing``
    (it touches neither the silhouette nor the border), and clears ``full`` where part of
    the footprint may be seen but not all of it is inside the silhouette. ``wall`` (when
    ``has_wall``): the static scene's depth; a voxel behind it is hidden from this camera.
    float32 arithmetic in NumPy's order (bit for bit the NumPy version's votes)."""
    one = np.float32(1.0)
    two = np.float32(2.0)
    inf = np.float32(np.inf)
    half_px = np.float32(0.71)
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    two_p1 = two * p1
    two_p2 = two * p2
    w = np.float32(width)
    h = np.float32(height)
    for n in range(idx.shape[0]):
        fi = np.float32(idx[n, 0])
        fj = np.float32(idx[n, 1])
        fk = np.float32(idx[n, 2])
        xc = A[0, 0] * fi + A[0, 1] * fj + A[0, 2] * fk + b[0]
        yc = A[1, 0] * fi + A[1, 1] * fj + A[1, 2] * fk + b[1]
        zc = A[2, 0] * fi + A[2, 1] * fj + A[2, 2] * fk + b[2]
        xn = xc / zc
        yn = yc / zc
        if distorted:
            r2 = xn * xn + yn * yn
            radial = one + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = xn * radial + two_p1 * xn * yn + p2 * (r2 + two * xn * xn)
            yd = yn * radial + p1 * (r2 + two * yn * yn) + two_p2 * xn * yn
            xn = xd
            yn = yd
        u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
        v = K[1, 1] * yn + K[1, 2]
        front = zc > half_diag
        radius = footprint / zc if front else inf
        ur = np.rint(u)
        vr = np.rint(v)
        inside = front and ur >= 0 and ur < w and vr >= 0 and vr < h
        # Any part of the footprint may reach into the image: children may be seen.
        near = zc > -half_diag and not (
            u < -radius - one or u > w + radius or v < -radius - one or v > h + radius
        )
        covered = False
        if inside:
            ui = int(ur)
            vi = int(vr)
            if has_wall and zc - half_diag > wall[vi, ui]:
                inside = False
                near = False
            else:
                if to_fg[vi, ui] <= radius + tol:
                    agree[n] += 1
                if to_fg_or_border[vi, ui] > radius + tol:
                    missing[n] += 1
                covered = inside_dist[vi, ui] >= radius + half_px
        if near and not covered:
            full[n] = False


@nb.njit(nogil=True, cache=True)
def mode_component(node: NDArray[np.int64], comp: NDArray[np.int32]) -> NDArray[np.int64]:
    """Per row of ``node``: the component (``comp`` of its nodes) most of the row's nodes
    (``node`` >= 0) belong to; ties go to the first such node's; -1 for a row without
    nodes (``split._associate_objects``: the object a point takes from the cameras' images it
    lands on)."""
    num_cams = node.shape[1]
    out = np.full(node.shape[0], -1, np.int64)
    pc = np.empty(num_cams, np.int64)
    for p in range(node.shape[0]):
        for j in range(num_cams):
            pc[j] = comp[node[p, j]] if node[p, j] >= 0 else -1
        best = -1
        best_support = 0
        for j in range(num_cams):
            if pc[j] < 0:
                continue
            support = 0
            for i in range(num_cams):
                if pc[i] == pc[j]:
                    support += 1
            if support > best_support:
                best_support = support
                best = pc[j]
        out[p] = best
    return out


@nb.njit(nogil=True, cache=True)
def shared_points(node: NDArray[np.int64], num_nodes: int) -> NDArray[np.int32]:
    """(num_nodes, num_nodes) upper-triangular counts: entry (a, b) = how many rows hold
    both node a (at a lower column) and node b (``split._associate_objects``: points two
    cameras' per-image objects share)."""
    out = np.zeros((num_nodes, num_nodes), np.int32)
    num_cams = node.shape[1]
    for p in range(node.shape[0]):
        for a in range(num_cams):
            na = node[p, a]
            if na < 0:
                continue
            for b in range(a + 1, num_cams):
                nb_ = node[p, b]
                if nb_ >= 0:
                    out[na, nb_] += 1
    return out


@nb.njit(nogil=True, cache=True)
def camera_votes(
    c: int,
    uv: NDArray[np.float64],
    depth: NDArray[np.float64],
    width: int,
    height: int,
    scale_x: float,
    scale_y: float,
    scaled: bool,
    lab: NDArray[np.uint8],
    vis: NDArray[np.bool_],
    unobserving_weight: np.float32,
    fg_w: NDArray[np.float32],
    bg_w: NDArray[np.float32],
    local: NDArray[np.int32],
    local_any: NDArray[np.int32],
) -> None:
    """Camera ``c``'s votes on the points (``split.split_sparse``): a point in front of the
    camera and in its image (``uv`` within half a pixel of the ``width`` x ``height``
    image) looks up its pixel of the label image ``lab`` (at a reduced resolution when
    ``scaled``: ``(uv + 0.5) * scale - 0.5``, rounded half to even and clipped into it) and
    adds its weight (1 when the camera observes it, ``vis[:, c]``, else
    ``unobserving_weight``; 0 votes nothing) to ``fg_w`` or ``bg_w``; a foreground label is
    the point's object in this camera (``local_any``; ``local`` only from observing
    cameras)."""
    lw = lab.shape[1]
    lh = lab.shape[0]
    for p in range(uv.shape[0]):
        u = uv[p, 0]
        v = uv[p, 1]
        if not (depth[p] > 0):
            continue
        if not (u >= -0.5 and u <= width - 0.5 and v >= -0.5 and v <= height - 0.5):
            continue
        w = np.float32(1.0) if vis[p, c] else unobserving_weight
        if not (w > 0):
            continue
        if scaled:
            u = (u + 0.5) * scale_x - 0.5
            v = (v + 0.5) * scale_y - 0.5
        ui = min(max(int(np.rint(u)), 0), lw - 1)
        vi = min(max(int(np.rint(v)), 0), lh - 1)
        hit = lab[vi, ui]
        if hit > 0:
            fg_w[p] += w
            if vis[p, c]:
                local[p, c] = hit
            local_any[p, c] = hit
        else:
            bg_w[p] += w


#: The largest disc radius (pixels) the splat kernels draw point by point; wider discs cost
#: their area per point, and one dilation per radius is cheaper for them.
MAX_KERNEL_DISC = 16


def disc_half_widths(max_radius: int = MAX_KERNEL_DISC) -> NDArray[np.int32]:
    """(R + 1, 2R + 1) per radius r and row offset dy + r, the half width of OpenCV's
    elliptic structuring element of radius r in that row (-1: the row is outside it), so
    that a disc drawn from this table is the element ``cv2.dilate`` / ``cv2.erode`` would
    apply, pixel for pixel."""
    out = np.full((max_radius + 1, 2 * max_radius + 1), -1, np.int32)
    for r in range(max_radius + 1):
        element = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        for row in range(2 * r + 1):
            (cols,) = np.nonzero(element[row])
            if len(cols):
                out[r, row - r + max_radius] = r - int(cols[0])
    return out


#: The table of ``disc_half_widths`` up to MAX_KERNEL_DISC, shared by every caller.
DISC_HALF_WIDTHS = disc_half_widths()


@nb.njit(nogil=True, cache=True)
def _draw_disc(
    out: NDArray[np.uint8],
    cu: int,
    cv: int,
    r: int,
    half_widths: NDArray[np.int32],
    x0: int,
    y0: int,
    x1: int,
    y1: int,
) -> None:
    rmax = (half_widths.shape[1] - 1) // 2
    for dy in range(-r, r + 1):
        y = cv + dy
        if y < y0 or y >= y1:
            continue
        hw = half_widths[r, dy + rmax]
        if hw < 0:
            continue
        for x in range(max(cu - hw, x0), min(cu + hw + 1, x1)):
            out[y, x] = 1


@nb.njit(nogil=True, cache=True)
def splat_discs(
    out: NDArray[np.uint8],
    u: NDArray[np.int64],
    v: NDArray[np.int64],
    radius: NDArray[np.int64],
    half_widths: NDArray[np.int32],
    x0: int,
    y0: int,
    x1: int,
    y1: int,
) -> None:
    """Set to 1 the pixels of ``out`` within [x0, x1) x [y0, y1) that the disc of each point
    (u, v) with its ``radius`` (at most the table's, ``disc_half_widths``) covers: one
    ``cv2.dilate`` per radius with the elliptic element, without the passes over the box.
    The elements are nested (a row's half width grows with the radius), so each centre pixel
    is drawn once, with the largest radius of the points on it (tens of thousands of hull
    samples land on a few thousand pixels)."""
    h, w = out.shape
    widest = np.full((h, w), -1, np.int8)
    for i in range(len(u)):
        r = radius[i]
        cu, cv = u[i], v[i]
        if cu + r < x0 or cu - r >= x1 or cv + r < y0 or cv - r >= y1:
            continue
        if 0 <= cu < w and 0 <= cv < h:
            if r > widest[cv, cu]:
                widest[cv, cu] = r
        else:  # a centre outside the image whose disc reaches into the box
            _draw_disc(out, cu, cv, r, half_widths, x0, y0, x1, y1)
    for i in range(len(u)):
        cu, cv = u[i], v[i]
        if 0 <= cu < w and 0 <= cv < h and widest[cv, cu] == radius[i]:
            widest[cv, cu] = -1  # drawn
            _draw_disc(out, cu, cv, radius[i], half_widths, x0, y0, x1, y1)


@nb.njit(nogil=True, cache=True)
def splat_min_discs(
    out: NDArray[np.float32],
    u: NDArray[np.int64],
    v: NDArray[np.int64],
    radius: NDArray[np.int64],
    values: NDArray[np.float32],
    half_widths: NDArray[np.int32],
) -> None:
    """Lower ``out`` to the smallest of ``values`` over the discs (as ``splat_discs``, the
    centres inside the image) that cover each pixel: ``cv2.erode`` of a layer holding each
    point's value, per radius (merging the points that share a pixel and a radius first,
    as ``splat_discs`` does, cost more than it saved: the values differ)."""
    h, w = out.shape
    rmax = (half_widths.shape[1] - 1) // 2
    for i in range(len(u)):
        r = radius[i]
        cu, cv = u[i], v[i]
        val = values[i]
        for dy in range(-r, r + 1):
            y = cv + dy
            if y < 0 or y >= h:
                continue
            hw = half_widths[r, dy + rmax]
            if hw < 0:
                continue
            for x in range(max(cu - hw, 0), min(cu + hw + 1, w)):
                if val < out[y, x]:
                    out[y, x] = val


@nb.njit(nogil=True, cache=True)
def gather_channels(
    image: NDArray[np.float32], u: NDArray[np.intp], v: NDArray[np.intp]
) -> NDArray[np.float32]:
    """(C, N) ``image[v, u].T`` of an (H, W, C) image, channel-first and contiguous, in one
    pass (NumPy's fancy index and transpose copy made two, holding the GIL)."""
    channels = image.shape[2]
    out = np.empty((channels, len(u)), np.float32)
    for i in range(len(u)):
        for k in range(channels):
            out[k, i] = image[v[i], u[i], k]
    return out


@nb.njit(nogil=True, cache=True)
def surface_normals(
    occ: NDArray[np.bool_], p: NDArray[np.int64], directions: NDArray[np.int64]
) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
    """Per voxel at grid cell ``p`` of the occupancy grid ``occ`` (padded: every neighbour
    is inside it), whether one of its ``directions`` (6, 3) neighbours is empty and its unit
    outward normal (the sum of the directions towards the empty ones, zero inside), in one
    pass; the arithmetic of the NumPy version (integer sums, a square root, a division), so
    the same normals."""
    m = p.shape[0]
    surface = np.zeros(m, np.bool_)
    normals = np.zeros((m, 3), np.float32)
    for i in range(m):
        x, y, z = 0.0, 0.0, 0.0
        for j in range(directions.shape[0]):
            a = p[i, 0] + directions[j, 0]
            b = p[i, 1] + directions[j, 1]
            c = p[i, 2] + directions[j, 2]
            if not occ[a, b, c]:
                surface[i] = True
                x += directions[j, 0]
                y += directions[j, 1]
                z += directions[j, 2]
        norm = np.sqrt(x * x + y * y + z * z)
        if norm > 0:
            d = max(norm, 1e-12)
            normals[i, 0] = x / d
            normals[i, 1] = y / d
            normals[i, 2] = z / d
    return surface, normals


@nb.njit(nogil=True, cache=True)
def outline_gaps(pts: NDArray[np.int32], owner: NDArray[np.int64], num: int) -> NDArray[np.float64]:
    """(num, num) smallest distance between the points ``pts`` (P, 2) of every two owners
    (``owner`` (P,), 0..num-1; every owner has a point): all pairs of points of different
    owners, squared distances in integers, one square root per pair of owners at the end,
    so the same numbers as a k-d tree's nearest-neighbour queries (the few thousand
    points of a mask's outlines: ~0.5 M pairs)."""
    big = np.iinfo(np.int64).max
    best = np.full((num, num), big, np.int64)
    n = pts.shape[0]
    for i in range(n):
        xi, yi, oi = np.int64(pts[i, 0]), np.int64(pts[i, 1]), owner[i]
        row = best[oi]
        for j in range(i + 1, n):
            oj = owner[j]
            if oj == oi:
                continue
            dx = xi - pts[j, 0]
            dy = yi - pts[j, 1]
            d2 = dx * dx + dy * dy
            if d2 < row[oj]:
                row[oj] = d2
    gaps = np.zeros((num, num))
    for a in range(num):
        for b in range(a + 1, num):
            d2 = min(best[a, b], best[b, a])
            gaps[a, b] = gaps[b, a] = np.sqrt(np.float64(d2))
    return gaps


@nb.njit(nogil=True, cache=True)
def disc_centres(
    uv: NDArray[np.float64], radius: NDArray[np.float64], width: int, height: int, max_radius: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The splats' integer discs of points at pixels ``uv`` (N, 2) (finite): the nearest
    pixel (rounded half to even, clipped into the image) and the radius rounded up, clipped
    to [0, ``max_radius``]; NumPy's ``clip(rint(.))`` / ``clip(ceil(.))`` in one pass."""
    n = uv.shape[0]
    u = np.empty(n, np.int64)
    v = np.empty(n, np.int64)
    r = np.empty(n, np.int64)
    for i in range(n):
        u[i] = int(min(max(np.rint(uv[i, 0]), 0.0), width - 1.0))
        v[i] = int(min(max(np.rint(uv[i, 1]), 0.0), height - 1.0))
        r[i] = int(min(max(np.ceil(radius[i]), 0.0), float(max_radius)))
    return u, v, r
