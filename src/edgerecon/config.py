"""Configuration of one reconstruction task, and named presets.

A task's configuration is the pair the optimizer tunes — image scale r and camera subset —
plus the settings of each stage. The optimizer derives new configurations with
``dataclasses.replace(config, scale=..., camera_ids=...)``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from edgerecon.dense import DenseConfig
from edgerecon.sparse import SparseConfig

#: Smallest camera subset a reconstruction accepts (the paper's constraint C3).
MIN_CAMERAS = 3


@dataclass(frozen=True, kw_only=True)
class ReconstructionConfig:
    """What to reconstruct for one task, and how."""

    scale: float = 1.0
    """Image scale r in (0, 1]: frames are undistorted and resized by r before every stage."""
    camera_ids: tuple[int, ...] | None = None
    """Rig ids of the cameras to use (None = all cameras with a frame)."""
    dense: bool = True
    """Run multi-view stereo after the sparse stage."""
    sparse_config: SparseConfig = field(default_factory=SparseConfig)
    """Settings of the sparse stage (features, matching, triangulation)."""
    dense_config: DenseConfig = field(default_factory=DenseConfig)
    """Settings of the dense stage (depth maps, consistency, fusion)."""

    def __post_init__(self) -> None:
        if not (0.0 < self.scale <= 1.0 and math.isfinite(self.scale)):
            raise ValueError(f"ReconstructionConfig.scale must be in (0, 1], got {self.scale!r}")
        if self.camera_ids is not None:
            ids = tuple(int(i) for i in self.camera_ids)
            if len(set(ids)) != len(ids):
                raise ValueError(f"ReconstructionConfig.camera_ids has duplicates: {ids}")
            if len(ids) < MIN_CAMERAS:
                raise ValueError(
                    f"ReconstructionConfig.camera_ids needs at least {MIN_CAMERAS} cameras, "
                    f"got {list(ids)}"
                )
            object.__setattr__(self, "camera_ids", ids)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scale": self.scale,
            "camera_ids": None if self.camera_ids is None else list(self.camera_ids),
            "dense": self.dense,
            "sparse_config": dataclasses.asdict(self.sparse_config),
            "dense_config": dataclasses.asdict(self.dense_config),
        }


PRESETS: dict[str, ReconstructionConfig] = {
    "golden": ReconstructionConfig(),
    "sparse-only": ReconstructionConfig(dense=False),
}
"""Named configurations: ``golden`` (r = 1, all cameras, dense) and ``sparse-only``."""


def preset(name: str) -> ReconstructionConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}") from None
