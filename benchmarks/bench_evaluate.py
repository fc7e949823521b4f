"""``edgerecon evaluate`` at scale (issue 15's done-when: a 1 M-point unlabelled cloud with
``--part foreground`` and an openMVS-style PLY with a list property, each in under 10 s).

    python benchmarks/bench_evaluate.py                     # scene in a temporary folder
    python benchmarks/bench_evaluate.py --scene /tmp/demo --json evaluate.json

Builds the synthetic ``demo`` scene (ground truth; reused when ``--scene`` holds it), then
times the installed command in a fresh process (start-up and PLY reading included), as a
user runs it:

* ``unlabelled-fg``: 1,000,000 unlabelled points (the scene's ground-truth surfaces, all of
  them, with 3 mm noise, resampled to 1 M, plus 2 % outliers up to 2 m away) scored with
  ``--gt --part foreground`` (the cloud is cropped to the points near the actors);
* ``unlabelled-bg`` / ``all``: the same cloud with ``--part background`` / ``--part all``;
* ``openmvs-1M``: the same points written as openMVS writes a dense cloud (a per-point
  ``views`` list and ``weights`` list) against a 1 M-point reference cloud (PRED REF).

Reported: seconds (wall, of the whole command), its CPU seconds (user + system, both cores
count), ``inner_s`` (the command's own measurement, after start-up), points, F-score at the
default thresholds.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import print_rows, report_header, write_report
from edgerecon.io.ply import write_ply
from edgerecon.synth import GroundTruth, preset_config, write_dataset
from edgerecon.types import PointCloud

N = 1_000_000


def scene(folder: Path) -> Path:
    if not (folder / "gt" / "scene.json").exists():
        write_dataset(preset_config("demo", num_frames=2, background_frames=4), folder)
    return folder


def unlabelled_cloud(gt: GroundTruth, t: int, seed: int = 0) -> PointCloud:
    rng = np.random.default_rng(seed)
    pts = gt.reference_cloud(t, "all", min_views=1).points3D
    idx = rng.integers(0, len(pts), N)
    out = pts[idx] + rng.normal(0, 0.003, (N, 3))
    k = N // 50
    out[:k] += rng.uniform(-2, 2, (k, 3))
    return PointCloud(points3D=out, colors=rng.integers(0, 256, (N, 3)).astype(np.uint8))


def write_openmvs_ply(path: Path, cloud: PointCloud, seed: int = 1) -> None:
    """Binary PLY as openMVS's dense clouds: xyz, colour, then 'views' (uchar count, uint
    ids) and 'weights' (uchar count, float) lists of 2-4 entries per point."""
    rng = np.random.default_rng(seed)
    n = len(cloud)
    counts = rng.integers(2, 5, n).astype(np.int64)
    size = 12 + 3 + 2 * (1 + 4 * counts)
    starts = np.zeros(n + 1, np.int64)
    np.cumsum(size, out=starts[1:])
    buf = np.zeros(int(starts[-1]), np.uint8)
    xyz = cloud.points3D.astype("<f4")
    buf[starts[:-1, None] + np.arange(12)] = xyz.view(np.uint8).reshape(n, 12)
    assert cloud.colors is not None
    buf[starts[:-1, None] + 12 + np.arange(3)] = cloud.colors
    buf[starts[:-1] + 15] = counts
    views_end = starts[:-1] + 16 + 4 * counts
    buf[views_end] = counts  # weights count; entries stay 0.0
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment openMVS-style test cloud\n"
        f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "property list uchar uint views\nproperty list uchar float weights\nend_header\n"
    )
    path.write_bytes(header.encode() + buf.tobytes())


def timed(args: list[str]) -> dict[str, Any]:
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "edgerecon", *args, "--json"],
        capture_output=True,
        text=True,
        check=False,
    )
    wall = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    if proc.returncode != 0:
        raise SystemExit(f"edgerecon {' '.join(args)} failed:\n{proc.stderr}")
    out = json.loads(proc.stdout)
    return {"seconds": round(wall, 2), "cpu_s": round(cpu, 2), "result": out}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, help="folder for the synthetic scene (reused)")
    ap.add_argument("--json", help="write the report here")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_evaluate_"))
    root = scene(args.scene or work / "scene")
    gt = GroundTruth.open(root)
    t = 1
    cloud = unlabelled_cloud(gt, t)
    write_ply(work / "pred.ply", cloud)
    write_openmvs_ply(work / "mvs.ply", cloud)
    ref = unlabelled_cloud(gt, t, seed=5)
    write_ply(work / "ref.ply", ref)
    rows = []
    base = ["evaluate", str(work / "pred.ply"), "--gt", str(root), "--time", str(t)]
    for name, extra in (
        ("unlabelled-fg", ["--part", "foreground"]),
        ("unlabelled-bg", ["--part", "background"]),
        ("unlabelled-all", ["--part", "all"]),
    ):
        r = timed(base + extra)
        res = r["result"]
        rows.append(
            {
                "case": name,
                "seconds": r["seconds"],
                "cpu_s": r["cpu_s"],
                "pred": res["num_pred_total"],
                "scored": res["num_pred"],
                "ref": res["scores"][0]["num_ref"],
                "F@1%": res["scores"][0]["fscore"],
                "F@2%": res["scores"][1]["fscore"],
                "inner_s": res["seconds"],
            }
        )
    r = timed(["evaluate", str(work / "mvs.ply"), str(work / "ref.ply"), "--dataset", str(root)])
    res = r["result"]
    rows.append(
        {
            "case": "openmvs-1M",
            "seconds": r["seconds"],
            "cpu_s": r["cpu_s"],
            "pred": res["scores"][0]["num_pred"],
            "scored": res["scores"][0]["num_pred"],
            "ref": res["scores"][0]["num_ref"],
            "F@1%": res["scores"][0]["fscore"],
            "F@2%": res["scores"][1]["fscore"],
            "inner_s": res["seconds"],
        }
    )
    header = report_header()
    print(f"commit {header['commit']}, load {header['load_avg']:.2f}, {header['cpus']} CPUs")
    print_rows(
        "edgerecon evaluate, wall seconds of the whole command (default thresholds 1 % / 2 %)",
        ["case", "seconds", "cpu_s", "inner_s", "pred", "scored", "ref", "F@1%", "F@2%"],
        rows,
    )
    if args.json:
        write_report(args.json, {**header, "rows": rows})


if __name__ == "__main__":
    main()
