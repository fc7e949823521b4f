"""Sparse reconstruction benchmark: per-stage seconds and point counts over a grid of image
scales x camera subsets, on utrecht4cam (frame 200), the Middlebury temple ring and a
synthetic scene rendered in memory (with its exact depth maps: precision of the points).

    python benchmarks/bench_sparse.py                          # everything, a few minutes
    python benchmarks/bench_sparse.py --datasets utrecht4cam --scales 1 0.5 --repeat 5
    python benchmarks/bench_sparse.py --datasets arc7 --json sparse.json

Times are the median of ``--repeat`` runs after one warm-up; "CPU s" is the process CPU time
of a run (all threads): on a busy shared machine wall time is noisy, CPU time / 2 is roughly
what an idle 2-core machine takes when both threads are busy. "prec" is the share of points
within 2 cm (5 cm) of the true surface, in the closest observing camera's depth map.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgerecon.geometry import Rig
from edgerecon.io.dataset import open_dataset
from edgerecon.sparse import SparseConfig, SparseReconstruction, reconstruct_sparse
from edgerecon.types import FrameSet
from edgerecon.views import prepare_views

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
REAL = {"utrecht4cam": 200, "middlebury_templeSparseRing": 0}


def load(name: str, seed: int) -> tuple[Rig, FrameSet, list[Any] | None]:
    """Rig, frames and (synthetic only) per-camera ground-truth depth maps."""
    if name in REAL:
        ds = open_dataset(SHARED / name)
        with ds.open_frames() as frames:
            return ds.rig, frames.read(REAL[name]), None
    from edgerecon.synth import Renderer, build_scene, preset_config

    scene = build_scene(preset_config(name, seed=seed))
    frame = Renderer(scene).render(10)
    return scene.rig, FrameSet(time_index=10, images=frame.images), list(frame.depths)


def subsets(n: int) -> list[tuple[int, ...]]:
    """All cameras, and evenly spread subsets down to 3."""
    out = [tuple(range(n))]
    for k in sorted({max(3, n - 2), 3}, reverse=True):
        if k < n:
            idx = tuple(int(x) for x in np.rint(np.linspace(0, n - 1, k)))
            if idx not in out:
                out.append(idx)
    return out


def precision(rig: Rig, depths: list[Any], rec: SparseReconstruction) -> tuple[float, float]:
    if rec.num_points == 0:
        return float("nan"), float("nan")
    err = np.full(rec.num_points, np.inf)
    for n, cid in enumerate(rec.camera_ids):
        cam = rig[cid]  # the original (distorted, full resolution) camera of the depth map
        sel = rec.visibility[:, n]
        uv, z = cam.project(rec.points3D[sel])
        ok = cam.in_image(uv) & (z > 0)
        px = np.rint(np.nan_to_num(uv)).astype(int)
        zgt = np.full(len(z), np.nan)
        zgt[ok] = depths[cid][px[ok, 1], px[ok, 0]]
        err[sel] = np.minimum(err[sel], np.nan_to_num(np.abs(z - zgt), nan=np.inf))
    return float(np.mean(err <= 0.02)), float(np.mean(err <= 0.05))


def bench(
    name: str,
    rig: Rig,
    frames: FrameSet,
    depths: list[Any] | None,
    scale: float,
    cameras: Sequence[int],
    config: SparseConfig,
    repeat: int,
) -> dict[str, Any]:
    views = prepare_views(frames, rig, scale, cameras)
    reconstruct_sparse(views, config)  # warm-up
    walls, cpus, stages = [], [], []
    rec = None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        rec = reconstruct_sparse(views, config)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        stages.append(rec.timings.seconds)
    assert rec is not None
    row: dict[str, Any] = {
        "dataset": name,
        "scale": scale,
        "cameras": ",".join(map(str, cameras)),
        "size": f"{views[0].camera.width}x{views[0].camera.height}",
        "seconds": round(float(np.median(walls)), 3),
        "cpu_seconds": round(float(np.median(cpus)), 3),
        "stages": {k: round(float(np.median([s[k] for s in stages])), 3) for k in stages[0]},
        "points": rec.num_points,
        "reprojection_px": round(float(np.median(rec.reprojection_error_px)), 3)
        if rec.num_points
        else None,
        "three_view_share": round(float(np.mean(rec.visibility.sum(axis=1) >= 3)), 3)
        if rec.num_points
        else None,
        "features": int(sum(rec.stats.get("features_per_view", {}).values())),
        "matches": int(sum(rec.stats.get("matches_per_pair", {}).values())),
    }
    if depths is not None:
        p2, p5 = precision(rig, depths, rec)
        row["precision_2cm"], row["precision_5cm"] = round(p2, 3), round(p5, 3)
    if name == "middlebury_templeSparseRing" and rec.num_points:
        box = np.array([[-0.073568, 0.021728, -0.012445], [0.028855, 0.181892, 0.062736]])
        inside = np.all((rec.points3D >= box[0] - 0.005) & (rec.points3D <= box[1] + 0.005), 1)
        row["inside_bbox"] = round(float(inside.mean()), 3)
    if name == "utrecht4cam" and rec.num_points:
        z = rec.points3D[:, 2]  # floor z = 0, up = -z (mm)
        row["in_room"] = round(float(np.mean((z < 50) & (z > -4000))), 3)
    print(
        f"{name:28s} r={scale:<4} cams={row['cameras']:16s} {row['seconds']:6.2f}s "
        f"cpu={row['cpu_seconds']:6.2f}s pts={row['points']:5d} {row['stages']}",
        flush=True,
    )
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--datasets", nargs="+", default=["utrecht4cam", "middlebury_templeSparseRing", "arc7"]
    )
    parser.add_argument("--scales", nargs="+", type=float, default=[1.0, 0.8, 0.6, 0.5])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=1, help="synthetic scene seed")
    parser.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    args = parser.parse_args()
    config = SparseConfig(num_threads=args.threads)
    rows = []
    for name in args.datasets:
        rig, frames, depths = load(name, args.seed)
        grid = [(s, subsets(len(rig))[0]) for s in args.scales]
        grid += [(1.0, c) for c in subsets(len(rig))[1:]]
        if name == "middlebury_templeSparseRing":
            grid = [(s, c) for s, c in grid if s in (1.0, 0.5)]
        for scale, cams in grid:
            rows.append(bench(name, rig, frames, depths, scale, cams, config, args.repeat))
    _print_table(
        f"sparse reconstruction ({args.threads} threads, {os.cpu_count()} CPUs, "
        f"load {os.getloadavg()[0]:.1f})",
        [
            "dataset",
            "r",
            "cameras",
            "size",
            "s",
            "CPU s",
            "features s",
            "matching s",
            "triang. s",
            "points",
            "reproj px",
            ">=3 views",
            "quality",
        ],
        [
            [
                r["dataset"],
                r["scale"],
                r["cameras"],
                r["size"],
                r["seconds"],
                r["cpu_seconds"],
                r["stages"].get("features", 0.0),
                r["stages"].get("matching", 0.0),
                r["stages"].get("triangulation", 0.0),
                r["points"],
                r["reprojection_px"],
                r["three_view_share"],
                _quality(r),
            ]
            for r in rows
        ],
    )
    if args.json:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
        ).stdout.strip()
        report = {
            "commit": commit,
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "config": {k: v for k, v in vars(config).items()},
            "results": rows,
        }
        Path(args.json).write_text(json.dumps(report, indent=2, default=str))


def _print_table(title: str, columns: list[str], rows: list[list[Any]]) -> None:
    """Plain fixed-width table (readable in logs and pipes, whatever the terminal width)."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
        return "-" if v is None else str(v)

    cells = [columns] + [[fmt(v) for v in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(columns))]
    print(f"\n{title}")
    for k, r in enumerate(cells):
        print(
            "  ".join(
                c.rjust(w) if k and i else c.ljust(w)
                for i, (c, w) in enumerate(zip(r, widths, strict=True))
            )
        )
        if k == 0:
            print("  ".join("-" * w for w in widths))


def _quality(r: dict[str, Any]) -> str:
    if "precision_2cm" in r:
        return f"prec {r['precision_2cm']:.2f} ({r['precision_5cm']:.2f})"
    if "inside_bbox" in r:
        return f"in box {r['inside_bbox']:.2f}"
    if "in_room" in r:
        return f"in room {r['in_room']:.2f}"
    return "-"


if __name__ == "__main__":
    main()
