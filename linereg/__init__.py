"""linereg: camera pose in an untextured 3D point-cloud map from line segments alone.

import linereg
cam = linereg.Camera(fx=800, fy=800, cx=320, cy=240, width=640, height=480)
res = linereg.register(lines2d, lines3d, cam)   # (N, 4) pixels, (M, 6) world metres
res.success, res.cam_from_world, res.matches, res.covariance
"""

from ._kernel_cache import clear_stale as _clear_stale

_clear_stale()  # before any kernel loads: a cache compiled from older sources goes

from .camera import Camera  # noqa: E402
from .config import RegisterConfig  # noqa: E402
from .errors import FileFormatError, InvalidInputError, LineregError  # noqa: E402
from .registration import Registration  # noqa: E402

__all__ = [
    "Calibration",
    "Camera",
    "FileFormatError",
    "InvalidInputError",
    "LineMap",
    "LineregError",
    "Prior",
    "RegisterConfig",
    "Registration",
    "SequenceConfig",
    "Tracker",
    "TrackingConfig",
    "calibrate",
    "calibrate_segments",
    "colorize",
    "localize",
    "localize_segments",
    "localize_sequence",
    "register",
    "warm_up",
]
__version__ = "0.1.0"

# Heavy stages (gtsam, open3d) load on first use, so ``import linereg`` stays fast for clients and the CLI.
_LAZY = {
    "register": "linereg.pipeline",
    "localize": "linereg.localization",
    "localize_segments": "linereg.localization",
    "Prior": "linereg.priors",
    "LineMap": "linereg.map.linemap",
    "localize_sequence": "linereg.sequence",
    "SequenceConfig": "linereg.sequence",
    "Tracker": "linereg.tracking",
    "TrackingConfig": "linereg.tracking",
    "colorize": "linereg.colorization",
    "warm_up": "linereg.warm",
    "calibrate": "linereg.calibration",
    "calibrate_segments": "linereg.calibration",
    "Calibration": "linereg.calibration",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'linereg' has no attribute {name!r}")
