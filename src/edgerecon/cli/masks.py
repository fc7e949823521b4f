"""``edgerecon masks``: foreground masks, objects and visual hull of one timestamp, for
inspection.

The background models are the ones the online system has at time T (one definition for
every command: :mod:`edgerecon.scene.stream`). Segments frame T and writes per camera
``<cam>_mask.png`` (0/255, upsampled from the working resolution to the frame's),
``<cam>_overlay.png`` (the frame with the objects tinted, the background model's foreground
that the later steps removed in red and the foreground they added in yellow: the hull
consistency and fill, the ghost checks, the outline refinement; object ROIs boxed; the
table and ``masks.json`` count the hull's and the refinement's pixels apart) and
``masks.json``; with ``--hull-ply`` also the coloured visual-hull surface (``hull.ply``).
Synthetic datasets with ground truth also get the mask IoU per camera.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table, to_json
from edgerecon.cli._config import add_config_flag, load_config
from edgerecon.configfile import build, section
from edgerecon.io.dataset import Dataset, open_dataset
from edgerecon.io.ply import atomic_write_bytes, atomic_write_text, ply_frame, write_ply
from edgerecon.quality.masks import at_resolution
from edgerecon.scene.foreground import ForegroundConfig, ForegroundResult
from edgerecon.scene.hull import hull_cloud
from edgerecon.scene.stream import dataset_scene_at
from edgerecon.types import DataError, FrameSet, Image

#: Object colours in overlays (BGR).
_PALETTE = [(0, 200, 0), (255, 140, 0), (200, 0, 200), (0, 200, 255), (255, 255, 0), (120, 60, 255)]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "masks",
        help="save the foreground masks and objects of one timestamp",
        description="Background subtraction, visual-hull consistency and object clustering for "
        "one timestamp; writes <camera>_mask.png, <camera>_overlay.png and masks.json to --out "
        "and prints mask areas and object counts.",
    )
    p.add_argument("--dataset", required=True, metavar="DIR", help="dataset folder")
    p.add_argument("--time", "-t", type=int, default=0, help="frame index (default 0)")
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--no-hull", action="store_true", help="skip the visual-hull consistency of the masks"
    )
    p.add_argument("--hull-ply", action="store_true", help="also write the visual hull (hull.ply)")
    add_config_flag(p)
    add_json_flag(p)
    p.set_defaults(func=run)


def overlay(image: Image, result: ForegroundResult, camera_id: int) -> Image:
    """The frame with its objects tinted, the model's foreground the later steps removed in
    red, the foreground they added in yellow (hull steps, ghost checks, outline refinement),
    ROIs boxed."""
    out = image.copy()
    seg = result.objects[camera_id]
    model = result.model_masks[camera_id]
    final = result.masks[camera_id]
    if seg is None or model is None or final is None:
        return out
    # Masks are at the scene stage's working resolution; the overlay is at the frame's.
    shape = image.shape[:2]
    rejected = at_resolution(model & ~final, shape)
    out[rejected] = (0.4 * out[rejected] + (0, 0, 150)).astype(np.uint8)
    labels = at_resolution(seg.labels, shape)
    sx, sy = shape[1] / seg.labels.shape[1], shape[0] / seg.labels.shape[0]
    for obj in seg.objects:
        color = np.array(_PALETTE[(obj.id - 1) % len(_PALETTE)], np.float64)
        sel = labels == obj.id
        out[sel] = (0.5 * out[sel] + 0.5 * color).astype(np.uint8)
        x0, y0, w0, h0 = obj.roi
        x, y, w, h = round(x0 * sx), round(y0 * sy), round(w0 * sx), round(h0 * sy)
        cv2.rectangle(out, (x, y), (x + w - 1, y + h - 1), tuple(int(c) for c in color), 1)
        cv2.putText(
            out, str(obj.id), (x + 2, y + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1
        )
    filled = at_resolution(final & ~model, shape)
    out[filled] = (0.4 * out[filled] + (0, 150, 150)).astype(np.uint8)
    return out


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise DataError(f"cannot encode {path.name}")
    atomic_write_bytes(path, lambda f: f.write(buf.tobytes()))


def _ground_truth_scores(dataset: Dataset, result: ForegroundResult) -> list[float | None] | None:
    if dataset.ground_truth is None:
        return None
    from edgerecon.quality.masks import mask_iou
    from edgerecon.synth.groundtruth import GroundTruth

    gt = GroundTruth.open(dataset.root)
    scores: list[float | None] = []
    for cam, mask in zip(dataset.rig, result.masks, strict=True):
        if mask is None:
            scores.append(None)
            continue
        truth = gt.object_mask(cam.name, result.time_index)
        scores.append(mask_iou(at_resolution(mask, truth.shape), truth))
    return scores


def run(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.dataset)
    if not 0 <= args.time < dataset.num_frames:
        raise DataError(
            f"--time {args.time} is outside the dataset's frames 0..{dataset.num_frames - 1}"
        )
    rig = dataset.rig
    # The scene model's settings are the online system's: [runtime.foreground] of --config.
    config = build(
        ForegroundConfig,
        section(load_config(args), "runtime", "foreground"),
        where="runtime.foreground",
        overrides={"hull_consistency": False} if args.no_hull else None,
    )
    t0 = time.perf_counter()
    tracker = dataset_scene_at(dataset, args.time, config, progress=not args.json)
    learned_from = tracker.learned_from
    learn_s = time.perf_counter() - t0
    with dataset.open_frames() as source:
        frames: FrameSet = source.read(args.time)
    result = tracker.segment(frames)
    out = Path(args.out)
    cameras: list[dict[str, Any]] = []
    ious = _ground_truth_scores(dataset, result)
    for i, cam in enumerate(rig):
        mask = result.masks[i]
        image = frames.images[i]
        seg = result.objects[i]
        if mask is None or image is None or seg is None:
            cameras.append({"camera": cam.name, "available": False})
            continue
        _write_png(
            out / f"{cam.name}_mask.png", at_resolution(mask, image.shape).astype(np.uint8) * 255
        )
        _write_png(out / f"{cam.name}_overlay.png", overlay(image, result, i))
        model_mask = result.model_masks[i]
        checked = result.checked_masks[i] if result.checked_masks else mask
        if checked is None:
            checked = mask
        entry: dict[str, Any] = {
            "camera": cam.name,
            "available": True,
            "area_px": int(mask.sum()),
            "area_fraction": float(mask.mean()),
            "removed_by_hull_px": (
                int((model_mask & ~checked).sum()) if model_mask is not None else 0
            ),
            "filled_by_hull_px": int((checked & ~model_mask).sum())
            if model_mask is not None
            else 0,
            "removed_by_refine_px": int((checked & ~mask).sum()),
            "added_by_refine_px": int((mask & ~checked).sum()),
            "num_objects": seg.num_objects,
            "objects": [o.to_dict() for o in seg.objects],
        }
        if ious is not None:
            entry["iou_vs_ground_truth"] = ious[i]
        cameras.append(entry)
    hull = result.hull
    summary: dict[str, Any] = {
        "dataset": str(dataset.root),
        "time": args.time,
        "background_model": learned_from,
        "learn_seconds": round(learn_s, 3),
        "background_updates": tracker.updates,
        "static_scene_from": tracker.static_from,
        "ghosts_repaired": tracker.ghosts,
        "working_size": list(result.cameras[0].size) if result.cameras else None,
        "timings": result.timings.to_dict(),
        "cameras": cameras,
        "hull": None
        if hull is None
        else {
            "status": hull.status,
            "voxel_size": hull.voxel_size,
            "unit": rig.unit,
            "num_voxels": hull.num_voxels,
            "num_objects": hull.num_objects,
            "object_volumes": [hull.object_volume(k) for k in range(1, hull.num_objects + 1)],
        },
    }
    if args.hull_ply and hull is not None:
        write_ply(
            out / "hull.ply",
            hull_cloud(hull, rig.cameras, frames.images),
            **ply_frame(rig),
        )
    atomic_write_text(out / "masks.json", to_json(summary) + "\n")
    if args.json:
        emit_json(summary)
        return 0
    columns = [
        "camera",
        "area px",
        "area %",
        "objects",
        "hull-removed px",
        "hull-filled px",
        "refined -/+ px",
    ]
    if ious is not None:
        columns.append("IoU vs GT")
    rows = []
    for c in cameras:
        if not c["available"]:
            rows.append(
                [c["camera"], "-", "-", "-", "-", "-", "-"] + (["-"] if ious is not None else [])
            )
            continue
        row = [
            c["camera"],
            c["area_px"],
            100 * c["area_fraction"],
            c["num_objects"],
            c["removed_by_hull_px"],
            c["filled_by_hull_px"],
            f"{c['removed_by_refine_px']} / {c['added_by_refine_px']}",
        ]
        if ious is not None:
            row.append(c.get("iou_vs_ground_truth"))
        rows.append(row)
    print_table(f"{dataset.name} t={args.time} (background: {learned_from})", columns, rows)
    if hull is not None:
        console.print(
            f"visual hull: {hull.status}, {hull.num_objects} object(s), {hull.num_voxels:,} voxels "
            f"of {hull.voxel_size:.4g} {rig.unit}"
        )
    console.print(f"learn {learn_s:.2f} s, segment {result.timings.total:.2f} s -> {out}")
    return 0
