"""Inferred points (issue 13): how many points the ground completion adds, how the scores
change when only measured points are scored, and what the level map that verifies the
completion costs.

    python benchmarks/bench_inferred.py --synth DIR       # DIR: edgerecon synth --preset arc7 ...
    python benchmarks/bench_inferred.py --synth ARC7 DEMO --repeat 2 --json inferred.json

Each dataset runs the golden whole-scene pipeline (``edgerecon.pipeline.reconstruct``) with
the level map (``DenseConfig.ground_level_cell`` 16, the default) and without it (0),
alternately (A B A B ..., one process, after a warm-up run), and reports the median seconds
of the dense ground stage, the level map's cells and the completed / refused depths. The
clouds of the last runs are written to ``--out`` and scored with ``edgerecon evaluate``
(synthetic: against the ground truth at t=20, all points and ``--measured-only``); utrecht4cam
(frame 200, real): floor points (within 100 mm of the board's z = 0), measured and inferred,
and points more than 300 mm above the floor (the person on the chair).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from edgerecon.config import ReconstructionConfig
from edgerecon.io.dataset import open_dataset
from edgerecon.io.ply import write_ply
from edgerecon.pipeline import reconstruct, warm_up

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def run_variant(frames: Any, rig: Any, cell: float) -> dict[str, Any]:
    base = ReconstructionConfig()
    config = dataclasses.replace(
        base, dense_config=dataclasses.replace(base.dense_config, ground_level_cell=cell)
    )
    c0 = time.process_time()
    result = reconstruct(frames, rig, config)
    cpu = time.process_time() - c0
    assert result.dense is not None
    st = result.dense.stats
    t = result.timings.seconds
    return {
        "cloud": result.dense.cloud,
        "points": len(result.dense.cloud),
        "inferred": result.dense.cloud.num_inferred,
        "ground_s": t.get("dense.ground", 0.0),
        "dense_s": sum(v for k, v in t.items() if k.startswith("dense.")),
        "total_s": result.timings.total,
        "cpu_s": cpu,
        "ground": {k: v for k, v in (st.get("ground") or {}).items()},
        "plane": st.get("ground_plane"),
    }


def evaluate(ply: Path, gt: Path, time_index: int, measured_only: bool) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "edgerecon", "evaluate", str(ply), "--gt", str(gt)]
    cmd += ["--time", str(time_index), "--part", "all", "-d", "0.01", "0.02", "--json"]
    if measured_only:
        cmd.append("--measured-only")
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--synth", type=Path, nargs="*", default=[], help="synthetic datasets")
    ap.add_argument("--time", type=int, default=20, help="synthetic time index (default 20)")
    ap.add_argument("--no-utrecht", action="store_true")
    ap.add_argument("--repeat", type=int, default=2, help="A/B pairs per dataset")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_inferred"))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    warm_up()
    sets = []
    for folder in args.synth:
        sets.append((folder.name, folder, args.time))
    if not args.no_utrecht and (SHARED / "utrecht4cam").exists():
        sets.append(("utrecht4cam", SHARED / "utrecht4cam", 200))
    report: dict[str, Any] = {"load_before": os.getloadavg(), "datasets": {}}
    for name, folder, t_index in sets:
        ds = open_dataset(folder)
        with ds.open_frames() as src:
            frames = src.read(t_index)
        run_variant(frames, ds.rig, 16.0)  # warm-up (kernels, caches)
        runs: dict[str, list[dict[str, Any]]] = {"map": [], "no map": []}
        for _ in range(args.repeat):
            runs["map"].append(run_variant(frames, ds.rig, 16.0))
            runs["no map"].append(run_variant(frames, ds.rig, 0.0))
        rows = {}
        for key, rs in runs.items():
            last = rs[-1]
            ply = args.out / f"{name}_{key.replace(' ', '_')}.ply"
            write_ply(ply, last["cloud"], unit=ds.rig.unit, up=ds.rig.up)
            row = {
                "points": last["points"],
                "inferred": last["inferred"],
                "ground_s": float(np.median([r["ground_s"] for r in rs])),
                "dense_s": float(np.median([r["dense_s"] for r in rs])),
                "total_s": float(np.median([r["total_s"] for r in rs])),
                "cpu_s": float(np.median([r["cpu_s"] for r in rs])),
                "ground": last["ground"],
                "ply": str(ply),
            }
            P, inf = last["cloud"].points3D, last["cloud"].inferred
            if name == "utrecht4cam":  # z points down, millimetres
                floor = np.abs(P[:, 2]) < 100
                row["floor_measured"] = int((floor & ~inf).sum())
                row["floor_inferred"] = int((floor & inf).sum())
                row["above_300mm"] = int((P[:, 2] < -300).sum())
                row["median_abs_z_floor_mm"] = float(np.median(np.abs(P[floor, 2])))
            else:
                for mo in (False, True):
                    ev = evaluate(ply, folder, t_index, mo)
                    row["measured_only" if mo else "all"] = [
                        {k: s[k] for k in ("threshold", "precision", "recall", "fscore")}
                        for s in ev["scores"]
                    ]
            rows[key] = row
        report["datasets"][name] = rows
        print(json.dumps({name: rows}, indent=1))
    report["load_after"] = os.getloadavg()
    print("load", report["load_before"], "->", report["load_after"])
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
