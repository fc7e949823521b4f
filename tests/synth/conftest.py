"""Small synthetic scenes shared by the synth tests (built once per session)."""

from __future__ import annotations

from pathlib import Path

import pytest

from edgerecon.synth import (
    DatasetSummary,
    RenderedFrame,
    Renderer,
    SynthScene,
    build_scene,
    preset_config,
    write_dataset,
)
from edgerecon.synth.scene import STUDIO_DISTORTION

SMALL = {"num_frames": 4, "background_frames": 2, "width": 320, "height": 240}


@pytest.fixture(scope="session")
def small_scene() -> SynthScene:
    return build_scene(preset_config("demo", **SMALL))


@pytest.fixture(scope="session")
def small_renderer(small_scene: SynthScene) -> Renderer:
    return Renderer(small_scene)


@pytest.fixture(scope="session")
def small_frame(small_renderer: Renderer) -> RenderedFrame:
    return small_renderer.render(2, clean=True)


@pytest.fixture(scope="session")
def distorted_renderer() -> Renderer:
    scene = build_scene(preset_config("demo", distortion=STUDIO_DISTORTION, seed=5, **SMALL))
    return Renderer(scene)


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory: pytest.TempPathFactory) -> DatasetSummary:
    out: Path = tmp_path_factory.mktemp("synth") / "demo"
    return write_dataset(preset_config("demo", **SMALL), out)


#: The people-in-a-room preset, downscaled (full length: the scripts' stretches are intact).
HD4_SMALL = {"width": 320, "height": 180}


@pytest.fixture(scope="session")
def hd4_scene() -> SynthScene:
    return build_scene(preset_config("hd4", **HD4_SMALL))


@pytest.fixture(scope="session")
def hd4_renderer(hd4_scene: SynthScene) -> Renderer:
    return Renderer(hd4_scene)
