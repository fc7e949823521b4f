"""Scene-stage benchmark: foreground-mask quality, object counts, visual-hull accuracy and
per-stage seconds, on synthetic scenes with exact ground truth (and, when present, on
utrecht4cam).

    python benchmarks/bench_scene.py                                   # demo + ring + arc7
    python benchmarks/bench_scene.py --presets demo --seeds 0 1 2 --frames 30
    python benchmarks/bench_scene.py --baselines                       # + OpenCV MOG2 / KNN
    python benchmarks/bench_scene.py --utrecht --time 200              # real data only
    python benchmarks/bench_scene.py --json scene.json
    python benchmarks/bench_scene.py --online hd4 --tasks 0:240:6      # online, no empty clip
    python benchmarks/bench_scene.py --online work/hd4p --json hd4p.json

Per preset and seed the background models learn from the scene's background-only clip, then
segment ``--frames`` timestamps. Reported:

* IoU: foreground-mask IoU against the ground-truth object masks (summed intersections over
  summed unions of all cameras and timestamps); "model" = background model alone, "final" =
  after the visual-hull consistency; MOG2 / KNN = OpenCV's subtractors (``--baselines``) fed
  the same frames, their masks cleaned the same way.
* objects/img: share of images whose object count equals the number of separated actors
  (ground-truth actors whose masks are farther apart than the object clustering's fragment
  gap, 1.5 % of the image diagonal, count separately; actors covering < 0.02 % of the image
  are ignored).
* objects/task: share of timestamps whose number of 3D hull objects equals the number of
  separated actors on the floor (actors closer than ``--contact`` m are one group).
* hull: the hull surface cloud against the ground-truth foreground cloud (precision,
  recall at ``d``), and the share of ground-truth foreground pixels whose true depth lies in
  the hull's per-pixel [near, far] range (what the dense stage would search).
* ms/cam: milliseconds per camera-frame of background subtraction, and per frame of the hull
  and the objects.

``--online DATASET_OR_PRESET`` runs the scene stage as the online system does (no empty-scene
clip needed): the background models follow the one stream definition of
``edgerecon.scene.stream`` (bootstrap from the clip or the stream's first second, then the
scheduled updates before each task), then every task of ``--tasks A:B:STEP`` is segmented in
order and scored against
the ground-truth object masks of all cameras: per time, the foreground IoU and per actor the
IoU of the predicted object matched to it (Hungarian on IoU, per image; 0 when no object
matches) and its recall (share of its pixels called foreground, whatever the object). The
summary gives mean / min over the tasks, over the stretches gt/scene.json records (an actor
standing still, one away, the dimming), and the seconds of the scene stage per task. A preset
name is written once under ``--work`` (at ``--size`` if given) and reused.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from _report import print_rows, report_header, with_settings
from edgerecon.quality import evaluate_clouds
from edgerecon.quality.masks import at_resolution
from edgerecon.scene import (
    BackgroundConfig,
    ForegroundConfig,
    HullConfig,
    RigForeground,
    clean_mask,
    hull_cloud,
    hull_depth_range,
)
from edgerecon.scene.ghosts import StaticCheckConfig
from edgerecon.types import FrameSet

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"

#: Presets at the resolution the benchmark renders them (full arc7 is 7 x 1920x1080).
PRESET_SIZES = {"demo": {}, "ring": {"width": 640, "height": 360}, "arc7": {}}


def separated_groups(labels: np.ndarray, gap_px: float, min_px: int) -> int:
    """Number of groups of ground-truth actors whose masks are closer than ``gap_px``."""
    ids = [k for k in np.unique(labels) if k > 0 and np.count_nonzero(labels == k) >= min_px]
    if not ids:
        return 0
    r = int(np.ceil(gap_px / 2))
    fg = np.isin(labels, ids).astype(np.uint8)
    grown = cv2.dilate(fg, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    _, comp = cv2.connectedComponents(grown)
    return len({int(np.bincount(comp[labels == k]).argmax()) for k in ids})


def floor_groups(positions: list[np.ndarray], contact_m: float) -> int:
    """Groups of actors (floor positions) closer than ``contact_m`` to each other."""
    n = len(positions)
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            if np.linalg.norm(positions[i] - positions[j]) < contact_m:
                parent[find(i)] = find(j)
    return len({find(i) for i in range(n)})


def run_preset(
    preset: str, seed: int, frames: int, config: ForegroundConfig, args: argparse.Namespace
) -> dict[str, Any]:
    from edgerecon.synth import Renderer, build_scene, preset_config, sample_visible_cloud

    overrides = dict(PRESET_SIZES.get(preset, {}))
    if args.size:
        w, h = (int(x) for x in args.size.lower().split("x"))
        overrides.update(width=w, height=h)
    scene = build_scene(preset_config(preset, seed=seed, num_frames=frames, **overrides))
    renderer = Renderer(scene)
    rig = scene.rig
    bg_frames = [renderer.render(t) for t in range(-scene.config.background_frames, 0)]
    fg = RigForeground.learn_from_framesets(
        rig, [FrameSet(time_index=f.time_index, images=f.images) for f in bg_frames], config
    )
    if args.occluders:
        # Ground-truth depth of the static scene (what the background cloud would give).
        fg.set_occluders([renderer.background_depth(i) for i in range(len(rig))])
    baselines: dict[str, list[Any]] = {}
    if args.baselines:
        for name, make in (
            ("MOG2", lambda: cv2.createBackgroundSubtractorMOG2(detectShadows=True)),
            ("KNN", lambda: cv2.createBackgroundSubtractorKNN(detectShadows=True)),
        ):
            subs = [make() for _ in rig]
            for f in bg_frames:
                for s, im in zip(subs, f.images, strict=True):
                    s.apply(im)
            baselines[name] = subs
    inter = {"model": 0, "final": 0, **{k: 0 for k in baselines}}
    union = dict.fromkeys(inter, 0)
    img_ok: list[bool] = []
    task_ok: list[bool] = []
    seconds = {"background": 0.0, "hull": 0.0, "objects": 0.0}
    hull_scores = []
    depth_cover = []
    cleaning = config.background.mask
    for t in range(frames):
        frame = renderer.render(t)
        fs = FrameSet(time_index=t, images=frame.images)
        res = fg.segment(fs)
        seconds["background"] += res.timings.seconds.get("background_subtraction", 0.0)
        seconds["hull"] += res.timings.seconds.get("visual_hull", 0.0) + res.timings.seconds.get(
            "hull_consistency", 0.0
        )
        seconds["objects"] += res.timings.seconds.get("objects", 0.0)
        for c, cam in enumerate(rig):
            gt = frame.masks[c] > 0
            for key, low in (("model", res.model_masks[c]), ("final", res.masks[c])):
                pred = at_resolution(low, gt.shape)  # working resolution -> the frame's
                inter[key] += int(np.count_nonzero(pred & gt))
                union[key] += int(np.count_nonzero(pred | gt))
            for name, subs in baselines.items():
                raw = subs[c].apply(frame.images[c]) == 255
                pred = clean_mask(raw, cleaning)
                inter[name] += int(np.count_nonzero(pred & gt))
                union[name] += int(np.count_nonzero(pred | gt))
            diag = float(np.hypot(cam.width, cam.height))
            expected = separated_groups(
                frame.masks[c],
                config.objects.merge_gap_fraction * diag,
                int(2e-4 * cam.width * cam.height),
            )
            img_ok.append(res.objects[c].num_objects == expected)  # type: ignore[union-attr]
        positions = [a.position(t)[:2] for a in scene.actors_at(t)]
        hull = res.hull
        n_hull = 0 if hull is None else hull.num_objects
        task_ok.append(n_hull == floor_groups(positions, args.contact))
        if hull is not None and hull.num_voxels and t % args.hull_every == 0:
            cloud = hull_cloud(hull, rig.cameras, frame.images)
            ref = sample_visible_cloud(
                rig,
                [renderer.rays(i) for i in range(len(rig))],
                frame.depths,
                frame.masks,
                None,
                voxel_m=0.005,
                part="foreground",
            )
            # Against the surfaces >= 2 cameras see (a hull cannot know the rest).
            seen = ref.attributes["num_views"] >= 2
            score = evaluate_clouds(cloud, ref.points3D[seen], [args.d])[0]
            hull_scores.append((score.precision, score.recall, score.fscore))
            for c, cam in enumerate(rig):
                dr = hull_depth_range(hull, cam)
                m = frame.masks[c] > 0
                d = frame.depths[c][m]
                ok = (dr.near[m] <= d) & (d <= dr.far[m])
                depth_cover.append((int(ok.sum()), int(m.sum())))
    n_img = frames * len(rig)
    out = {
        "preset": preset,
        "seed": seed,
        "cameras": len(rig),
        "size": f"{rig[0].width}x{rig[0].height}",
        "frames": frames,
        "iou": {k: inter[k] / max(union[k], 1) for k in inter},
        "objects_per_image": float(np.mean(img_ok)),
        "objects_per_task": float(np.mean(task_ok)),
        "ms_per_camera_frame": 1000 * seconds["background"] / n_img,
        "ms_hull_per_frame": 1000 * seconds["hull"] / frames,
        "ms_objects_per_frame": 1000 * seconds["objects"] / frames,
    }
    if hull_scores:
        p, r, f = np.mean(hull_scores, axis=0)
        out["hull_vs_gt"] = {"d": args.d, "precision": p, "recall": r, "fscore": f}
    if depth_cover:
        hit, tot = np.sum(depth_cover, axis=0)
        out["depth_range_coverage"] = hit / max(tot, 1)
    return out


def run_utrecht(t: int, config: ForegroundConfig, dense: str | None) -> dict[str, Any]:
    from edgerecon.io.dataset import open_dataset
    from edgerecon.scene.stream import dataset_scene_at

    ds = open_dataset(SHARED / "utrecht4cam")
    t0 = time.perf_counter()
    tracker = dataset_scene_at(ds, t, config)
    learn_s = time.perf_counter() - t0
    with ds.open_frames() as src:
        frames = src.read(t)
    res = tracker.segment(frames)
    out: dict[str, Any] = {
        "time": t,
        "learn_s": learn_s,
        "area_fraction": res.areas(),
        "model_area_fraction": [
            float(m.mean()) if m is not None else None for m in res.model_masks
        ],
        "objects": res.num_objects(),
        "hull_objects": None if res.hull is None else res.hull.num_objects,
        "timings": res.timings.to_dict(),
    }
    if dense:
        from edgerecon.io.ply import read_ply

        cloud = read_ply(dense)
        pts = cloud.points3D
        if cloud.labels is not None and (cloud.labels > 0).any():
            pts = pts[cloud.labels > 0]
        out["silhouette_consistency"] = silhouette_consistency(pts, ds.rig, res.masks)
    return out


def silhouette_consistency(points3D: np.ndarray, rig: Any, masks: Any, tol_px: int = 2) -> float:
    """Share of points that project inside the (dilated by ``tol_px``) foreground of every
    camera whose image they fall in."""
    ok = np.ones(len(points3D), bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tol_px + 1,) * 2)
    for cam, m in zip(rig, masks, strict=True):
        if m is None:
            continue
        grown = at_resolution(
            cv2.dilate(m.astype(np.uint8), k).astype(bool), (cam.height, cam.width)
        )
        uv, depth = cam.project(points3D)
        inside = (depth > 0) & cam.in_image(uv)
        u = np.rint(uv[inside, 0]).astype(int).clip(0, cam.width - 1)
        v = np.rint(uv[inside, 1]).astype(int).clip(0, cam.height - 1)
        ok[np.flatnonzero(inside)[~grown[v, u]]] = False
    return float(ok.mean()) if len(ok) else float("nan")


def online_dataset(spec: str, args: argparse.Namespace) -> Path:
    """The dataset folder ``spec``, or the preset ``spec`` written (once) under ``--work``."""
    from edgerecon.synth import PRESETS, preset_config, write_dataset

    path = Path(spec)
    if (path / "dataset.json").is_file():
        return path
    if spec not in PRESETS:
        raise SystemExit(f"--online: {spec!r} is neither a dataset folder nor a preset")
    overrides: dict[str, Any] = {"seed": args.seeds[0]}
    if args.size:
        w, h = (int(x) for x in args.size.lower().split("x"))
        overrides.update(width=w, height=h)
    config = preset_config(spec, **overrides)
    out = Path(args.work) / f"{spec}-{config.rig.width}x{config.rig.height}-seed{args.seeds[0]}"
    if not (out / "dataset.json").is_file():
        print(f"writing {spec} to {out} (once)", flush=True)
        write_dataset(config, out, overwrite=True)
    return out


def _like(pred: np.ndarray | None, truth: np.ndarray) -> np.ndarray:
    """A predicted mask or label image at the ground truth's resolution (nearest keeps the
    ids; a missing camera predicts nothing)."""
    if pred is None:
        return np.zeros(truth.shape, np.int32)
    if pred.shape != truth.shape:
        src = pred.astype(np.uint8) if pred.dtype == bool else pred
        pred = cv2.resize(src, truth.shape[::-1], interpolation=cv2.INTER_NEAREST)
    return pred


def _with_settings(config: ForegroundConfig, items: list[str]) -> ForegroundConfig:
    """``config`` with ``--set`` settings on top, read as the ``[runtime.foreground]`` table of
    a ``--config`` file would be (``configfile.build``: TOML values, the same checks)."""
    return with_settings(config, items, "runtime.foreground")


def _moving_iou(truth: list[np.ndarray], preds: list[np.ndarray], seated: list[int]) -> float:
    """Foreground IoU over all cameras, the pixels of actors seated from the first frame
    neither counting nor costing."""
    inter = union = 0
    for m, p in zip(truth, preds, strict=True):
        care = ~np.isin(m, seated)
        inter += int(np.count_nonzero((m > 0) & (p > 0) & care))
        union += int(np.count_nonzero(((m > 0) | (p > 0)) & care))
    return inter / union if union else 1.0


def run_online(spec: str, config: ForegroundConfig, args: argparse.Namespace) -> dict[str, Any]:
    from edgerecon.io.dataset import open_dataset
    from edgerecon.quality.masks import at_resolution, score_mask_set
    from edgerecon.runtime.session import FrameRange
    from edgerecon.scene.stream import bootstrap_scene
    from edgerecon.synth import GroundTruth

    path = online_dataset(spec, args)
    ds = open_dataset(path)
    gt = GroundTruth.open(path)
    rig = ds.rig
    t_learn = time.perf_counter()
    clip = ds.open_background()
    with ds.open_frames() as source:
        tracker = bootstrap_scene(rig, source, ds.fps, config, clip=clip)
    learn_s = time.perf_counter() - t_learn
    tasks = FrameRange.parse(args.tasks).indices(ds.num_frames) if args.tasks else None
    if tasks is None:
        step = max(1, ds.num_frames // 40)
        tasks = list(range(0, ds.num_frames, step))[:40]
    ids = gt.actor_ids
    # "moving IoU" scores the actors other than those seated from the first frame (their
    # pixels neither count nor cost).
    seated = gt.seated_from_start
    rows: list[dict[str, Any]] = []
    with ds.open_frames() as source:
        for t in tasks:
            # The scheduled background updates before t (as the online system applies them).
            update_s = tracker.catch_up(source, t)
            frames = source.read(t)
            t0, c0 = time.perf_counter(), time.process_time()
            res = tracker.segment(frames)
            seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
            truth = [gt.object_mask(c, t) for c in range(len(rig))]
            preds = [_like(lab, m) for lab, m in zip(res.label_images(), truth, strict=True)]
            score = score_mask_set(preds, truth)
            before_hull = [_like(p, m) for p, m in zip(res.model_masks, truth, strict=True)]
            model_iou = score_mask_set(before_hull, truth).foreground_iou
            # The foreground masks as the dense stage gets them (``views.with_masks``:
            # bilinear, 0.5 threshold); the label images by nearest (their object ids).
            smooth = [
                np.zeros(m.shape, bool) if f is None else at_resolution(f, m.shape)
                for f, m in zip(res.masks, truth, strict=True)
            ]
            moving_iou = _moving_iou(truth, preds, seated)
            moving_iou_smooth = _moving_iou(truth, smooth, seated)
            recall: dict[int, float] = {}
            for k in ids:
                area = sum(int(np.count_nonzero(m == k)) for m in truth)
                if area:
                    hit = sum(
                        int(np.count_nonzero((m == k) & (p > 0)))
                        for m, p in zip(truth, preds, strict=True)
                    )
                    recall[k] = hit / area
            rows.append(
                {
                    "time": t,
                    "light": gt.illumination(t),
                    "foreground_iou": score.foreground_iou,
                    "model_iou": model_iou,
                    "moving_iou": moving_iou,
                    "moving_iou_smooth": moving_iou_smooth,
                    "precision": score.precision,
                    "recall": score.recall,
                    "object_iou": {k: score.object_iou[k] for k in ids if k in score.object_iou},
                    "object_recall": recall,
                    "seconds": seconds,
                    "update_seconds": update_s,
                    "cpu_seconds": cpu,
                }
            )
    selections: list[tuple[str, set[int]]] = [("all tasks", set(tasks))]
    for kind in ("still", "away", "dimming"):
        for item in gt.stretches[kind]:
            who = f" actor {item['actor']}" if "actor" in item else ""
            frames_in = set(range(item["start"], item["stop"]))
            selections.append((f"{kind}{who} {item['start']}..{item['stop'] - 1}", frames_in))
    summary = []
    for name, frames_in in selections:
        sel = [r for r in rows if r["time"] in frames_in]
        if not sel:
            continue
        entry: dict[str, Any] = {
            "stretch": name,
            "tasks": len(sel),
            "foreground_iou_mean": float(np.mean([r["foreground_iou"] for r in sel])),
            "model_iou_mean": float(np.mean([r["model_iou"] for r in sel])),
            "moving_iou_mean": float(np.mean([r["moving_iou"] for r in sel])),
            "moving_iou_smooth_mean": float(np.mean([r["moving_iou_smooth"] for r in sel])),
            "precision_mean": float(np.mean([r["precision"] for r in sel])),
            "recall_mean": float(np.mean([r["recall"] for r in sel])),
            "seconds_mean": float(np.mean([r["seconds"] for r in sel])),
            "cpu_seconds_mean": float(np.mean([r["cpu_seconds"] for r in sel])),
        }
        for k in ids:
            ious = [r["object_iou"][k] for r in sel if k in r["object_iou"]]
            recs = [r["object_recall"][k] for r in sel if k in r["object_recall"]]
            entry[f"iou_{k}_mean"] = float(np.mean(ious)) if ious else None
            entry[f"iou_{k}_min"] = float(np.min(ious)) if ious else None
            entry[f"recall_{k}_mean"] = float(np.mean(recs)) if recs else None
        summary.append(entry)
    cam = rig[0]
    return {
        **report_header(),
        "dataset": str(path),
        "name": ds.name,
        "size": f"{cam.width}x{cam.height}",
        "cameras": len(rig),
        "learned_from": tracker.learned_from,
        "learn_s": learn_s,
        "updates": tracker.updates,
        "ghosts_repaired": tracker.ghosts,
        "seated_from_start": seated,
        "tasks": tasks,
        "stretches": gt.stretches,
        "rows": rows,
        "summary": summary,
    }


def print_online(r: dict[str, Any]) -> None:
    ids = sorted({int(k) for row in r["rows"] for k in (*row["object_iou"], *row["object_recall"])})
    print(
        f"{r['name']} {r['cameras']} x {r['size']}, background learned from {r['learned_from']} "
        f"in {r['learn_s']:.1f} s (load {r['load_avg']:.1f})"
    )
    per_object = [f"IoU {k}" for k in ids] + [f"rec {k}" for k in ids]
    rows = [
        {
            "t": row["time"],
            "light": row["light"],
            "fg IoU": row["foreground_iou"],
            "model": row["model_iou"],
            "moving": row["moving_iou"],
            "moving sm": row["moving_iou_smooth"],
            **{f"IoU {k}": row["object_iou"].get(k) for k in ids},
            **{f"rec {k}": row["object_recall"].get(k) for k in ids},
            "prec": row["precision"],
            "s/task": row["seconds"],
            "CPU s": row["cpu_seconds"],
        }
        for row in r["rows"]
    ]
    columns = [
        "t",
        "light",
        "fg IoU",
        "model",
        "moving",
        "moving sm",
        "prec",
        *per_object,
        "s/task",
        "CPU s",
    ]
    print_rows("per task", columns, rows)
    stats = [f"IoU {k} {m}" for k in ids for m in ("mean", "min")] + [f"rec {k}" for k in ids]
    rows = [
        {
            "stretch": e["stretch"],
            "tasks": e["tasks"],
            "fg IoU": e["foreground_iou_mean"],
            "model": e["model_iou_mean"],
            "moving": e["moving_iou_mean"],
            "moving sm": e["moving_iou_smooth_mean"],
            **{f"IoU {k} {m}": e[f"iou_{k}_{m}"] for k in ids for m in ("mean", "min")},
            **{f"rec {k}": e[f"recall_{k}_mean"] for k in ids},
            "prec": e["precision_mean"],
            "rec": e["recall_mean"],
            "s/task": e["seconds_mean"],
            "CPU s": e["cpu_seconds_mean"],
        }
        for e in r["summary"]
    ]
    print_rows(
        "summary (means over tasks)",
        [
            "stretch",
            "tasks",
            "fg IoU",
            "model",
            "moving",
            "moving sm",
            "prec",
            "rec",
            *stats,
            "s/task",
            "CPU s",
        ],
        rows,
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--presets", nargs="*", default=["demo", "ring", "arc7"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1])
    ap.add_argument("--frames", type=int, default=20, help="timestamps per scene")
    ap.add_argument("--size", default=None, help="render at WxH instead of the preset's size")
    ap.add_argument("--baselines", action="store_true", help="also score OpenCV MOG2 and KNN")
    ap.add_argument("--max-missing", type=int, default=0, help="hull: cameras allowed to disagree")
    ap.add_argument("--no-hull", action="store_true", help="no hull consistency")
    ap.add_argument("--no-hull-fill", action="store_true", help="no hole filling from the hull")
    ap.add_argument(
        "--static-every-s",
        type=float,
        default=StaticCheckConfig().every_s,
        help="stream seconds between two static scenes",
    )
    ap.add_argument(
        "--static-keep",
        type=int,
        default=StaticCheckConfig().keep,
        help="how many of the latest static scenes make the static depth",
    )
    ap.add_argument(
        "--static-check",
        action="store_true",
        help="check the ghosts against the stream's static scene (off by default)",
    )
    ap.add_argument(
        "--no-hull-rescue",
        action="store_true",
        help="no objects brought back from one camera's veto",
    )
    ap.add_argument("--threshold-sigma", type=float, default=None)
    ap.add_argument("--min-abs-diff", type=float, default=None)
    ap.add_argument(
        "--occluders", action="store_true", help="hull knows the static scene's depth (GT)"
    )
    ap.add_argument("--contact", type=float, default=0.6, help="actors closer (m) are one group")
    ap.add_argument("--d", type=float, default=0.03, help="hull cloud score threshold (m)")
    ap.add_argument("--hull-every", type=int, default=5, help="score the hull every N frames")
    ap.add_argument("--utrecht", action="store_true", help="utrecht4cam only")
    ap.add_argument("--time", type=int, default=200, help="utrecht4cam frame")
    ap.add_argument("--dense", default=None, help="utrecht4cam dense PLY for the silhouette figure")
    ap.add_argument(
        "--online", default=None, help="dataset folder or preset: the online scene stage vs truth"
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a ForegroundConfig setting, dotted for nested ones (background.ghost_min_matches=1)",
    )
    ap.add_argument("--tasks", default=None, help="--online: timestamps A:B:STEP (default 40)")
    ap.add_argument(
        "--work", default="/tmp/edgerecon-bench", help="--online: where presets are written"
    )
    ap.add_argument("--json", default=None, help="write the results to this file")
    args = ap.parse_args()

    bg = BackgroundConfig()
    if args.threshold_sigma is not None:
        bg = dataclasses.replace(bg, threshold_sigma=args.threshold_sigma)
    if args.min_abs_diff is not None:
        bg = dataclasses.replace(bg, min_abs_diff=args.min_abs_diff)
    config = ForegroundConfig(
        background=bg,
        hull=HullConfig(max_missing=args.max_missing),
        hull_consistency=not args.no_hull,
        hull_fill=not args.no_hull_fill,
        hull_rescue=not args.no_hull_rescue,
        static_check=args.static_check,
        static=StaticCheckConfig(every_s=args.static_every_s, keep=args.static_keep),
    )
    config = _with_settings(config, args.set)
    results: list[dict[str, Any]] = []
    if args.utrecht:
        r = run_utrecht(args.time, config, args.dense)
        print(json.dumps(r, indent=2))
        results.append(r)
    elif args.online:
        r = run_online(args.online, config, args)
        print_online(r)
        results.append(r)
    else:
        header = (
            f"{'preset':8} {'seed':>4} {'size':>10} {'IoU final':>9} {'model':>6} "
            + ("  MOG2   KNN " if args.baselines else "")
            + f"{'obj/img':>8} {'obj/task':>8} {'hull P':>7} {'hull R':>7} {'d-cover':>7} "
            f"{'ms/cam':>7} {'ms hull':>8} {'ms obj':>7}"
        )
        print(header)
        for preset in args.presets:
            for seed in args.seeds:
                r = run_preset(preset, seed, args.frames, config, args)
                results.append(r)
                iou = r["iou"]
                hv = r.get("hull_vs_gt", {})
                print(
                    f"{preset:8} {seed:4d} {r['size']:>10} {iou['final']:9.3f} {iou['model']:6.3f} "
                    + (f"{iou['MOG2']:6.3f} {iou['KNN']:5.3f} " if args.baselines else "")
                    + f"{r['objects_per_image']:8.2f} {r['objects_per_task']:8.2f} "
                    f"{hv.get('precision', float('nan')):7.3f} {hv.get('recall', float('nan')):7.3f} "
                    f"{r.get('depth_range_coverage', float('nan')):7.3f} "
                    f"{r['ms_per_camera_frame']:7.1f} {r['ms_hull_per_frame']:8.1f} "
                    f"{r['ms_objects_per_frame']:7.1f}",
                    flush=True,
                )
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float) + "\n")


if __name__ == "__main__":
    main()
