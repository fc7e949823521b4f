"""``edgerecon select-cameras``: the camera subsets pi(N') (problem P2) of a dataset frame's
sparse cloud, or of a saved visibility matrix."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from edgerecon.cli._common import add_json_flag, emit_json, print_table
from edgerecon.optimize.selection import CameraSelector, SelectionConfig
from edgerecon.types import DataError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "select-cameras",
        help="choose the camera subset for every subset size (problem P2)",
        description="Maximise the sparse points seen by >= 2 chosen cameras for every N' "
        "from N down to 3. SOURCE is a dataset folder (the sparse cloud of --frame at "
        "--scale is reconstructed first) or a .npy file holding a (points x cameras) boolean "
        "visibility matrix.",
    )
    p.add_argument("source", help="dataset folder or visibility .npy file")
    p.add_argument(
        "--time",
        "-t",
        "--frame",
        dest="frame",
        type=int,
        default=0,
        help="frame index (dataset; default 0)",
    )
    p.add_argument("--scale", type=float, default=1.0, help="image scale r (dataset; 1.0)")
    p.add_argument(
        "--solver",
        default="auto",
        choices=["auto", "brute_force", "enumerate", "cpsat", "milp", "local_search"],
        help="solver (default: auto, chosen per size)",
    )
    p.add_argument(
        "--available", type=int, nargs="+", help="camera ids that may be chosen (default all)"
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def _load(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    src = Path(args.source)
    if src.suffix == ".npy":
        if not src.is_file():
            raise DataError(f"visibility file not found: {src}")
        try:
            vis = np.load(src, allow_pickle=False)
        except ValueError as exc:
            raise DataError(f"{src}: not a NumPy array file ({exc})") from None
        return vis, None, None
    from edgerecon.io.dataset import open_dataset
    from edgerecon.sparse import reconstruct_sparse
    from edgerecon.views import prepare_views

    ds = open_dataset(src)
    if not 0 <= args.frame < ds.num_frames:
        raise DataError(f"--frame {args.frame} out of range 0..{ds.num_frames - 1}")
    with ds.open_frames() as frames:
        fs = frames.read(args.frame)
    try:
        views = prepare_views(fs, ds.rig, args.scale)
    except ValueError as exc:
        raise DataError(str(exc)) from None
    rec = reconstruct_sparse(views)
    dirs = np.array([c.viewing_direction for c in ds.rig])
    return rec.visibility_matrix(len(ds.rig)), ds.rig.centers, dirs


def run(args: argparse.Namespace) -> int:
    vis, centers, dirs = _load(args)
    selector = CameraSelector(
        vis,
        SelectionConfig(solver=args.solver),
        available=args.available,
        camera_centers=centers,
        viewing_directions=dirs,
    )
    mapping = selector.mapping()
    if args.json:
        emit_json({"source": args.source, "mapping": mapping.to_dict()})
        return 0
    print_table(
        f"{args.source}: {mapping.num_points} points, {mapping.num_coverable} seen by >= 2 "
        f"cameras, criterion {mapping.criterion}",
        ["N'", "cameras", "covered", "share", "solver", "optimal"],
        [
            [
                k,
                " ".join(map(str, mapping(k))),
                mapping.selection(k).covered,
                mapping.coverage_fraction(k),
                mapping.selection(k).solver,
                "yes" if mapping.selection(k).optimal else "no",
            ]
            for k in mapping.sizes
        ],
    )
    return 0
