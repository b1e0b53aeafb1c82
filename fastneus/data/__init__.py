"""fastneus.data: the scene model (cameras, projectors, patterns, frames) and its validation.

Modules: ``scene`` (:class:`Scene`: load, validate, save, accessors), ``model`` (the elements
of a scene), ``validate`` (field and geometry checks, JSON parsing), ``images`` (image headers,
EXIF, reading, undistortion), ``groundtruth`` (depth, normal and clean-image files)."""
from fastneus.data.images import image_size
from fastneus.data.model import Bounds, Camera, Frame, FrameProjector, Illumination, Pattern, Projector
from fastneus.data.scene import Scene
from fastneus.data.validate import check_pose
from fastneus.geometry.cameras import look_at, rigid_inverse

__all__ = ["Bounds", "Camera", "Frame", "FrameProjector", "Illumination", "Pattern", "Projector", "Scene",
           "check_pose", "image_size", "look_at", "rigid_inverse"]
