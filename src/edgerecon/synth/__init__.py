"""Ground-truth scenes: a synthetic room with walking actors, rendered into a calibrated rig.

Library API::

    from edgerecon.synth import preset_config, build_scene, Renderer, write_dataset, GroundTruth

    config = preset_config("demo", seed=3)          # or "ring", "arc7", "hd4", "hd4p", "object"
    summary = write_dataset(config, "work/demo")    # dataset.json + rig.json + frames + gt/
    gt = GroundTruth.open("work/demo")
    gt.depth("cam0", 5); gt.object_mask("cam0", 5); gt.reference_cloud(5, "foreground")

``Renderer(build_scene(config)).render(t)`` renders in memory (images, depth maps, masks).
"""

from edgerecon.synth.dataset import DatasetSummary, write_dataset
from edgerecon.synth.groundtruth import GroundTruth, count_views, sample_visible_cloud
from edgerecon.synth.render import RenderedFrame, Renderer
from edgerecon.synth.scene import (
    PRESETS,
    RealismConfig,
    RigSpec,
    SceneConfig,
    SynthScene,
    build_scene,
    make_rig,
    preset_config,
)
from edgerecon.synth.scripts import ActorScript

__all__ = [
    "PRESETS",
    "ActorScript",
    "DatasetSummary",
    "GroundTruth",
    "RealismConfig",
    "RenderedFrame",
    "Renderer",
    "RigSpec",
    "SceneConfig",
    "SynthScene",
    "build_scene",
    "count_views",
    "make_rig",
    "preset_config",
    "sample_visible_cloud",
    "write_dataset",
]
