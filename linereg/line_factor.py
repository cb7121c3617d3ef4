"""The line-projection factor of the refinement (paper section III-D, eq. "costs") on a gtsam ``Pose3``.

For a 2D segment with infinite line ``A x + B y + C = 0`` (``A^2 + B^2 = 1``) and its matched 3D segment,
the error is the signed perpendicular pixel distance of BOTH projected 3D endpoints to that line. One
factor holds every correspondence of an image (error of length 2K, endpoints interleaved: line k gives
rows 2k and 2k + 1), which is far cheaper than one Python callback per line.

The pose variable is gtsam's ``Pose3`` = ``world_T_cam`` (= ``world_from_cam``); gtsam retracts it on the
right, ``world_T_cam * Exp(xi)`` with ``xi = (omega, v)`` (rotation first) in the camera frame. Then a
camera-frame point moves as ``P' = Exp(xi)^-1 P = P - omega x P - v`` to first order, so
``dP'/domega = [P]_x`` and ``dP'/dv = -I`` (the paper's matrix is for a left perturbation of
``cam_from_world`` with translation first: different signs and order).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numba
import numpy as np

from .camera import Camera


@dataclass(frozen=True)
class LineProjection:
    """Everything per match set that does not depend on the pose, so each factor call is a few numpy ops.

    points_world: (2K, 3) float64 endpoints, interleaved (line k -> rows 2k, 2k + 1).
    a, b, c: (2K,) float64 with ``e = (a X + b Y) / Z + c`` for a camera-frame point (X, Y, Z):
        ``a = A fx``, ``b = B fy``, ``c = A cx + B cy + C`` (eq. "costs" with K folded in).
    min_depth_m: depth clamp so endpoints behind the camera give large but finite errors.
    """

    points_world: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    min_depth_m: float

    @classmethod
    def build(
        cls, lines2d_coeffs: np.ndarray, endpoints3d: np.ndarray, camera: Camera, min_depth_m: float = 1e-3
    ) -> LineProjection:
        """Returns the precomputation for (K, 3) line coefficients and their (K, 6) world 3D segments."""
        H = np.repeat(np.asarray(lines2d_coeffs, dtype=np.float64), 2, axis=0)
        points = np.asarray(endpoints3d, dtype=np.float64).reshape(-1, 3)
        c = H[:, 0] * camera.cx + H[:, 1] * camera.cy + H[:, 2]
        return cls(points, H[:, 0] * camera.fx, H[:, 1] * camera.fy, c, float(min_depth_m))

    def evaluate(self, points_cam: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Returns ((2K,) signed distances px, (2K, 6) d/dxi or None) for (2K, 3) camera-frame endpoints."""
        points_cam = np.ascontiguousarray(points_cam, dtype=np.float64)
        # one compiled call: the refinement's optimiser calls this every iteration, a dozen numpy calls on a
        # few hundred rows each time
        e, J = _evaluate(points_cam, self.a, self.b, self.c, self.min_depth_m, jacobian)
        return e, (J if jacobian else None)

    def points_cam(self, world_R_cam: np.ndarray, world_t_cam: np.ndarray) -> np.ndarray:
        """Returns (2K, 3) endpoints in the camera frame of the pose ``world_T_cam = (R, t)``."""
        return (self.points_world - world_t_cam) @ world_R_cam


@numba.njit(cache=True, nogil=True)
def _evaluate(
    points_cam: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, min_depth: float, jacobian: bool
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """``LineProjection.evaluate``: ((2K,) distances, (2K, 6) Jacobian, (0, 6) without ``jacobian``), each
    element computed in the operations and order of its numpy form."""
    n = len(points_cam)
    e = np.empty(n)
    J = np.empty((n if jacobian else 0, 6))
    for i in range(n):
        X, Y, Z = points_cam[i, 0], points_cam[i, 1], points_cam[i, 2]
        inv_z = 1.0 / (min_depth if Z < min_depth else Z)  # np.maximum: a NaN stays NaN
        num = a[i] * X + b[i] * Y
        e[i] = num * inv_z + c[i]
        if not jacobian:
            continue
        # de/dP' (3,): gradient of the distance w.r.t. the camera-frame point; Z is constant where clamped
        g0, g1 = a[i] * inv_z, b[i] * inv_z
        g2 = 0.0 if Z < min_depth else -num * inv_z * inv_z
        # rotation: g . ([P]_x omega) = g . (P x omega) = (g x P) . omega
        J[i, 0], J[i, 1], J[i, 2] = g1 * Z - g2 * Y, g2 * X - g0 * Z, g0 * Y - g1 * X
        J[i, 3], J[i, 4], J[i, 5] = -g0, -g1, -g2
    return e, J


def line_residuals(
    cam_from_world: np.ndarray,
    lines2d_coeffs: np.ndarray,
    endpoints3d: np.ndarray,
    camera: Camera,
    min_depth_m: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((2K,) signed endpoint-to-line distances px, (2K, 6) Jacobian) at ``cam_from_world``.

    lines2d_coeffs: (K, 3) ``(A, B, C)`` with ``A^2 + B^2 = 1`` (``geometry.line_coefficients``);
    endpoints3d: (K, 6) world 3D segments. The Jacobian is w.r.t. gtsam's tangent ``xi = (omega, v)`` of
    ``world_T_cam * Exp(xi)`` (``world_T_cam`` = inverse of ``cam_from_world``).
    """
    projection = LineProjection.build(lines2d_coeffs, endpoints3d, camera, min_depth_m)
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    e, J = projection.evaluate(projection.points_world @ R.T + t, jacobian=True)
    assert J is not None
    return e, J


def line_factor(
    key: int, projection: LineProjection, noise_model: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """Returns a gtsam CustomFactor on the ``Pose3`` (world_T_cam) at ``key`` with error of length 2K."""

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        pose = values.atPose3(key)
        points = projection.points_cam(pose.rotation().matrix(), pose.translation())
        e, J = projection.evaluate(points, jacobians is not None)
        if jacobians is not None:
            jacobians[0] = J
        return e

    return gtsam.CustomFactor(noise_model, [key], error)
