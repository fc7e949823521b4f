"""Board check on real data: the ChArUco corners of caliscope_charuco, triangulated from
``checks/charuco_corners_2d.csv`` with the rig's calibration, against the nearest point of a
dense cloud (median and max distance, mm), and the dense points over the board against the
corners' plane (``quality.board.board_surface``: how many, their median distance, the share
within 2 and 5 mm: the cloud's precision on a real surface).

    python benchmarks/bench_board.py                          # golden reconstruction at t=100
    python benchmarks/bench_board.py --times 96 100 104
    python benchmarks/bench_board.py --cloud out/dense.ply --times 100   # a cloud you have
    python benchmarks/bench_board.py --set consistency_rel_depth=0.005   # DenseConfig settings

Without ``--cloud`` each time index is reconstructed with the golden pipeline (r = 1; the
default settings and ``--set`` ones, read as the ``[reconstruction.dense_config]`` table of a
``--config`` file) in this process; CPU seconds of the reconstruction are printed with it.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

from _report import SHARED, report_header, with_settings
from edgerecon.config import ReconstructionConfig
from edgerecon.io.dataset import open_dataset
from edgerecon.io.ply import read_ply
from edgerecon.pipeline import reconstruct
from edgerecon.quality.board import (
    board_check,
    board_surface,
    read_corner_csv,
    triangulate_corners,
)

#: Points within this distance of the board's plane (metres) are the board's.
BAND_M = 0.03


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default=str(SHARED / "caliscope_charuco"))
    parser.add_argument("--times", type=int, nargs="+", default=[100])
    parser.add_argument("--cloud", help="a dense cloud (PLY) to check instead of reconstructing")
    parser.add_argument(
        "--set", action="append", default=[], metavar="FIELD=VALUE", help="a DenseConfig setting"
    )
    args = parser.parse_args()
    base = ReconstructionConfig()
    config = dataclasses.replace(
        base,
        dense_config=with_settings(base.dense_config, args.set, "reconstruction.dense_config"),
    )
    head = report_header()
    print(f"commit {head['commit']} load {os.getloadavg()}")
    ds = open_dataset(args.dataset)
    detections = read_corner_csv(Path(args.dataset) / "checks" / "charuco_corners_2d.csv", ds.rig)
    if args.set:
        print("settings:", " ".join(args.set))
    print(
        "time  corners  board rms mm  median mm  max mm  points  CPU s"
        "  board pts  plane med mm  <=2mm  <=5mm"
    )
    for t in args.times:
        corners = triangulate_corners(detections, ds.rig, t)
        cpu = float("nan")
        if args.cloud:
            cloud = read_ply(args.cloud)
        else:
            with ds.open_frames() as source:
                frames = source.read(t)
            c0 = time.process_time()
            result = reconstruct(frames, ds.rig, config)
            cpu = time.process_time() - c0
            assert result.dense is not None
            cloud = result.dense.cloud
        check = board_check(cloud, corners, t)
        surface = board_surface(cloud, corners, t, BAND_M)
        print(
            f"{t:4d}  {check.num_corners:7d}  {check.board_rms * 1e3:12.2f}  "
            f"{check.median * 1e3:9.2f}  {check.max * 1e3:6.2f}  {len(cloud):6d}  {cpu:5.1f}"
            f"  {surface.num_points:9d}  {surface.median * 1e3:12.2f}  "
            f"{surface.within(0.002):5.3f}  {surface.within(0.005):5.3f}"
        )


if __name__ == "__main__":
    main()
