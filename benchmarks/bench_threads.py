"""Memory kept per thread: a thread made per call against threads that last.

    python benchmarks/bench_threads.py
    python benchmarks/bench_threads.py --calls 6000 --json threads.json

Each way of running one call's work runs in a process of its own (malloc tuned as a long
run's: ``runtime.memory.tune_malloc``), ``--warm`` calls first and then ``--calls`` more; the
resident memory after each stretch is read once the heap is trimmed (``malloc_trim``), and
the growth per 1000 calls is printed. The work is a slice of what the stages do per camera
(OpenCV's resize, blur, colour conversion and remap of a 1280x720 frame, a NumPy reduction).

* ``thread``: a new thread per call (a task's thread, ``call_bounded``, before);
* ``pool-per-call``: a new two-thread pool per call, the work on it (the stages' pools,
  before);
* ``runner``: the calls on one thread that lasts (``runtime.interrupt.Runner``);
* ``pool``: the calls' work on the caller's lasting pool (``edgerecon.threads.thread_map``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from _report import print_rows, report_header, write_report

MODES = ("thread", "pool-per-call", "runner", "pool")


def _child(mode: str, warm: int, calls: int) -> dict[str, Any]:
    import cv2
    import numpy as np

    from edgerecon.runtime import memory
    from edgerecon.runtime.interrupt import Runner
    from edgerecon.threads import thread_map

    memory.tune_malloc(mmap_threshold=memory.MMAP_THRESHOLD)
    trim = memory._malloc_trim()
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8)
    mapx = rng.uniform(0, 639, (360, 640)).astype(np.float32)
    mapy = rng.uniform(0, 359, (360, 640)).astype(np.float32)

    def work(_: object = None) -> float:
        small = cv2.resize(frame, (640, 360), interpolation=cv2.INTER_AREA)
        grey = cv2.cvtColor(cv2.GaussianBlur(small, (5, 5), 0), cv2.COLOR_BGR2GRAY)
        warped = cv2.remap(grey, mapx, mapy, cv2.INTER_LINEAR)
        return float(np.mean(warped))

    runner = Runner("bench")

    def one() -> None:
        if mode == "thread":
            th = threading.Thread(target=work)
            th.start()
            th.join()
        elif mode == "pool-per-call":
            with ThreadPoolExecutor(2) as pool:
                list(pool.map(work, range(2)))
        elif mode == "runner":
            runner.call(work, 60.0)
        else:
            thread_map(work, range(2), 2)

    def resident() -> float:
        if trim is not None:
            trim(0)
        mb = memory.resident_mb()
        return float("nan") if mb is None else mb

    for _ in range(warm):
        one()
    before = resident()
    threads_before = threading.active_count()
    for _ in range(calls):
        one()
    after = resident()
    return {
        "mode": mode,
        "calls": calls,
        "rss_before_mb": round(before, 1),
        "rss_after_mb": round(after, 1),
        "kb_per_call": round((after - before) * 1024 / calls, 3),
        "mb_per_1000_calls": round((after - before) * 1000 / calls, 2),
        "threads_alive": threading.active_count() - threads_before,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--calls", type=int, default=4000)
    ap.add_argument("--warm", type=int, default=500)
    ap.add_argument("--json", default=None)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(args.child, args.warm, args.calls)))
        return
    header = report_header()
    print(json.dumps(header))
    rows = []
    for mode in args.modes:
        cmd = [sys.executable, __file__, "--child", mode]
        cmd += ["--calls", str(args.calls), "--warm", str(args.warm)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    print_rows(
        f"resident memory kept, {args.calls} calls after {args.warm}",
        ["mode", "calls", "rss_before_mb", "rss_after_mb", "kb_per_call", "mb_per_1000_calls"],
        rows,
    )
    if args.json:
        write_report(args.json, {"header": header, "rows": rows})


if __name__ == "__main__":
    main()
