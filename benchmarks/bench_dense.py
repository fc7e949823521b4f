"""Dense reconstruction benchmark: per-stage seconds, point counts and quality over a grid of
image scales x camera subsets, on utrecht4cam (frame 200), the Middlebury temple ring and the
synthetic 7-camera 1920x1080 arc (written once to ``--synthetic-dir``, with ground truth).

    python benchmarks/bench_dense.py                                  # everything
    python benchmarks/bench_dense.py --datasets utrecht4cam --scales 1 0.5 --repeat 3
    python benchmarks/bench_dense.py --datasets arc7 --scales 1 --masks 0.1 --json dense.json
    python benchmarks/bench_dense.py --datasets arc7 --render out/   # PNG views of the clouds
    python benchmarks/bench_dense.py --datasets arc7 --scales 1 --devices cpu cuda  # GPU path

Each row runs the golden pipeline of one task: sparse (``reconstruct_sparse``, its depth
ranges feed the sweep) then dense (``reconstruct_dense``); "total s" is both. Times are the
median of ``--repeat`` runs after one warm-up (numba kernels load once per process); "CPU s"
is the process CPU time of the dense stage (all threads): on a busy shared machine the wall
time is noisy, CPU / 2 is roughly what an idle 2-core machine takes.

Quality: synthetic -> precision / recall / F-score at 2 cm against the ground-truth surfaces
seen by >= 2 cameras; utrecht4cam -> median |z| (mm) of the points within 100 mm of the
floor (z = 0) and the number of floor points; temple -> share of points inside the published
bounding box. ``--masks F`` adds rows where every view is masked to a disc covering the share
F of the image around the scene's centre (the foreground pipeline's case). ``--devices cpu
cuda`` runs every row with the NCC scoring on the CPU kernels and on the GPU
(``DenseConfig.device``; the cuda rows need a CUDA GPU) and adds each GPU row's F-score against
its CPU row's cloud at 1 mm ("vs cpu").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from edgerecon.dense import DenseConfig, DenseReconstruction, reconstruct_dense
from edgerecon.geometry import Camera, Rig, look_at
from edgerecon.io.dataset import open_dataset
from edgerecon.quality.metrics import evaluate_clouds
from edgerecon.types import FrameSet, PointCloud
from edgerecon.views import View, prepare_views

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
REAL = {"utrecht4cam": 200, "middlebury_templeSparseRing": 0}
TEMPLE_BOX = np.array([[-0.073568, 0.021728, -0.012445], [0.028855, 0.181892, 0.062736]])


def load(name: str, synthetic_dir: Path) -> tuple[Rig, FrameSet, PointCloud | None]:
    """Rig, frames and (synthetic only) the ground-truth cloud seen by >= 2 cameras."""
    if name in REAL:
        ds = open_dataset(SHARED / name)
        with ds.open_frames() as frames:
            return ds.rig, frames.read(REAL[name]), None
    from edgerecon.synth import GroundTruth, preset_config, write_dataset

    folder = synthetic_dir / name
    if not (folder / "dataset.json").is_file():
        print(f"writing the synthetic dataset {name} to {folder} (once, minutes)", flush=True)
        write_dataset(preset_config(name, num_frames=1), folder)
    ds = open_dataset(folder)
    with ds.open_frames() as frames:
        fs = frames.read(0)
    ref = GroundTruth.open(folder).reference_cloud(0, part="all", min_views=2)
    return ds.rig, fs, ref


def subsets(n: int) -> list[tuple[int, ...]]:
    """All cameras, and evenly spread subsets down to 3."""
    out = [tuple(range(n))]
    for k in sorted({max(3, n - 3), 3}, reverse=True):
        if k < n:
            idx = tuple(int(x) for x in np.rint(np.linspace(0, n - 1, k)))
            if idx not in out:
                out.append(idx)
    return out


def disc_masks(views: Sequence[View], share: float) -> list[View]:
    """Every view masked to a disc of ``share`` of its area around the views' common centre
    (the point closest to all optical axes)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for v in views:
        d = v.camera.viewing_direction
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ v.camera.center
    centre = np.linalg.lstsq(A, b, rcond=None)[0]
    out = []
    for v in views:
        uv, _ = v.camera.project(centre[None])
        h, w = v.image.shape[:2]
        radius = int(np.sqrt(share * w * h / np.pi))
        mask = np.zeros((h, w), np.uint8)
        cx = int(np.clip(uv[0, 0], radius, w - radius))
        cy = int(np.clip(uv[0, 1], radius, h - radius))
        cv2.circle(mask, (cx, cy), radius, 1, -1)
        out.append(dataclasses.replace(v, mask=mask.astype(bool)))
    return out


def quality(name: str, rec: DenseReconstruction, ref: PointCloud | None) -> dict[str, Any]:
    P = rec.cloud.points3D
    if ref is not None:
        s = evaluate_clouds(rec.cloud, ref, [0.02])[0]
        return {
            "precision_2cm": round(s.precision, 3),
            "recall_2cm": round(s.recall, 3),
            "fscore_2cm": round(s.fscore, 3),
        }
    if name == "middlebury_templeSparseRing":
        inside = np.all((P >= TEMPLE_BOX[0]) & (P <= TEMPLE_BOX[1]), axis=1)
        return {"inside_bbox": round(float(inside.mean()), 3) if len(P) else None}
    if name == "utrecht4cam":
        floor = np.abs(P[:, 2]) < 100
        return {
            "floor_points": int(floor.sum()),
            "floor_median_abs_z_mm": round(float(np.median(np.abs(P[floor, 2]))), 1)
            if floor.any()
            else None,
        }
    return {}


def bench(
    name: str,
    rig: Rig,
    frames: FrameSet,
    ref: PointCloud | None,
    scale: float,
    cameras: Sequence[int],
    config: DenseConfig,
    repeat: int,
    sparse: bool,
    mask_share: float | None,
) -> tuple[dict[str, Any], DenseReconstruction]:
    views = prepare_views(frames, rig, scale, cameras)
    if mask_share is not None:
        views = disc_masks(views, mask_share)
    run_sparse = None
    if sparse:
        from edgerecon.sparse import SparseConfig, reconstruct_sparse

        def run_sparse():  # type: ignore[no-untyped-def]
            return reconstruct_sparse(views, SparseConfig(num_threads=config.num_threads))

    def once() -> tuple[float, float, float, DenseReconstruction, int]:
        t0 = time.perf_counter()
        sp = run_sparse() if run_sparse else None
        t1, c1 = time.perf_counter(), time.process_time()
        rec = reconstruct_dense(views, config, sp, up=rig.up)
        return (
            time.perf_counter() - t0,
            time.perf_counter() - t1,
            time.process_time() - c1,
            rec,
            (len(sp) if sp is not None else -1),
        )

    once()  # warm-up (kernel loading, caches)
    runs = [once() for _ in range(repeat)]
    rec = runs[-1][3]
    stages = [r[3].timings.seconds for r in runs]
    row: dict[str, Any] = {
        "dataset": name,
        "device": config.device,
        "scale": scale,
        "cameras": ",".join(map(str, cameras)),
        "size": f"{views[0].camera.width}x{views[0].camera.height}",
        "mask_share": mask_share,
        "total_seconds": round(float(np.median([r[0] for r in runs])), 3),
        "dense_seconds": round(float(np.median([r[1] for r in runs])), 3),
        "dense_cpu_seconds": round(float(np.median([r[2] for r in runs])), 3),
        "stages": {
            k: round(float(np.median([s.get(k, 0.0) for s in stages])), 3) for k in stages[0]
        },
        "sparse_points": runs[-1][4],
        "points": len(rec.cloud),
        "work_M": round(rec.stats["work"] / 1e6, 1),
        "scoring": rec.stats.get("scoring"),
        **quality(name, rec, ref),
    }
    print(
        f"{name:28s} {_scoring_short(row)} r={scale:<4} cams={row['cameras']:14s} mask={mask_share} "
        f"total={row['total_seconds']:6.2f}s dense={row['dense_seconds']:6.2f}s "
        f"cpu={row['dense_cpu_seconds']:6.2f}s pts={row['points']:7d} {_quality_text(row)} "
        f"{row['stages']}",
        flush=True,
    )
    return row, rec


def render_cloud(cloud: PointCloud, rig: Rig, size: tuple[int, int] = (800, 600)) -> np.ndarray:
    """Splat the cloud into four virtual cameras around the points' centre (a 2x2 PNG)."""
    P = cloud.points3D
    if len(P) == 0:
        return np.full((size[1] * 2, size[0] * 2, 3), 255, np.uint8)
    centre = np.median(P, axis=0)
    radius = float(np.percentile(np.linalg.norm(P - centre, axis=1), 90)) * 2.5
    up = np.asarray(rig.up, float)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    other = np.cross(up, side)
    tiles = []
    for k in range(4):
        a = np.pi / 4 + k * np.pi / 2
        eye = centre + radius * (np.cos(a) * side + np.sin(a) * other + 0.6 * up)
        R, t = look_at(eye, centre, up)
        w, h = size
        K = np.array([[0.9 * w, 0, w / 2], [0, 0.9 * w, h / 2], [0, 0, 1.0]])
        cam = Camera(name="v", width=w, height=h, K=K, R=R, t=t)
        uv, z = cam.project(P)
        ok = (z > 0) & cam.in_image(uv)
        px = np.rint(uv[ok]).astype(int)
        order = np.argsort(-z[ok])
        img = np.full((h, w, 3), 255, np.uint8)
        colors = (cloud.colors if cloud.colors is not None else np.full((len(P), 3), 90))[ok]
        for dy in (0, 1):
            for dx in (0, 1):
                x = np.clip(px[order, 0] + dx, 0, w - 1)
                y = np.clip(px[order, 1] + dy, 0, h - 1)
                img[y, x] = colors[order][:, ::-1]
        tiles.append(img)
    return np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])])


def _print_table(title: str, header: list[str], rows: list[list[Any]]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    for h in header:
        table.add_column(h, justify="right")
    for r in rows:
        table.add_row(*["" if v is None else str(v) for v in r])
    Console(width=220).print(table)


def _quality_text(r: dict[str, Any]) -> str:
    if "fscore_2cm" in r:
        return f"P {r['precision_2cm']} R {r['recall_2cm']} F {r['fscore_2cm']}"
    if "inside_bbox" in r:
        return f"in box {r['inside_bbox']}"
    if "floor_points" in r:
        return f"floor {r['floor_points']} pts, med|z| {r['floor_median_abs_z_mm']} mm"
    return ""


def _scoring_short(row: dict[str, Any]) -> str:
    """The table's "scoring" cell: "cuda (NAME)" or "cpu" (the JSON keeps why not the GPU)."""
    scoring = str(row.get("scoring") or "")
    return scoring if scoring.startswith("cuda") else "cpu"


def _unit_mm(name: str) -> float:
    """Rig units per millimetre (utrecht4cam is in mm, the temple and the synthetic rigs in m)."""
    return 1.0 if name == "utrecht4cam" else 1e-3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--datasets", nargs="+", default=["utrecht4cam", "middlebury_templeSparseRing", "arc7"]
    )
    parser.add_argument("--scales", nargs="+", type=float, default=[1.0, 0.8, 0.6])
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-sparse", action="store_true", help="dense without sparse priors")
    parser.add_argument("--masks", type=float, default=None, help="also run with disc masks")
    parser.add_argument("--synthetic-dir", type=Path, default=Path("/tmp/edgerecon-bench"))
    parser.add_argument("--render", type=Path, help="write PNG renderings of the clouds here")
    parser.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    parser.add_argument(
        "--devices", nargs="+", default=["cpu"], choices=["cpu", "cuda", "auto"],
        help="where the NCC scoring runs (DenseConfig.device), one row each",
    )  # fmt: skip
    args = parser.parse_args()
    config = DenseConfig(num_threads=args.threads)
    rows = []
    for name in args.datasets:
        rig, frames, ref = load(name, args.synthetic_dir)
        cams = subsets(len(rig))
        grid: list[tuple[float, tuple[int, ...], float | None]] = [
            (s, cams[0], None) for s in args.scales
        ]
        grid += [(args.scales[0], c, None) for c in cams[1:]]
        if args.masks is not None:
            grid += [(args.scales[0], cams[0], args.masks)]
        if name == "middlebury_templeSparseRing":
            grid = [g for g in grid if g[0] == args.scales[0]]
        for scale, subset, share in grid:
            first: DenseReconstruction | None = None
            for device in args.devices:
                row, rec = bench(
                    name,
                    rig,
                    frames,
                    ref,
                    scale,
                    subset,
                    dataclasses.replace(config, device=device),
                    args.repeat,
                    not args.no_sparse,
                    share,
                )
                if first is None:
                    first = rec
                elif len(first.cloud) and len(rec.cloud):
                    vs = evaluate_clouds(rec.cloud, first.cloud, [_unit_mm(name)])[0]
                    row["fscore_vs_first_device_1mm"] = round(vs.fscore, 4)
                rows.append(row)
                if args.render is not None:
                    args.render.mkdir(parents=True, exist_ok=True)
                    tag = f"{name}_r{scale}_c{len(subset)}" + (f"_m{share}" if share else "")
                    tag += f"_{device}" if len(args.devices) > 1 else ""
                    cv2.imwrite(str(args.render / f"{tag}.png"), render_cloud(rec.cloud, rig))
    _print_table(
        f"dense reconstruction ({args.threads} threads, {os.cpu_count()} CPUs, "
        f"load {os.getloadavg()[0]:.1f})",
        ["dataset", "scoring", "r", "cameras", "size", "mask", "total s", "dense s", "CPU s",
         "depth s", "consist. s", "ground s", "fusion s", "sparse pts", "points", "quality",
         "vs cpu"],
        [
            [
                r["dataset"], _scoring_short(r), r["scale"], r["cameras"], r["size"], r["mask_share"],
                r["total_seconds"], r["dense_seconds"], r["dense_cpu_seconds"],
                r["stages"].get("depth"), r["stages"].get("consistency"),
                r["stages"].get("ground"), r["stages"].get("fusion"), r["sparse_points"],
                r["points"], _quality_text(r), r.get("fscore_vs_first_device_1mm"),
            ]
            for r in rows
        ],
    )  # fmt: skip
    if args.json:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
        ).stdout.strip()
        report = {
            "commit": commit,
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load": os.getloadavg()[0],
            "config": dataclasses.asdict(config),
            "rows": rows,
        }
        Path(args.json).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
