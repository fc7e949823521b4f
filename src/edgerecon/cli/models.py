"""``edgerecon models``: the learned models edgerecon can use and where they are;
``edgerecon models fetch`` gets them (``scene.people``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from edgerecon.cli._common import add_json_flag, console, emit_json
from edgerecon.scene.people import (
    PERSON_MODEL_FILE,
    PERSON_MODEL_SOURCES,
    PersonSegmenter,
    fetch_person_model,
    is_measured_model,
    models_dir,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "models",
        help="the learned person model: where it is, or fetch it",
        description="Without an action: where edgerecon keeps its models ($EDGERECON_MODELS, "
        "else ~/.cache/edgerecon/models) and whether the person segmentation model is there "
        "and intact. `fetch`: take it from MediaPipe's wheel on the package index (pip "
        "download; about 35 MB once, 250 kB kept) or from --wheel FILE, and check its "
        "SHA-256. The scene stage then adds its masks where the background models learned "
        "from the stream (no clip of the empty scene): people who sit or stand still from "
        "the first frame are foreground ([runtime.foreground] person_model).",
    )
    p.add_argument("action", nargs="?", choices=("list", "fetch"), default="list")
    p.add_argument(
        "--wheel",
        type=Path,
        default=None,
        metavar="FILE",
        help="fetch: a MediaPipe 0.10.14-0.10.21 wheel already downloaded (no network)",
    )
    p.add_argument(
        "--dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="where to keep the models (default: $EDGERECON_MODELS or ~/.cache/edgerecon/models; "
        "edgerecon looks there through $EDGERECON_MODELS)",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def status(folder: Path) -> dict[str, Any]:
    """What ``folder`` holds of the person model."""
    path = folder / PERSON_MODEL_FILE
    info: dict[str, Any] = {
        "models_dir": str(folder),
        "person_model": {
            "file": str(path),
            "present": path.is_file(),
            "sha256_ok": None,
            "loads": None,
            "sources": list(PERSON_MODEL_SOURCES),
        },
    }
    if path.is_file():
        pm = info["person_model"]
        pm["sha256_ok"] = is_measured_model(path)
        try:
            PersonSegmenter(path)
            pm["loads"] = True
        except Exception as exc:  # reported, not raised: this command describes
            pm["loads"] = False
            pm["error"] = str(exc)
    return info


def run(args: argparse.Namespace) -> int:
    folder = models_dir() if args.dir is None else args.dir
    if args.action == "fetch":
        fetch_person_model(folder, wheel=args.wheel)
    info = status(folder)
    pm = info["person_model"]
    if args.json:
        emit_json(info)
    else:
        console.print(f"models: {folder}", soft_wrap=True)
        if not pm["present"]:
            console.print(
                f"person segmentation ({PERSON_MODEL_FILE}): not fetched; "
                "`edgerecon models fetch` gets it",
                soft_wrap=True,
            )
        else:
            state = (
                "ready"
                if pm["sha256_ok"] and pm["loads"]
                else "changed (SHA-256 differs): fetch it again"
                if not pm["sha256_ok"]
                else f"does not load: {pm.get('error', '')}"
            )
            console.print(f"person segmentation ({PERSON_MODEL_FILE}): {state}", soft_wrap=True)
    ok = pm["present"] and pm["sha256_ok"] and pm["loads"]
    return 0 if ok or args.action == "list" else 1
