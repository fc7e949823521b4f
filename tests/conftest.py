"""Shared fixtures: synthetic rigs and the location of ../shared/data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from edgerecon.geometry import Camera, Rig, look_at

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_data(name: str) -> Path:
    """Path of a dataset in ../shared/data; skips the test when it is absent."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"{path} not available (../shared/data is only beside CI checkouts)")
    return path


def ring_rig(
    num_cameras: int = 5,
    radius: float = 4.0,
    height: float = 1.5,
    width: int = 640,
    height_px: int = 480,
    focal_px: float = 500.0,
    dist: tuple[float, ...] = (0, 0, 0, 0, 0),
) -> Rig:
    """Cameras on a circle around the origin, looking at (0, 0, 1), metres, z up."""
    cams = []
    for i in range(num_cameras):
        a = 2 * np.pi * i / num_cameras
        R, t = look_at((radius * np.cos(a), radius * np.sin(a), height), (0, 0, 1.0))
        K = np.array(
            [[focal_px, 0, (width - 1) / 2], [0, focal_px, (height_px - 1) / 2], [0, 0, 1]]
        )
        cams.append(Camera(name=f"cam{i}", width=width, height=height_px, K=K, R=R, t=t, dist=dist))
    return Rig(cameras=tuple(cams), unit="m")


@pytest.fixture
def rig5() -> Rig:
    return ring_rig(5)


#: A small synthetic scene shared by the pipeline, runtime and CLI tests (rendered once).
TINY_SCENE = dict(width=320, height=240, num_frames=8, background_frames=12, seed=7)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Folder of a 5-camera 320x240 synthetic dataset (8 timestamps, 2 actors) with ground
    truth, in the format ``open_dataset`` reads."""
    from edgerecon.synth import preset_config, write_dataset

    out = tmp_path_factory.mktemp("tiny") / "scene"
    write_dataset(preset_config("demo", **TINY_SCENE), out)
    return out
