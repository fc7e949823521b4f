"""A real capture at another sensor size or orientation, its calibration transformed to match:
real content (noise, compression, real people) on the rig shapes the system is judged on
(1920x1080 landscape, 1080x1920 portrait phones) from the real data at hand.

    python benchmarks/resample_dataset.py --dataset caliscope_charuco --size 1920x1080 \\
        --out /tmp/cal1080
    python benchmarks/resample_dataset.py --dataset caliscope_charuco --size 1920x1080 \\
        --rotate 90 --out /tmp/cal1080p                     # portrait: 1080x1920

Every frame is resized to ``--size`` (bicubic) and then, with ``--rotate 90`` / ``270``,
turned clockwise / counter-clockwise, as a phone held upright records; each camera's K is
scaled with the image (pixel centres on each other, ``Camera.resized``), and a turn of the
image is a turn of the camera about its optical axis: R and t are turned with it and the
tangential distortion coefficients swap (the radial ones do not change). The frames are
written as MPEG-4 video (OpenCV's ``mp4v``: lossy again, like a phone's), one file per
camera; the world frame, unit and up direction stay, so the clouds of the source and of the
copy can be compared point for point. Printed: per camera the new size and focal length and
the largest difference, over points seen by the camera, between projecting with the new
camera and moving the source camera's projection through the same resize and turn (a check
of the transformed calibration, distortion included: about 1e-9 px).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from _report import SHARED, print_rows, report_header, write_report
from edgerecon import progress
from edgerecon.geometry.camera import Camera
from edgerecon.io.dataset import open_dataset, write_dataset_descriptor
from edgerecon.progress import track

#: A quarter turn clockwise of the image, as a map of homogeneous pixel coordinates of an
#: image of height h: (u, v) -> (h - 1 - v, u).
_QUARTER = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def turned(camera: Camera, quarters: int) -> Camera:
    """The camera whose image is ``camera``'s turned by ``quarters`` x 90 degrees clockwise
    (what ``cv2.rotate`` with ``ROTATE_90_CLOCKWISE`` gives, applied that many times)."""
    cam = camera
    for _ in range(quarters % 4):
        K = cam.K
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        # A K Q^-1 with A the pixel map: the focal lengths swap, the principal point turns.
        new_K = np.array([[fy, K[0, 1], cam.height - 1 - cy], [0.0, fx, cx], [0.0, 0.0, 1.0]])
        dist = np.array(cam.dist, np.float64).copy()
        dist[2], dist[3] = cam.dist[3], -cam.dist[2]  # p1' = p2, p2' = -p1
        cam = dataclasses.replace(
            cam,
            width=cam.height,
            height=cam.width,
            K=new_K,
            R=_QUARTER @ cam.R,
            t=_QUARTER @ cam.t,
            dist=dist,
        )
    return cam


def turn_pixels(uv: NDArray[np.float64], width: int, height: int, quarters: int) -> Any:
    """Pixel coordinates of an image ``width`` x ``height`` after ``quarters`` clockwise turns."""
    uv = uv.copy()
    for _ in range(quarters % 4):
        uv = np.stack([height - 1 - uv[:, 1], uv[:, 0]], axis=1)
        width, height = height, width
    return uv


def check_camera(source: Camera, new: Camera, size: tuple[int, int], quarters: int) -> float:
    """The largest pixel difference between ``new``'s projection and ``source``'s moved
    through the resize and the turns, over points spread in ``source``'s view."""
    rng = np.random.default_rng(0)
    w, h = source.width, source.height
    pix = rng.uniform([0.1 * w, 0.1 * h], [0.9 * w, 0.9 * h], size=(500, 2))
    depth = rng.uniform(0.5, 5.0, size=500) * float(np.linalg.norm(source.center) or 1.0)
    pts = source.backproject(pix, depth)
    uv, _ = source.project(pts)
    sx, sy = size[0] / w, size[1] / h
    moved = np.stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5], axis=1)
    moved = turn_pixels(moved, size[0], size[1], quarters)
    got, _ = new.project(pts)
    return float(np.max(np.abs(got - moved)))


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--dataset", required=True, help="a name under ../shared/data or a folder")
    ap.add_argument("--size", required=True, help="WIDTHxHEIGHT before the turn")
    ap.add_argument("--rotate", type=int, default=0, choices=[0, 90, 180, 270])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--json", type=Path, default=None, help="write a JSON report")
    args = ap.parse_args()
    progress.enable()
    root = Path(args.dataset)
    if not (root / "dataset.json").exists() and (SHARED / args.dataset).exists():
        root = SHARED / args.dataset
    ds = open_dataset(root)
    width, height = (int(x) for x in args.size.lower().split("x"))
    quarters = args.rotate // 90
    rows = []
    cameras = []
    for cam in ds.rig.cameras:
        new = turned(cam.resized(width, height), quarters)
        cameras.append(new)
        rows.append(
            {
                "camera": cam.name,
                "source": f"{cam.width}x{cam.height}",
                "size": f"{new.width}x{new.height}",
                "focal_px": round(float(new.K[0, 0]), 1),
                "check_px": f"{check_camera(cam, new, (width, height), quarters):.1e}",
            }
        )
    rig = dataclasses.replace(ds.rig, cameras=tuple(cameras))
    out: Path = args.out
    (out / "videos").mkdir(parents=True, exist_ok=True)
    fps = ds.fps or 25.0
    t0 = time.perf_counter()
    writers = {
        cam.name: cv2.VideoWriter(
            str(out / "videos" / f"{cam.name}.mp4"),
            cv2.VideoWriter.fourcc(*"mp4v"),
            fps,
            (cam.width, cam.height),
        )
        for cam in rig.cameras
    }
    with ds.open_frames() as source:
        num = source.num_frames
        for t in track(range(num), f"frames of {ds.name}"):
            frames = source.read(t)
            for cam, image in zip(rig.cameras, frames.images, strict=True):
                if image is None:
                    raise SystemExit(f"time {t}: camera {cam.name} has no frame")
                img = cv2.resize(image, (width, height), interpolation=cv2.INTER_CUBIC)
                for _ in range(quarters):
                    img = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
                writers[cam.name].write(img)
    for w in writers.values():
        w.release()
    spec = {"kind": "video", "cameras": {c.name: f"videos/{c.name}.mp4" for c in rig.cameras}}
    write_dataset_descriptor(out, rig=rig, frames=spec, name=out.name, fps=ds.fps)
    title = f"{ds.name} -> {out} ({num} frames, {time.perf_counter() - t0:.0f} s)"
    print_rows(title, list(rows[0]), rows)
    if args.json:
        write_report(args.json, {**report_header(), "source": str(root), "cameras": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
