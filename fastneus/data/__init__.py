"""fastneus.data: the scene model (cameras, projectors, patterns, frames) and its validation."""
from .scene import (
    Bounds,
    Camera,
    Frame,
    FrameProjector,
    Illumination,
    Pattern,
    Projector,
    Scene,
    check_pose,
    image_size,
    look_at,
    rigid_inverse,
)

__all__ = ["Bounds", "Camera", "Frame", "FrameProjector", "Illumination", "Pattern", "Projector", "Scene",
           "check_pose", "image_size", "look_at", "rigid_inverse"]
