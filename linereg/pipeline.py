"""``register``: the paper's section III from segments to a refined pose (composer only, no math here)."""

from __future__ import annotations

from .camera import Camera
from .config import RegisterConfig
from .registration import Registration


def register(lines2d, lines3d, camera: Camera, config: RegisterConfig | None = None) -> Registration:
    """Returns the Registration of an image's 2D segments against a map's 3D segments (being written)."""
    raise NotImplementedError("register is being assembled")
