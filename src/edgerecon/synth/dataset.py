"""Write a synthetic scene as a dataset folder (docs/ARCHITECTURE.md, "Dataset descriptor")
with its ground truth ("Ground truth folder").

Layout::

    dataset.json                    descriptor (written last: a folder without it is partial)
    rig.json                        Rig.to_dict()
    frames/camK/000000.png ...      the sequence (or frames/camK.avi with video=True)
    background/camK/000000.png ...  the empty scene before the sequence (background_frames)
    gt/                             ground truth, see groundtruth.py
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon import progress
from edgerecon.io.dataset import write_dataset_descriptor
from edgerecon.io.ply import atomic_write_bytes, atomic_write_text, write_ply
from edgerecon.synth.groundtruth import GT_FORMAT, GT_VERSION, sample_visible_cloud
from edgerecon.synth.render import Renderer
from edgerecon.synth.scene import SceneConfig, SynthScene, build_scene
from edgerecon.types import DataError, StageTimings

logger = logging.getLogger(__name__)

DATASET_FORMAT = "edgerecon-dataset"
FRAME_PATTERN = "frames/{camera}/{{index:06d}}.png"
BACKGROUND_PATTERN = "background/{camera}/{{index:06d}}.png"
VIDEO_FOURCC = "FFV1"  # lossless; decoded by OpenCV's FFmpeg backend

GT_FILES = {
    "background_depth": "background/depth_{camera}.npy",
    "background_cloud": "background.ply",
    "mask": "masks/{camera}/{index:06d}.png",
    "foreground_depth": "depth/{camera}/{index:06d}.npy",
    "foreground_cloud": "foreground/{index:06d}.ply",
}


@dataclass(frozen=True, kw_only=True)
class DatasetSummary:
    """What ``write_dataset`` wrote."""

    path: Path
    name: str
    num_cameras: int
    num_frames: int
    background_frames: int
    image_size: tuple[int, int]
    """(width, height) in pixels."""
    num_background_points: int
    """Points of the background ground-truth cloud (all visible, any number of views)."""
    num_foreground_points: list[int]
    """Points of the foreground ground-truth cloud per timestamp."""
    stretches: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    """The difficult stretches (``SynthScene.stretches``: still, away, seated, dimming)."""
    timings: StageTimings = field(default_factory=StageTimings)

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "name": self.name,
            "num_cameras": self.num_cameras,
            "num_frames": self.num_frames,
            "background_frames": self.background_frames,
            "image_size": list(self.image_size),
            "num_background_points": self.num_background_points,
            "num_foreground_points": self.num_foreground_points,
            "stretches": self.stretches,
            "seconds": self.timings.to_dict(),
        }


def _imwrite(path: Path, image: NDArray[np.uint8]) -> None:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - OpenCV failure
        raise DataError(f"could not encode {path}")
    atomic_write_bytes(path, lambda f: f.write(buf.tobytes()))


def _npy_write(path: Path, array: NDArray[Any]) -> None:
    atomic_write_bytes(path, lambda f: np.save(f, array, allow_pickle=False))


def _prepare_folder(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise DataError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise DataError(f"{out} is not empty (use overwrite / --overwrite to replace it)")
        desc = out / "dataset.json"
        ours = (out / "gt" / "scene.json").is_file() or (
            desc.is_file() and '"edgerecon-dataset"' in desc.read_text(errors="ignore")
        )
        if not ours:
            raise DataError(
                f"{out} is not empty and not a synthetic dataset: refusing to replace it"
            )
        for child in ("frames", "background", "gt", "rig.json", "dataset.json"):
            p = out / child
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)


def write_dataset(
    scene: SynthScene | SceneConfig,
    out_dir: str | Path,
    *,
    video: bool = False,
    overwrite: bool = False,
    threads: int = 2,
) -> DatasetSummary:
    """Render ``scene`` and write it with its ground truth into ``out_dir``."""
    if isinstance(scene, SceneConfig):
        scene = build_scene(scene)
    out = Path(out_dir)
    _prepare_folder(out, overwrite)
    timings = StageTimings()
    config = scene.config
    rig = scene.rig
    names = rig.names
    renderer = Renderer(scene, threads=threads)
    with timings.stage("prepare"):
        renderer.prepare()
    rays = [renderer.rays(i) for i in range(len(rig))]
    pending: list[Future[Any]] = []
    writers: dict[str, cv2.VideoWriter] = {}
    fg_counts: list[int] = []
    gt = out / "gt"
    with ThreadPoolExecutor(max_workers=max(1, threads)) as io_pool:

        def submit(fn: Callable[..., Any], *args: Any) -> None:
            pending.append(io_pool.submit(fn, *args))

        # ---- the background-only clip
        for b in progress.track(range(config.background_frames), "background clip"):
            with timings.stage("render"):
                frame = renderer.render(b - config.background_frames)
            for name, image in zip(names, frame.images, strict=True):
                submit(
                    _imwrite, out / BACKGROUND_PATTERN.format(camera=name).format(index=b), image
                )
        # ---- ground truth of the static scene
        with timings.stage("gt_background"):
            bg_depths = [renderer.background_depth(i) for i in range(len(rig))]
            zero_masks = [np.zeros(d.shape, np.uint8) for d in bg_depths]
            bg_clean = [renderer.background_clean(i) for i in range(len(rig))]
            bg_cloud = sample_visible_cloud(
                rig,
                rays,
                bg_depths,
                zero_masks,
                bg_clean,
                voxel_m=config.gt_voxel_background_m,
                part="background",
            )
            for name, depth in zip(names, bg_depths, strict=True):
                submit(_npy_write, gt / GT_FILES["background_depth"].format(camera=name), depth)
            submit(write_ply, gt / GT_FILES["background_cloud"], bg_cloud)
        # ---- the sequence
        positions: list[dict[str, list[float]]] = []
        for t in progress.track(range(config.num_frames), "rendering"):
            with timings.stage("render"):
                frame = renderer.render(t, clean=True)
            with timings.stage("gt_foreground"):
                assert frame.clean is not None
                cloud = sample_visible_cloud(
                    rig,
                    rays,
                    frame.depths,
                    frame.masks,
                    frame.clean,
                    voxel_m=config.gt_voxel_foreground_m,
                    part="foreground",
                )
                fg_counts.append(len(cloud))
            submit(write_ply, gt / GT_FILES["foreground_cloud"].format(index=t), cloud)
            positions.append(
                {str(a.actor_id): a.position(t).round(5).tolist() for a in scene.actors_at(t)}
            )
            for name, image, depth, mask in zip(
                names, frame.images, frame.depths, frame.masks, strict=True
            ):
                if video:
                    with timings.stage("video"):
                        _video_writer(writers, out, name, image, config.fps).write(image)
                else:
                    submit(_imwrite, out / FRAME_PATTERN.format(camera=name).format(index=t), image)
                submit(_imwrite, gt / GT_FILES["mask"].format(camera=name, index=t), mask)
                fg = mask > 0
                if fg.any():
                    values = np.ascontiguousarray(depth[fg])
                    submit(
                        _npy_write,
                        gt / GT_FILES["foreground_depth"].format(camera=name, index=t),
                        values,
                    )
            # Bound the memory held by queued writes.
            if len(pending) > 8 * len(names):
                with timings.stage("write_wait"):
                    for f in pending:
                        f.result()
                pending.clear()
        with timings.stage("write_wait"):
            for f in pending:
                f.result()
    for w in writers.values():
        w.release()

    stretches = scene.stretches()
    meta = {
        "format": GT_FORMAT,
        "version": GT_VERSION,
        "name": config.name,
        "num_frames": config.num_frames,
        "background_frames": config.background_frames,
        "fps": config.fps,
        "unit": "m",
        "depth": "float32 metres along the optical axis (Camera.project's depth), distorted pixels",
        "mask": "uint8 object id: 0 = static background, k = actor k",
        "files": GT_FILES,
        "voxel_m": {
            "foreground": config.gt_voxel_foreground_m,
            "background": config.gt_voxel_background_m,
        },
        "actors": [
            {
                "id": a.actor_id,
                "enter_frame": a.enter_frame,
                "leave_frame": a.leave_frame,
                "presence": [list(p) for p in a.presence] or [[a.enter_frame, a.leave_frame]],
            }
            for a in scene.actors
        ],
        "stretches": stretches,
        "actor_positions": positions,
        "rig": rig.to_dict(),
        "config": config.to_dict(),
        "scene": scene.describe(),
    }
    atomic_write_text(gt / "scene.json", json.dumps(meta, indent=1))
    if video:
        frames_desc = {"kind": "video", "cameras": {n: f"frames/{n}.avi" for n in names}}
    else:
        frames_desc = {
            "kind": "images",
            "cameras": {n: FRAME_PATTERN.format(camera=n) for n in names},
        }
    background_desc = None
    if config.background_frames:
        background_desc = {
            "kind": "images",
            "cameras": {n: BACKGROUND_PATTERN.format(camera=n) for n in names},
        }
    # The descriptor goes last: a folder without it is an unfinished dataset.
    write_dataset_descriptor(
        out,
        rig=rig,
        frames=frames_desc,
        name=config.name,
        background=background_desc,
        fps=config.fps,
        ground_truth="gt",
    )
    cam = rig[0]
    return DatasetSummary(
        path=out,
        name=config.name,
        num_cameras=len(rig),
        num_frames=config.num_frames,
        background_frames=config.background_frames,
        image_size=(cam.width, cam.height),
        num_background_points=len(bg_cloud),
        num_foreground_points=fg_counts,
        stretches=stretches,
        timings=timings,
    )


def _video_writer(
    writers: dict[str, cv2.VideoWriter], out: Path, name: str, image: NDArray[np.uint8], fps: float
) -> cv2.VideoWriter:
    w = writers.get(name)
    if w is None:
        path = out / "frames" / f"{name}.avi"
        path.parent.mkdir(parents=True, exist_ok=True)
        h, wd = image.shape[:2]
        w = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*VIDEO_FOURCC), fps, (wd, h))
        if not w.isOpened():
            raise DataError(f"cannot write video {path} (codec {VIDEO_FOURCC} unavailable)")
        writers[name] = w
    return w
