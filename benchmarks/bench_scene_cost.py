"""What the scene stage costs per camera and per task, at three sensor resolutions (issue 11).

The scene stage of one task: every camera's background subtraction, the visual hull of the
masks and the masks made consistent with it, their holes filled from the other cameras, the
photo check of the ghosts (``ForegroundConfig.photo_check``), the phantoms' and the hull's
explanations, the outline refinement and the objects of each mask (all at the working
resolution, ``BackgroundConfig.working_pixels``; every step ``RigForeground.segment`` times is
counted, a step not named here under ``other``), plus the scheduled background update. Its
share of the golden task is measured against the golden reconstruction of the same frames
(``pipeline.reconstruct`` at r = 1 with all cameras, the product's own stage timings).

The scenes are the people-in-a-room preset (``hd4``: 4 cameras 90 degrees apart, no background
clip) rendered at each size. Also scored: mask IoU against the ground truth (at the ground
truth's resolution).

    python benchmarks/bench_scene_cost.py                       # 640x480, 1280x720, 1920x1080
    python benchmarks/bench_scene_cost.py --sizes 1920x1080 --tasks 20 --json cost.json
    python benchmarks/bench_scene_cost.py --dataset /tmp/cal1080      # a real capture

``--dataset``: the same measurement on a dataset's own frames (a real capture, or one at
another size made by ``resample_dataset.py``), its models bootstrapped from the stream as the
online system does when it has no clip of the empty scene (no mask IoU: there is no truth).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import print_rows, report_header, with_settings, write_report
from edgerecon.io.dataset import open_dataset
from edgerecon.pipeline import reconstruct, warm_up
from edgerecon.quality.masks import mask_iou
from edgerecon.scene.foreground import ForegroundConfig, RigForeground
from edgerecon.scene.stream import bootstrap_indices
from edgerecon.synth import Renderer, build_scene, preset_config
from edgerecon.types import FrameSet

STAGES = (
    "background_subtraction",
    "visual_hull",
    "hull_consistency",
    "hull_rescue",
    "tolerant_hull",
    "hull_fill",
    "photo_check",
    "phantom_explained",
    "hull_explained",
    "static_check",
    "refine",
    "objects",
)


def synthetic_source(preset: str, size: tuple[int, int]) -> tuple[Any, int, float, Any]:
    """(rig, frames, fps, frameset(t) -> (FrameSet, truth masks or None)) of a preset."""
    config = preset_config(preset, width=size[0], height=size[1])
    scene = build_scene(config)
    renderer = Renderer(scene)

    def frameset(t: int) -> tuple[FrameSet, Any]:
        fr = renderer.render(t)
        return FrameSet(time_index=t, images=tuple(fr.images)), fr.masks

    return scene.rig, config.num_frames, config.fps, frameset


def dataset_source(path: Path) -> tuple[Any, int, float | None, Any]:
    """The same of a dataset on disk (no truth masks)."""
    ds = open_dataset(path)
    source = ds.open_frames()

    def frameset(t: int) -> tuple[FrameSet, Any]:
        return source.read(t), None

    return ds.rig, source.num_frames, source.fps, frameset


def measure(
    source: tuple[Any, int, float | None, Any],
    tasks: int,
    start: int,
    step: int,
    fg_config: ForegroundConfig | None = None,
) -> dict[str, Any]:
    rig, num_frames, fps, frameset = source
    fg_config = fg_config or ForegroundConfig()
    boot = bootstrap_indices(num_frames, fps, fg_config)
    # As the online system without an empty-scene clip: from the stream, the person model
    # where ``person_model`` uses it.
    fg = RigForeground.learn_from_framesets(
        rig, [frameset(t)[0] for t in boot], fg_config, from_stream=True
    )
    wall = dict.fromkeys((*STAGES, "other", "update"), 0.0)
    cpu = {"segment": 0.0, "update": 0.0}
    ious = []
    golden_s = []
    times = [t for t in range(start, num_frames, step)][:tasks]
    if not times:
        raise SystemExit(f"no timestamp from {start} in a stream of {num_frames} frames")
    for k, t in enumerate(times):
        fs, truth = frameset(t)
        c0 = time.process_time()
        res = fg.segment(fs)
        c1 = time.process_time()
        t1 = time.perf_counter()
        fg.update(fs, res)
        wall["update"] += time.perf_counter() - t1
        cpu["segment"] += c1 - c0
        cpu["update"] += time.process_time() - c1
        for s, seconds in res.timings.seconds.items():  # every step the segmentation timed
            wall[s if s in wall else "other"] += seconds
        if truth is not None:
            ious.append(
                np.mean([mask_iou(m, gt > 0) for m, gt in zip(res.masks, truth, strict=True)])
            )
        if k < 2:  # the golden task of the same frames (product timings)
            golden_s.append(reconstruct(fs, rig).timings.total)
    tasks = len(times)
    n = len(rig)
    per_task = {s: 1000 * v / tasks for s, v in wall.items()}
    total_ms = sum(per_task.values())
    golden = float(np.median(golden_s))
    w, h = rig[0].size
    working = fg.working_cameras[0].size
    return {
        "size": f"{w}x{h}",
        "working": f"{working[0]}x{working[1]}",
        "cameras": n,
        "tasks": tasks,
        **{f"{s}_ms": round(v, 1) for s, v in per_task.items()},
        "scene_ms_per_task": round(total_ms, 1),
        "scene_ms_per_camera": round(total_ms / n, 1),
        "scene_cpu_ms_per_task": round(1000 * (cpu["segment"] + cpu["update"]) / tasks, 1),
        "golden_task_s": round(golden, 3),
        "share_of_golden": round(total_ms / 1000 / golden, 4),
        "mask_iou": round(float(np.mean(ious)), 4) if ious else None,
    }


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="hd4")
    ap.add_argument(
        "--dataset", type=Path, default=None, help="a dataset's own frames instead of a preset"
    )
    ap.add_argument("--sizes", nargs="*", default=["640x480", "1280x720", "1920x1080"])
    ap.add_argument("--tasks", type=int, default=10, help="tasks timed per size")
    ap.add_argument("--start", type=int, default=40, help="first timestamp")
    ap.add_argument("--step", type=int, default=10, help="timestamps between tasks")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a ForegroundConfig setting, as in [runtime.foreground] (repeatable), e.g. "
        "photo_check=false",
    )
    ap.add_argument("--json", type=Path, default=None, help="write a JSON report")
    args = ap.parse_args()
    fg_config = with_settings(ForegroundConfig(), args.set, "runtime.foreground")
    warm_up()
    rows = []
    name = args.preset if args.dataset is None else args.dataset.name
    sources = (
        (dataset_source(args.dataset),)
        if args.dataset is not None
        else (
            synthetic_source(args.preset, (int(w), int(h)))
            for w, h in (text.lower().split("x") for text in args.sizes)
        )
    )
    for source in sources:
        rows.append(measure(source, args.tasks, args.start, args.step, fg_config))
        print_rows(f"scene stage, {name}", list(rows[-1]), rows[-1:])
    print_rows(f"scene stage per task ({name}, load {os.getloadavg()[0]:.1f})", list(rows[0]), rows)
    if args.json:
        write_report(args.json, {**report_header(), "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
