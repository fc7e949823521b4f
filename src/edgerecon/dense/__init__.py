"""Dense multi-view stereo on CPU: per-view depth maps, cross-view consistency, fusion.

Entry point: :func:`reconstruct_dense` (see :mod:`edgerecon.dense.reconstruct`); the algorithm
and its measured quality and speed are described in :mod:`edgerecon.dense.depth`.
"""

from edgerecon.dense.config import DenseConfig
from edgerecon.dense.reconstruct import (
    DenseReconstruction,
    estimate_up,
    reconstruct_dense,
    working_camera,
)

__all__ = [
    "DenseConfig",
    "DenseReconstruction",
    "estimate_up",
    "reconstruct_dense",
    "working_camera",
]
