"""The pinhole camera: intrinsics, optional OpenCV distortion, undistortion of pixel points.

Convention (stated once here): camera frame x right, y down, z forward; pixel (0, 0) is the centre of
the top-left pixel, so ``u = fx * X / Z + cx`` with no half-pixel shift.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import MAX_COORDINATE, InvalidInputError

MAX_IMAGE_SIDE = 10**6  # pixels: beyond any sensor or stitched panorama


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels; ``dist`` = OpenCV (k1, k2, p1, p2[, k3]) or empty."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value) or abs(value) > MAX_COORDINATE:
                raise InvalidInputError(f"camera {name} must be a finite number of pixels, got {value!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise InvalidInputError(f"camera focal length must be positive, got fx={self.fx}, fy={self.fy}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | np.integer)
                or not 0 < value <= MAX_IMAGE_SIDE
            ):
                raise InvalidInputError(f"camera {name} must be a positive integer of pixels, got {value!r}")
        dist = tuple(float(d) for d in self.dist)
        if len(dist) not in (0, 4, 5, 8) or not all(math.isfinite(d) for d in dist):
            raise InvalidInputError(f"camera dist must hold 4, 5 or 8 finite OpenCV coefficients, got {dist}")
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def undistorted(self) -> Camera:
        """Returns the same camera without distortion (what undistorted points live in)."""
        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def undistort_points(self, points: np.ndarray) -> np.ndarray:
        """Returns (N, 2) float64 pixels with lens distortion removed, same K."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion or len(points) == 0:
            return points.copy()
        import cv2

        out = cv2.undistortPoints(points[:, None, :], self.K, np.array(self.dist), P=self.K)
        return out.reshape(-1, 2)

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera") -> Camera:
        """Builds a camera from ``{fx, fy, cx, cy, width, height[, dist]}``; ``source`` names it in errors."""
        missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in d]
        if missing:
            raise InvalidInputError(f"{source}: missing key(s) {', '.join(missing)}")
        dist = d.get("dist", d.get("distortion", ()))
        if isinstance(dist, dict):  # {"model": ..., "coeffs": [...]} as in shared/data cameras.json
            model = dist.get("model")
            if isinstance(model, str) and _other_projection(model):
                raise InvalidInputError(
                    f"{source}: distortion model {model!r} is not OpenCV's radial-tangential one (k1 k2 p1 p2 "
                    "[k3 [k4 k5 k6]]), which linereg undistorts with: undistort the images first, or give the "
                    "camera in that model"
                )
            dist = dist.get("coeffs", ())
        try:
            return cls(
                fx=float(d["fx"]),
                fy=float(d["fy"]),
                cx=float(d["cx"]),
                cy=float(d["cy"]),
                width=int(d["width"]),
                height=int(d["height"]),
                dist=tuple(float(x) for x in (dist or ())),
            )
        except (TypeError, ValueError) as e:
            if isinstance(e, InvalidInputError):
                raise InvalidInputError(f"{source}: {e}") from None
            raise InvalidInputError(f"{source}: {e}") from None

    def to_dict(self) -> dict:
        """Returns ``{fx, fy, cx, cy, width, height, dist}`` (the form ``from_dict`` and camera files use)."""
        return {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
            "dist": list(self.dist),
        }


# words naming lens models whose coefficients are not OpenCV's radial-tangential ones: read as such, a
# fisheye's k1-k4 would be taken for k1 k2 p1 p2 and every line undistorted wrongly, without a word
_OTHER_PROJECTIONS = (
    "fisheye", "equidistant", "kannala", "brandt", "omni", "unified", "double_sphere", "division", "fov",
    "thin_prism", "scaramuzza",
)  # fmt: skip


def _other_projection(model: str) -> bool:
    """Returns True if a distortion model's name (any case, ``-`` or ``_``) names another projection."""
    words = model.strip().lower().replace("-", "_")
    return any(word in words for word in _OTHER_PROJECTIONS)
