"""Fault drill of the online system: kill -9 of the whole process at random moments (resumed
each time), back-end stalls, back-end crashes, front-end tasks that loop for ever (``hang``:
the watchdog abandons them and stops their threads) and Ray actor kills, each over one run of
``--tasks`` tasks, compared with an uninterrupted run of the same tasks.

    python benchmarks/bench_faults.py                       # 100 tasks, 5 kills, every drill
    python benchmarks/bench_faults.py --tasks 20 --drills kill9 crash --json faults.json

Every run is ``edgerecon run`` in a subprocess (a kill -9 is a real one) on a small synthetic
dataset (the ``demo`` preset at 320x240, one timestamp per task, written once in ``--work``),
with a fixed configuration (``--fixed 0.8``, all cameras: the optimizer's choices depend on
timings, the clouds of a fixed configuration do not) and background updates on.

Columns per drill: tasks recorded, lost (timestamps never recorded), duplicated (recorded
twice), files that do not parse (metrics lines, state.json, summary.json, every PLY, every
task's merged cloud composed from its foreground and background version),
failed tasks, degraded tasks, background continuity (the version never goes back, and after
every resume or back-end restart a newer background is merged: "advanced/boundaries"), and
how many tasks equal the uninterrupted run's (same configuration; same foreground cloud,
point for point; timing fields and the background part aside).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import print_rows, report_header, write_report
from edgerecon.io.ply import read_ply
from edgerecon.runtime.messages import BgVersion
from edgerecon.viewer.rundir import RunFolder

CONFIG_KEYS = ("status", "phase", "scale", "camera_ids", "num_cameras")
CLOUD_KEYS = ("num_sparse", "num_sparse_fg", "num_fg_points", "num_objects")


def make_dataset(work: Path, num_frames: int) -> Path:
    from edgerecon.synth import preset_config, write_dataset

    root = work / f"scene-{num_frames}"
    if not (root / "dataset.json").exists():
        config = preset_config(
            "demo", width=320, height=240, num_frames=num_frames, background_frames=12, seed=7
        )
        write_dataset(config, root, overwrite=True)
    return root


def run_command(root: Path, out: Path, tasks: int, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-c",
        "import sys; from edgerecon.cli import main; sys.exit(main())",
        "run",
        "--dataset",
        str(root),
        "--out",
        str(out),
        "--deadline",
        "20",  # generous waits for masks and golden references on a busy machine
        "--fixed",
        "0.8",
        "--background-scale",
        "0.5",  # background updates on, rebuilt often enough to see them advance
        "--frames",
        f"0:{tasks}",
        *extra,
    ]


def committed(out: Path) -> int:
    try:
        return int(json.loads((out / "state.json").read_text())["tasks_done"])
    except (OSError, ValueError, KeyError):
        return 0


def run_to_end(cmd: list[str], log: Path) -> tuple[int, float]:
    t0 = time.perf_counter()
    with open(log, "a") as f:
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, check=False).returncode
    return rc, time.perf_counter() - t0


def kill9_drill(
    root: Path, out: Path, tasks: int, kills: int, rng: random.Random, log: Path
) -> dict[str, Any]:
    """Start, kill -9 the whole process group at ``kills`` moments (one during the set-up,
    the others after random numbers of committed tasks plus a random delay into the next
    task), resume each time, then run to the end."""
    targets = sorted(rng.sample(range(max(1, tasks // 20), max(2, tasks * 85 // 100)), kills - 1))
    boundaries = []
    cmd = run_command(root, out, tasks, "--overwrite")
    t0 = time.perf_counter()
    for k, target in enumerate([None, *targets]):
        with open(log, "a") as f:
            proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
        if target is None:
            time.sleep(2.0 + rng.random())  # during the set-up: nothing committed yet
        else:
            while committed(out) < target and proc.poll() is None:
                time.sleep(0.05)
            time.sleep(rng.random() * 1.5)  # somewhere inside the next task
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        boundaries.append(committed(out))
        print(f"  kill -9 #{k + 1} after {boundaries[-1]} committed tasks", flush=True)
        cmd = run_command(root, out, tasks, "--resume")
    rc, _ = run_to_end(cmd, log)
    return {"rc": rc, "wall_s": time.perf_counter() - t0, "boundaries": boundaries}


def fault_drill(
    root: Path, out: Path, tasks: int, kind: str, seconds: float, log: Path, *extra: str
) -> dict[str, Any]:
    at = [tasks * k // 10 for k in (2, 5, 8)]
    faults = [x for t in at for x in ("--inject-fault", f"{t}:{kind}:{seconds:g}")]
    rc, wall = run_to_end(run_command(root, out, tasks, "--overwrite", *faults, *extra), log)
    return {"rc": rc, "wall_s": wall, "boundaries": at}


def read_run(out: Path) -> tuple[list[dict[str, Any]], int]:
    """The metrics lines and how many files do not parse."""
    bad = 0
    lines: list[dict[str, Any]] = []
    text = (out / "metrics.jsonl").read_text() if (out / "metrics.jsonl").exists() else ""
    for line in text.splitlines():
        try:
            lines.append(json.loads(line))
        except ValueError:
            bad += 1
    for name in ("state.json", "summary.json"):
        try:
            json.loads((out / name).read_text())
        except (OSError, ValueError):
            bad += 1
    plys = [*out.glob("tasks/*/fg.ply"), *out.glob("backgrounds/*.ply")]
    for ply in [*plys, *out.glob("background.ply")]:
        try:
            read_ply(ply)
        except Exception:
            bad += 1
    run = RunFolder(out)
    for x in lines:  # every recorded task's merged cloud composes (its background exists)
        if x.get("status") == "ok" and run.cloud(x["time_index"]) is None:
            bad += 1
    return lines, bad


def foreground(out: Path, t: int) -> np.ndarray:
    cloud = RunFolder(out).cloud(t)
    assert cloud is not None and cloud.labels is not None
    return cloud.points3D[cloud.labels > 0]


def score(
    name: str, out: Path, tasks: int, drill: dict[str, Any], base: Path | None
) -> dict[str, Any]:
    lines, bad = read_run(out)
    times = [x["time_index"] for x in lines]
    versions: list[BgVersion] = []
    for x in lines:  # a failed task merges no background: it holds the one before it
        held = versions[-1] if versions else BgVersion()
        ok = x["status"] == "ok"
        versions.append(BgVersion(x.get("bg_epoch", 0), x["bg_version"]) if ok else held)
    monotone = all(a <= b for a, b in itertools.pairwise(versions))
    advanced = 0
    for b in drill["boundaries"]:
        held = versions[b - 1] if 0 < b <= len(versions) else BgVersion()
        advanced += any(v > held for v in versions[b:])
    row: dict[str, Any] = {
        "drill": name,
        "tasks": len(lines),
        "lost": len(set(range(tasks)) - set(times)),
        "duplicated": len(times) - len(set(times)),
        "unparsable": bad,
        "failed": sum(x["status"] != "ok" for x in lines),
        "degraded": sum(bool(x.get("degraded")) for x in lines),
        "bg_monotone": monotone,
        "bg_advanced": f"{advanced}/{len(drill['boundaries'])}",
        "final_bg": str(versions[-1]) if versions else "-",
        "exit": drill["rc"],
        "wall_s": round(drill["wall_s"], 1),
    }
    if base is not None:
        ref = {x["time_index"]: x for x in read_run(base)[0]}
        same_cfg = same_cloud = 0
        for x in lines:
            r = ref.get(x["time_index"])
            if r is None or any(x[k] != r[k] for k in CONFIG_KEYS):
                continue
            same_cfg += 1
            if all(x[k] == r[k] for k in CLOUD_KEYS) and np.array_equal(
                foreground(out, x["time_index"]), foreground(base, x["time_index"])
            ):
                same_cloud += 1
        row["equal_config"] = f"{same_cfg}/{len(ref)}"
        row["equal_cloud"] = f"{same_cloud}/{len(ref)}"
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=int, default=100, help="tasks per run (one per timestamp)")
    ap.add_argument("--kills", type=int, default=5, help="kill -9 moments of the kill9 drill")
    ap.add_argument(
        "--drills",
        nargs="+",
        default=["kill9", "stall", "crash", "hang", "ray"],
        choices=["kill9", "stall", "crash", "hang", "ray"],
    )
    ap.add_argument("--stall-s", type=float, default=12.0, help="seconds of each back-end stall")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default="/tmp/edgerecon-bench/faults")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if args.kills < 1 or args.tasks < 10:
        ap.error("--kills >= 1 and --tasks >= 10")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    rng = random.Random(args.seed)
    root = make_dataset(work, args.tasks)
    log = work / "runs.log"
    print(f"dataset {root}; logs in {log}", flush=True)
    base = work / "uninterrupted"
    rc, wall = run_to_end(run_command(root, base, args.tasks, "--overwrite"), log)
    rows = [
        score("uninterrupted", base, args.tasks, {"rc": rc, "wall_s": wall, "boundaries": []}, None)
    ]
    print(f"uninterrupted: {wall:.0f} s", flush=True)
    for name in args.drills:
        out = work / name
        if name == "kill9":
            drill = kill9_drill(root, out, args.tasks, args.kills, rng, log)
        elif name == "stall":
            drill = fault_drill(root, out, args.tasks, "stall", args.stall_s, log)
        elif name == "crash":
            drill = fault_drill(root, out, args.tasks, "crash", 0.0, log)
        elif name == "hang":
            # the front-end's task loops for ever: a 15 s watchdog instead of 10 x 20 s
            config = work / "hang.toml"
            config.write_text("[runtime]\ntask_timeout_s = 15.0\n")
            drill = fault_drill(root, out, args.tasks, "hang", 0.0, log, "--config", str(config))
        else:
            drill = fault_drill(root, out, args.tasks, "kill", 0.0, log, "--engine", "ray")
        rows.append(score(name, out, args.tasks, drill, base))
        print(f"{name}: {drill['wall_s']:.0f} s", flush=True)
    cols = [
        "drill",
        "tasks",
        "lost",
        "duplicated",
        "unparsable",
        "failed",
        "degraded",
        "bg_monotone",
        "bg_advanced",
        "final_bg",
        "equal_config",
        "equal_cloud",
        "exit",
        "wall_s",
    ]
    print_rows(f"fault drill: {args.tasks} tasks per run, {args.kills} kill -9 moments", cols, rows)
    if args.json:
        write_report(args.json, {**report_header(), "tasks": args.tasks, "rows": rows})
        print(f"report: {args.json}")


if __name__ == "__main__":
    main()
