"""Camera models, projection, undistortion and rescaling."""

from edgerecon.geometry.camera import (
    Camera,
    Rig,
    fundamental_matrix,
    look_at,
    triangulation_angle_deg,
)

__all__ = ["Camera", "Rig", "fundamental_matrix", "look_at", "triangulation_angle_deg"]
