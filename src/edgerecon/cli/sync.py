"""``edgerecon sync``: are a dataset's cameras synchronised? Estimates each camera's offset from
what the cameras see move (``io.sync``), compares it with the dataset's own, and with
``--write`` stores the estimate in ``dataset.json``."""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any

import numpy as np

from edgerecon.cli._common import (
    add_json_flag,
    console,
    dataset_to_check,
    emit_json,
    print_table,
)
from edgerecon.io.dataset import DESCRIPTOR
from edgerecon.io.ply import atomic_write_text
from edgerecon.io.sync import SyncConfig, SyncResult, estimate_offsets


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sync",
        help="check the cameras' synchronisation from what they see move; --write fixes it",
        description="Estimate every camera's frame offset from the motion the cameras see "
        "(GCC-PHAT between their motion signals over the first --window seconds; see "
        "`edgerecon import --offset auto`), compare it with the offsets the dataset has, and "
        "with --write store the estimate in its dataset.json. Exit code 3 when a camera is "
        "out of sync by more than a frame.",
    )
    p.add_argument("--dataset", required=True, metavar="DIR", help="dataset folder")
    p.add_argument(
        "--window",
        type=float,
        default=SyncConfig.window_s,
        metavar="S",
        help=f"stream seconds read from the start (default {SyncConfig.window_s:g})",
    )
    p.add_argument(
        "--max-offset",
        type=float,
        default=SyncConfig.max_offset_s,
        metavar="S",
        help=f"largest offset searched, seconds (default {SyncConfig.max_offset_s:g})",
    )
    p.add_argument(
        "--write",
        action="store_true",
        help="write the estimated offsets into dataset.json (a camera it cannot link keeps its "
        "offset relative to the others)",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def compare(
    current: dict[str, int], result: SyncResult
) -> tuple[dict[str, int], dict[str, int | None]]:
    """(new offsets, change per camera): the estimate for the linked cameras; an unlinked one
    keeps its current offset, moved with the linked cameras' median change (None: no change
    known). Both sets normalised to start at 0."""
    linked = [n for n in current if n not in result.unlinked]
    cur0 = min(current.values())
    est0 = min(result.offsets[n] for n in linked) if linked else 0
    change = {
        n: (result.offsets[n] - est0) - (current[n] - cur0) if n in linked else None
        for n in current
    }
    shift = int(np.median([c for c in change.values() if c is not None])) if linked else 0
    new = {
        n: result.offsets[n] - est0 if n in linked else current[n] - cur0 + shift for n in current
    }
    low = min(new.values())
    return {n: k - low for n, k in new.items()}, change


def run(args: argparse.Namespace) -> int:
    ds = dataset_to_check(args.dataset, write=args.write, what="write offsets into")
    config = SyncConfig(window_s=args.window, max_offset_s=args.max_offset)
    raw = dataclasses.replace(ds.frames, offsets=(), rectify=())
    with raw.open(missing="skip_camera") as source:
        result = estimate_offsets(source, config, progress=not args.json)
    current = {n: 0 for n in ds.rig.names} | dict(ds.frames.offsets)
    new, change = compare(current, result)
    out_of_sync = sorted(n for n, c in change.items() if c is not None and abs(c) > 1)
    written = None
    if args.write:
        descriptor = ds.root / DESCRIPTOR
        data = json.loads(descriptor.read_text())
        offsets = {n: k for n, k in new.items() if k}
        if offsets:
            data["frames"]["offsets"] = offsets
        else:
            data["frames"].pop("offsets", None)
        atomic_write_text(descriptor, json.dumps(data, indent=2) + "\n")
        written = str(descriptor)
    report: dict[str, Any] = {
        "dataset": str(ds.root),
        "current": current,
        "estimated": result.offsets,
        "new": new,
        "change": change,
        "out_of_sync": out_of_sync,
        "written": written,
        **{k: v for k, v in result.to_dict().items() if k not in ("offsets",)},
    }
    if args.json:
        emit_json(report)
    else:
        _print(report, result)
    return 3 if out_of_sync and not args.write else 0


def _print(report: dict[str, Any], result: SyncResult) -> None:
    print_table(
        f"synchronisation from motion ({result.frames_read} frames, {result.seconds:.1f} s)",
        ["camera", "offset now", "estimated", "change (frames)", "linked by"],
        [
            [
                n,
                report["current"][n],
                "-" if n in result.unlinked else report["new"][n],
                "?" if report["change"][n] is None else f"{report['change'][n]:+d}",
                "nothing" if n in result.unlinked
                else "consensus" if n in result.joined else "pairs",
            ]
            for n in report["current"]
        ],
    )  # fmt: skip
    print_table(
        "camera pairs (lag in time indices; peak and next peak in robust sigma)",
        ["pair", "lag", "peak", "next", "used"],
        [
            [f"{p.a}-{p.b}", p.lag, f"{p.peak:.1f}", f"{p.second:.1f}", "yes" if p.used else "-"]
            for p in result.pairs
        ],
    )
    if result.unlinked:
        console.print(
            f"[yellow]not linked:[/] {', '.join(result.unlinked)} (too little motion seen by "
            "it and the others in the window); its offset is not checked",
            soft_wrap=True,
        )
    if report["out_of_sync"]:
        console.print(
            f"[yellow]out of sync by more than a frame:[/] {', '.join(report['out_of_sync'])}",
            soft_wrap=True,
        )
    else:
        console.print("the linked cameras are in sync (within a frame)")
    if report["written"]:
        console.print(f"wrote the offsets into {report['written']}", soft_wrap=True)
