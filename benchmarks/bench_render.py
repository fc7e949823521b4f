"""Render-time benchmark of the synthetic scene renderer.

Prints a table: preset, cameras, resolution, seconds to build the scene (textures), seconds to
cast the static background once (cached), and seconds per timestamp (all cameras, actors
re-cast, imaging) as median / min over the timed frames after one warm-up frame, plus the
process CPU seconds per timestamp (all threads; on a busy shared machine wall time is noisy, CPU
time / threads is what an idle machine of the same speed would take if the threads scale) and
the 1-minute load average when it finished.

    python benchmarks/bench_render.py                    # arc7 (7 x 1920x1080), demo, ring
    python benchmarks/bench_render.py --preset arc7 --frames 10 --threads 2 --json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time

import numpy as np

from edgerecon.cli._common import print_table
from edgerecon.synth import Renderer, build_scene, preset_config


def bench(preset: str, frames: int, threads: int, seed: int) -> dict[str, object]:
    config = preset_config(preset, seed=seed)
    t0 = time.perf_counter()
    scene = build_scene(config)
    build_s = time.perf_counter() - t0
    renderer = Renderer(scene, threads=threads)
    t0 = time.perf_counter()
    renderer.prepare()
    prepare_s = time.perf_counter() - t0
    times = np.linspace(0, config.num_frames - 1, frames + 1).round().astype(int)
    renderer.render(int(times[0]))  # warm-up (noise pools, caches)
    per_frame = []
    cpu_per_frame = []
    stages: dict[str, float] = {}
    for t in times[1:]:
        t0, c0 = time.perf_counter(), time.process_time()
        frame = renderer.render(int(t))
        per_frame.append(time.perf_counter() - t0)
        cpu_per_frame.append(time.process_time() - c0)
        for k, v in frame.timings.seconds.items():
            stages[k] = stages.get(k, 0.0) + v / frames
    cam = scene.rig[0]
    return {
        "preset": preset,
        "cameras": len(scene.rig),
        "resolution": f"{cam.width}x{cam.height}",
        "actors": len(scene.actors),
        "build_s": round(build_s, 3),
        "prepare_s": round(prepare_s, 3),
        "frame_median_s": round(float(np.median(per_frame)), 3),
        "frame_min_s": round(float(np.min(per_frame)), 3),
        "frame_cpu_s": round(float(np.median(cpu_per_frame)), 3),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "stage_s_summed_over_cameras": {k: round(v, 4) for k, v in stages.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", nargs="+", default=["arc7", "demo", "ring"])
    parser.add_argument("--frames", type=int, default=8, help="timed frames per preset")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows = [bench(p, args.frames, args.threads, args.seed) for p in args.preset]
    if args.json:
        try:
            commit = subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
            ).stdout.strip()
        except OSError:
            commit = ""
        print(
            json.dumps(
                {
                    "commit": commit,
                    "python": platform.python_version(),
                    "cpus": os.cpu_count(),
                    "threads": args.threads,
                    "results": rows,
                },
                indent=2,
            )
        )
        return
    print_table(
        f"synthetic render time ({args.threads} threads, {os.cpu_count()} CPUs)",
        [
            "preset",
            "cameras",
            "resolution",
            "build s",
            "bg s",
            "s/ts",
            "min s",
            "CPU s/ts",
            "load",
        ],
        [
            [
                r["preset"],
                r["cameras"],
                r["resolution"],
                r["build_s"],
                r["prepare_s"],
                r["frame_median_s"],
                r["frame_min_s"],
                r["frame_cpu_s"],
                r["load_avg_1min"],
            ]
            for r in rows
        ],
    )
    for r in rows:
        print(r["preset"], "stage seconds (summed over cameras):", r["stage_s_summed_over_cameras"])


if __name__ == "__main__":
    main()
