"""Where the foreground's depth is lost (issue 11): the per-view depth maps of the golden
foreground against the rendered depth of a synthetic dataset, by distance from the actors'
silhouettes, and how well a source camera can match an actor's inner pixels at all.

    python benchmarks/bench_depth_error.py /tmp/hd4 --tasks 62,96,224
    python benchmarks/bench_depth_error.py /tmp/hd4p --tasks 96 --background --json d.json

The golden foreground is ``bench_online.py``'s: ``pipeline.reconstruct_task`` at r = 1 with
all cameras and the masks of the stream's own models (one pass over the stream, no empty
clip unless the dataset has one). Each depth-map pixel is compared with the truth where its
ray meets the frame: back-projected through the view's pinhole camera and projected through
the rig camera's distortion (the views are undistorted; comparing pixel (u, v) of both
directly puts a radial offset into every depth). Rows:

* ``depth``: per task and camera, the depths on the moving actors (the actors seated from the
  first frame neither count nor cost): how many, their signed relative error (median, 25 / 75
  %; > 0 = behind the true surface) and the share off by more than 2 % of the median
  camera-to-scene distance, in bands of the distance (depth-map pixels) to the actor's
  silhouette;
* ``static`` (``--background``): the whole-frame golden depth (``pipeline.reconstruct``) on
  the static scene's pixels, the reference that the comparison itself is exact;
* ``match``: for ``--samples`` inner pixels of the moving actors in each camera (at least
  ``--inner-px`` from the silhouette at the view's scale), among those whose surface point
  the other camera sees (its true depth there agrees within 1 %), the NCC of a fronto-parallel
  window (``--window`` radius, the grey views at ``--scale``) with each other camera at the
  true depth and the best NCC within +-6 % of it, with where that best lies: a source whose
  best lies far from the truth with a clearly higher score cannot measure that surface.
  ``--surface`` puts each window pixel at its own true depth (moved along the rays by the
  same share): the window a perfectly slanted, surface-following match would compare.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from _report import print_rows, report_header, write_report
from edgerecon.geometry.camera import Camera
from edgerecon.io.dataset import open_dataset
from edgerecon.pipeline import reconstruct, reconstruct_task
from edgerecon.runtime.config import median_camera_distance
from edgerecon.scene.stream import bootstrap_scene
from edgerecon.synth import GroundTruth
from edgerecon.types import DepthMap, PointCloud
from edgerecon.views import prepare_views

#: Bands of the distance to the silhouette (depth-map pixels), (low, high].
BANDS = ((0.0, 2.0), (2.0, 4.0), (4.0, 8.0), (8.0, np.inf))
#: Relative depth offsets the ``match`` rows search around the truth.
OFFSETS = np.linspace(-0.06, 0.06, 121)


def truth_at(view_camera: Camera, rig_camera: Camera, truth: NDArray[Any]) -> NDArray[Any]:
    """``truth`` (an image of the rig camera's frames) at every pixel of a depth map made
    for ``view_camera`` (the rig camera undistorted and rescaled), nearest, through the
    rig camera's distortion (``Camera.undistort_maps``, as the views are made)."""
    scale = view_camera.width / rig_camera.width
    target = rig_camera.scaled(scale).undistorted()
    if target.size != view_camera.size or not np.allclose(target.K, view_camera.K, atol=1e-6):
        raise SystemExit(f"{rig_camera.name}: the depth map's camera is not a rescaled view")
    mx, my = rig_camera.undistort_maps(scale)
    return np.asarray(cv2.remap(truth, mx, my, cv2.INTER_NEAREST))


def error_row(
    depth: DepthMap, true_depth: DepthMap, where: NDArray[np.bool_], limit: float
) -> dict[str, Any]:
    """Count, signed relative error quantiles (%) and the share beyond ``limit`` (metres)
    of the depths at ``where``."""
    sel = where & (depth > 0) & (true_depth > 0)
    n = int(sel.sum())
    if n == 0:
        return {"n": 0}
    rel = (depth[sel] - true_depth[sel]) / true_depth[sel]
    q25, q50, q75 = np.quantile(rel, [0.25, 0.5, 0.75]) * 100.0
    off = np.abs(depth[sel] - true_depth[sel]) > limit
    return {
        "n": n,
        "median %": float(q50),
        "q25 %": float(q25),
        "q75 %": float(q75),
        "off > 2 %": float(off.mean()),
    }


def depth_rows(
    depth_maps: dict[int, DepthMap],
    depth_cameras: dict[int, Camera],
    ds: Any,
    gt: GroundTruth,
    t: int,
    seated: list[int],
    limit: float,
) -> list[dict[str, Any]]:
    rows = []
    for cid in sorted(depth_maps):
        dm = depth_maps[cid]
        cam = depth_cameras[cid]
        true_depth = truth_at(cam, ds.rig[cid], gt.depth(cid, t))
        labels = truth_at(cam, ds.rig[cid], gt.object_mask(cid, t))
        moving = (labels > 0) & ~np.isin(labels, seated)
        inside = cv2.distanceTransform(moving.astype(np.uint8), cv2.DIST_L2, 5)
        row: dict[str, Any] = {"task": t, "camera": ds.rig[cid].name}
        row.update(error_row(dm, true_depth, moving, limit))
        for lo, hi in BANDS:
            band = error_row(dm, true_depth, moving & (inside > lo) & (inside <= hi), limit)
            name = f"{lo:g}-{hi:g}px" if np.isfinite(hi) else f">{lo:g}px"
            row[f"{name} n"] = band["n"]
            row[f"{name} median %"] = band.get("median %")
            row[f"{name} off"] = band.get("off > 2 %")
        rows.append(row)
    return rows


def static_rows(
    frames: Any, ds: Any, gt: GroundTruth, t: int, limit: float
) -> list[dict[str, Any]]:
    dense = reconstruct(frames, ds.rig).dense
    rows = []
    if dense is None:
        return rows
    for cid in sorted(dense.depth_maps):
        cam = dense.depth_cameras[cid]
        true_depth = truth_at(cam, ds.rig[cid], gt.depth(cid, t))
        labels = truth_at(cam, ds.rig[cid], gt.object_mask(cid, t))
        row: dict[str, Any] = {"task": t, "camera": ds.rig[cid].name}
        row.update(error_row(dense.depth_maps[cid], true_depth, labels == 0, limit))
        rows.append(row)
    return rows


def _ncc_rows(a: NDArray[np.floating[Any]], b: NDArray[np.floating[Any]]) -> NDArray[np.float64]:
    """NCC of the window ``a`` (N,) with each row of ``b`` (O, N); -1 where a row is flat."""
    a = a - a.mean()
    b = b - b.mean(axis=1, keepdims=True)
    den = np.sqrt((a * a).sum() * (b * b).sum(axis=1))
    return np.where(den > 1e-6, (b @ a) / np.maximum(den, 1e-6), -1.0)


def match_rows(
    frames: Any,
    ds: Any,
    gt: GroundTruth,
    t: int,
    seated: list[int],
    args: argparse.Namespace,
) -> list[dict[str, Any]]:
    views = prepare_views(frames, ds.rig, args.scale)
    grey = {
        v.camera_id: cv2.cvtColor(v.image, cv2.COLOR_BGR2GRAY).astype(np.float32) for v in views
    }
    cams = {v.camera_id: v.camera for v in views}
    r = args.window
    du, dv = np.meshgrid(
        np.arange(-r, r + 1, dtype=np.float64), np.arange(-r, r + 1, dtype=np.float64)
    )
    rng = np.random.default_rng(0)
    rows = []
    for i, cam_i in cams.items():
        w, h = cam_i.size
        true_depth = truth_at(cam_i, ds.rig[i], gt.depth(i, t))
        labels = truth_at(cam_i, ds.rig[i], gt.object_mask(i, t))
        moving = (labels > 0) & ~np.isin(labels, seated)
        inside = cv2.distanceTransform(moving.astype(np.uint8), cv2.DIST_L2, 5)
        cand = np.argwhere(inside > args.inner_px * args.scale)
        if len(cand) == 0:
            continue
        pick = cand[rng.choice(len(cand), min(args.samples, len(cand)), replace=False)]
        centre = cam_i.backproject(
            pick[:, ::-1].astype(np.float64), true_depth[pick[:, 0], pick[:, 1]].astype(np.float64)
        )
        for j, cam_j in cams.items():
            if j == i:
                continue
            # Only the pixels whose surface point camera j sees (its true depth there agrees).
            uv_j, z_j = ds.rig[j].project(centre)
            depth_j = gt.depth(j, t)
            H, W = depth_j.shape
            xj = np.rint(uv_j[:, 0]).clip(0, W - 1).astype(np.int64)
            yj = np.rint(uv_j[:, 1]).clip(0, H - 1).astype(np.int64)
            seen = (
                (z_j > 0)
                & ds.rig[j].in_image(uv_j)
                & (np.abs(depth_j[yj, xj] - z_j) <= 0.01 * np.maximum(z_j, 1e-9))
            )
            found = []
            for y, x in pick[seen]:
                U = (x + du).ravel()
                V = (y + dv).ravel()
                if U.min() < 0 or V.min() < 0 or U.max() >= w or V.max() >= h:
                    continue
                a = grey[i][V.astype(np.int64), U.astype(np.int64)]
                if a.std() < 2.0:
                    continue
                if args.surface and not moving[V.astype(np.int64), U.astype(np.int64)].all():
                    continue
                z = true_depth[y, x] * (1.0 + OFFSETS)
                # All offsets of the window at once: (O * N, 3) points, on the plane at the
                # pixel's depth or (--surface) on the true surface moved along the rays.
                pix = np.tile(np.stack([U, V], 1), (len(z), 1))
                if args.surface:
                    zw = true_depth[V.astype(np.int64), U.astype(np.int64)].astype(np.float64)
                    zs = (zw[None, :] * (1.0 + OFFSETS)[:, None]).ravel()
                else:
                    zs = np.repeat(z, len(U))
                pts = cam_i.backproject(pix, zs)
                uv, zz = cam_j.project(pts)
                b = cv2.remap(
                    grey[j],
                    uv[:, 0].astype(np.float32)[:, None],
                    uv[:, 1].astype(np.float32)[:, None],
                    cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=-1.0,
                )[:, 0].reshape(len(z), len(U))
                ok = (zz.reshape(len(z), len(U)) > 0).all(axis=1) & (b >= 0).all(axis=1)
                scores = np.where(ok, _ncc_rows(a.astype(np.float64), b.astype(np.float64)), -1.0)
                mid = len(OFFSETS) // 2
                if scores[mid] <= -1.0:
                    continue
                found.append((scores[mid], scores.max(), OFFSETS[int(scores.argmax())]))
            if not found:
                continue
            arr = np.array(found)
            rows.append(
                {
                    "task": t,
                    "ref": ds.rig[i].name,
                    "source": ds.rig[j].name,
                    "pixels": len(arr),
                    "NCC at truth": float(np.median(arr[:, 0])),
                    "best NCC": float(np.median(arr[:, 1])),
                    "truth >= 0.7": float((arr[:, 0] >= 0.7).mean()),
                    "best within 1 %": float((np.abs(arr[:, 2]) <= 0.01).mean()),
                    "best offset q25 %": float(np.quantile(arr[:, 2], 0.25) * 100),
                    "best offset q75 %": float(np.quantile(arr[:, 2], 0.75) * 100),
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="a synthetic dataset folder (edgerecon synth) with truth")
    ap.add_argument("--tasks", default="62,96,224", help="comma-separated time indices")
    ap.add_argument("--background", action="store_true", help="also the static scene's rows")
    ap.add_argument("--no-match", action="store_true", help="skip the match rows")
    ap.add_argument("--samples", type=int, default=300, help="match: inner pixels per camera")
    ap.add_argument("--inner-px", type=float, default=8.0, help="match: px from the silhouette")
    ap.add_argument("--window", type=int, default=2, help="match: window radius (pixels)")
    ap.add_argument("--scale", type=float, default=0.5, help="match: view scale")
    ap.add_argument(
        "--surface",
        action="store_true",
        help="match: windows on the true surface (each pixel at its true depth), not a plane",
    )
    ap.add_argument("--json", default=None, help="write the results to this file")
    args = ap.parse_args()

    root = Path(args.dataset)
    ds = open_dataset(root)
    gt = GroundTruth.open(root)
    seated = gt.seated_from_start
    limit = 0.02 * median_camera_distance(ds.rig)
    tasks = sorted(int(x) for x in args.tasks.split(","))
    depth: list[dict[str, Any]] = []
    static: list[dict[str, Any]] = []
    match: list[dict[str, Any]] = []
    clip = ds.open_background()
    with ds.open_frames() as source:
        tracker = bootstrap_scene(ds.rig, source, ds.fps, clip=clip)
        for t in tasks:
            tracker.catch_up(source, t)
            frames = source.read(t)
            fg = tracker.segment(frames)
            rec = reconstruct_task(frames, ds.rig, fg, background=PointCloud.empty())
            dense = rec.foreground.dense
            if dense is not None:
                depth += depth_rows(dense.depth_maps, dense.depth_cameras, ds, gt, t, seated, limit)
            if args.background:
                static += static_rows(frames, ds, gt, t, limit)
            if not args.no_match:
                match += match_rows(frames, ds, gt, t, seated, args)
            print(f"task {t} done", flush=True)
    if clip is not None:
        clip.close()
    bands = [f"{lo:g}-{hi:g}px" if np.isfinite(hi) else f">{lo:g}px" for lo, hi in BANDS]
    print_rows(
        f"golden foreground depth maps vs truth, moving actors (limit {limit * 100:.1f} cm)",
        ["task", "camera", "n", "median %", "q25 %", "q75 %", "off > 2 %"],
        depth,
    )
    print_rows(
        "... by distance to the silhouette: median signed error % / share off",
        ["task", "camera"] + [f"{b} {k}" for b in bands for k in ("median %", "off")],
        depth,
    )
    if static:
        print_rows(
            "whole-frame golden depth maps vs truth, static scene",
            ["task", "camera", "n", "median %", "q25 %", "q75 %", "off > 2 %"],
            static,
        )
    if match:
        print_rows(
            f"matching an actor's inner pixels (window {2 * args.window + 1} px at scale "
            f"{args.scale:g}, {'on the true surface' if args.surface else 'fronto-parallel'})",
            [
                "task", "ref", "source", "pixels", "NCC at truth", "best NCC", "truth >= 0.7",
                "best within 1 %", "best offset q25 %", "best offset q75 %",
            ],
            match,
        )  # fmt: skip
    if args.json:
        write_report(
            args.json,
            {
                **report_header(),
                "dataset": str(root),
                "tasks": tasks,
                "limit_m": limit,
                "depth": depth,
                "static": static,
                "match": match,
            },
        )


if __name__ == "__main__":
    main()
