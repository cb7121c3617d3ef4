"""linereg: camera pose in an untextured 3D point-cloud map from line segments alone.

    import linereg
    cam = linereg.Camera(fx=800, fy=800, cx=320, cy=240, width=640, height=480)
    res = linereg.register(lines2d, lines3d, cam)   # (N, 4) pixels, (M, 6) world metres
    res.success, res.cam_from_world, res.matches, res.covariance
"""

from .camera import Camera
from .config import RegisterConfig
from .errors import FileFormatError, InvalidInputError, LineregError
from .pipeline import register
from .registration import Registration

__all__ = [
    "Camera",
    "FileFormatError",
    "InvalidInputError",
    "LineregError",
    "RegisterConfig",
    "Registration",
    "register",
]
__version__ = "0.1.0"
