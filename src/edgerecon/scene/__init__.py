"""Application side: background model, foreground masks, objects, sparse split, visual hull,
merge (the paper's Section IV-A).

Typical use per timestamp::

    fg = RigForeground.learn(rig, background_clips)        # once (state: BackgroundModel)
    result = fg.segment(frame_set)                          # masks, objects, hull
    split = split_sparse(points3D, visibility, rig.cameras, result.label_images())
    cloud = hull_cloud(result.hull, rig.cameras, frame_set.images)   # fallback shape
    merged = merge_clouds(fg_cloud, bg_cloud, bg_version=v, hull=result.hull)
"""

from edgerecon.scene.background import (
    BackgroundConfig,
    BackgroundModel,
    BackgroundState,
    Segmentation,
    learn_backgrounds,
)
from edgerecon.scene.foreground import ForegroundConfig, ForegroundResult, RigForeground
from edgerecon.scene.hull import (
    DepthRange,
    HullConfig,
    VisualHull,
    depth_map,
    hull_cloud,
    hull_consistent_masks,
    hull_depth_range,
    hull_object_silhouettes,
    hull_silhouette,
    rig_region,
    visual_hull,
)
from edgerecon.scene.masks import MaskConfig, clean_mask, fill_holes, remove_small_blobs
from edgerecon.scene.merge import BG_VERSION, MergeConfig, merge_clouds, split_merged, write_merged
from edgerecon.scene.objects import (
    ForegroundObject,
    ObjectConfig,
    ObjectSegmentation,
    find_objects,
    silhouette_score,
)
from edgerecon.scene.split import SplitConfig, SplitResult, split_sparse

__all__ = [
    "BG_VERSION",
    "BackgroundConfig",
    "BackgroundModel",
    "BackgroundState",
    "DepthRange",
    "ForegroundConfig",
    "ForegroundObject",
    "ForegroundResult",
    "HullConfig",
    "MaskConfig",
    "MergeConfig",
    "ObjectConfig",
    "ObjectSegmentation",
    "RigForeground",
    "Segmentation",
    "SplitConfig",
    "SplitResult",
    "VisualHull",
    "clean_mask",
    "depth_map",
    "fill_holes",
    "find_objects",
    "hull_cloud",
    "hull_consistent_masks",
    "hull_depth_range",
    "hull_object_silhouettes",
    "hull_silhouette",
    "learn_backgrounds",
    "merge_clouds",
    "remove_small_blobs",
    "rig_region",
    "silhouette_score",
    "split_merged",
    "split_sparse",
    "visual_hull",
    "write_merged",
]
