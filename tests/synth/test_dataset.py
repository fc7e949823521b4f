"""Writing a synthetic dataset: the documented layout, read back by edgerecon.io."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from edgerecon.io import open_dataset
from edgerecon.synth import Renderer, preset_config, write_dataset
from edgerecon.types import DataError


def test_descriptor_and_files(small_dataset, small_scene):
    root = small_dataset.path
    desc = json.loads((root / "dataset.json").read_text())
    assert desc["format"] == "edgerecon-dataset" and desc["version"] == 1
    assert desc["rig"] == "rig.json" and desc["ground_truth"] == "gt"
    assert desc["frames"]["kind"] == "images"
    assert desc["frames"]["cameras"]["cam0"] == "frames/cam0/{index:06d}.png"
    assert desc["background"]["cameras"]["cam4"] == "background/cam4/{index:06d}.png"
    assert desc["fps"] == 25.0
    meta = json.loads((root / "gt" / "scene.json").read_text())
    assert meta["format"] == "edgerecon-synth-gt" and meta["num_frames"] == 4
    assert len(list((root / "frames" / "cam2").glob("*.png"))) == 4
    assert len(list((root / "background" / "cam2").glob("*.png"))) == 2
    # Frames are lossless: the PNG is exactly what the renderer produced.
    frame = Renderer(small_scene).render(1)
    png = cv2.imread(str(root / "frames" / "cam3" / "000001.png"))
    assert np.array_equal(png, frame.images[3])
    bg = Renderer(small_scene).render(-1)
    png = cv2.imread(str(root / "background" / "cam0" / "000001.png"))
    assert np.array_equal(png, bg.images[0])


def test_open_dataset_reads_it(small_dataset, small_scene):
    ds = open_dataset(small_dataset.path)
    assert ds.num_frames == 4 and ds.fps == 25.0
    assert ds.rig.names == small_scene.rig.names
    assert ds.ground_truth is not None and ds.ground_truth.name == "gt"
    assert ds.background is not None
    with ds.open_frames() as source:
        frames = source.read(2)
    assert len(frames) == 5 and frames.images[0].shape == (240, 320, 3)


def test_refuses_to_overwrite_foreign_folders(tmp_path):
    cfg = preset_config("demo", num_frames=1, background_frames=0, width=96, height=72)
    (tmp_path / "notes.txt").write_text("keep me")
    with pytest.raises(DataError, match="not empty"):
        write_dataset(cfg, tmp_path)
    with pytest.raises(DataError, match="not a synthetic dataset"):
        write_dataset(cfg, tmp_path, overwrite=True)
    assert (tmp_path / "notes.txt").read_text() == "keep me"
    out = tmp_path / "ds"
    write_dataset(cfg, out)
    summary = write_dataset(cfg, out, overwrite=True)  # our own dataset may be replaced
    assert summary.num_frames == 1 and (out / "dataset.json").is_file()


def test_video_output_is_lossless(tmp_path):
    cfg = preset_config("demo", num_frames=3, background_frames=0, width=96, height=72)
    write_dataset(cfg, tmp_path / "v", video=True)
    ds = open_dataset(tmp_path / "v")
    assert ds.frames.kind == "video" and ds.num_frames == 3
    with ds.open_frames() as source:
        got = source.read(2).images[1]
    from edgerecon.synth import build_scene

    want = Renderer(build_scene(cfg)).render(2).images[1]
    assert got is not None
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 0


def test_same_seed_same_files(tmp_path):
    import hashlib

    cfg = preset_config("demo", num_frames=2, background_frames=1, width=80, height=60, seed=7)

    def digest(root):
        return {
            p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*"))
            if p.is_file()
        }

    write_dataset(cfg, tmp_path / "a")
    write_dataset(cfg, tmp_path / "b")
    a, b = digest(tmp_path / "a"), digest(tmp_path / "b")
    assert len(a) > 20 and a == b
    write_dataset(
        preset_config("demo", num_frames=2, background_frames=1, width=80, height=60, seed=8),
        tmp_path / "c",
    )
    c = digest(tmp_path / "c")
    assert a["frames/cam0/000001.png"] != c["frames/cam0/000001.png"]
