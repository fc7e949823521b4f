"""System-side optimisation: camera selection (problem P2), the online bisection controller
(Algorithm 1) with minor adjustment, and a simulator to test and tune them without running
reconstructions. See docs/OPTIMIZER.md."""

from edgerecon.optimize.controller import (
    BisectionController,
    ControllerConfig,
    Solution,
    TaskConfig,
)
from edgerecon.optimize.selection import (
    CameraMapping,
    CameraSelector,
    Selection,
    SelectionConfig,
    VisibilityPatterns,
    aggregate_patterns,
    camera_mapping,
    coverage,
    geometric_visibility,
    reduce_patterns_kmeans,
    select_cameras,
    visibility_from_points,
)
from edgerecon.optimize.simulator import (
    Optimum,
    PipelineModel,
    SimulationResult,
    SimulationSummary,
    SimulatorConfig,
    TaskRow,
    random_visibility,
    run_simulation,
    simulate,
    synthetic_visibility,
    true_optimum,
)

__all__ = [
    "BisectionController",
    "CameraMapping",
    "CameraSelector",
    "ControllerConfig",
    "Optimum",
    "PipelineModel",
    "Selection",
    "SelectionConfig",
    "SimulationResult",
    "SimulationSummary",
    "SimulatorConfig",
    "Solution",
    "TaskConfig",
    "TaskRow",
    "VisibilityPatterns",
    "aggregate_patterns",
    "camera_mapping",
    "coverage",
    "geometric_visibility",
    "random_visibility",
    "reduce_patterns_kmeans",
    "run_simulation",
    "select_cameras",
    "simulate",
    "synthetic_visibility",
    "true_optimum",
    "visibility_from_points",
]
