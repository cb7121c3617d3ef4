"""Trajectory errors as evo computes them (``evo_ape`` / ``evo_rpe`` with their defaults), in numpy.

Poses are compared as TUM stores them, ``world_from_cam`` (``P`` estimate, ``Q`` reference, same
timestamps, no alignment: both live in the map's frame):

- APE (``evo_ape``, translation part): ``E_i = Q_i^-1 P_i``, error ``|t(E_i)|`` = the distance between
  the camera centres; the ATE is its RMSE.
- RPE (``evo_rpe``, translation part, delta 1 frame): ``E_i = (Q_i^-1 Q_i+1)^-1 (P_i^-1 P_i+1)``, error
  ``|t(E_i)|``; its RMSE. Rotation parts: the angle of the rotation of ``E_i`` in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import invert


@dataclass(frozen=True)
class Errors:
    """Statistics of one error series (metres or degrees), as evo names them."""

    rmse: float
    mean: float
    median: float
    max: float
    count: int

    @classmethod
    def of(cls, e: np.ndarray) -> Errors:
        if len(e) == 0:
            return cls(float("nan"), float("nan"), float("nan"), float("nan"), 0)
        return cls(
            float(np.sqrt(np.mean(e**2))), float(e.mean()), float(np.median(e)), float(e.max()), len(e)
        )


def _angle_deg(R: np.ndarray) -> np.ndarray:
    """Returns (K,) rotation angles deg of (K, 3, 3) rotations."""
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def ape(est_cam_from_world: np.ndarray, ref_cam_from_world: np.ndarray) -> tuple[Errors, Errors]:
    """Returns (translation m, rotation deg) absolute pose errors of (K, 4, 4) poses against the reference."""
    P = np.array([invert(T) for T in est_cam_from_world]).reshape(-1, 4, 4)
    Q = np.array([invert(T) for T in ref_cam_from_world]).reshape(-1, 4, 4)
    E = np.linalg.inv(Q) @ P
    return Errors.of(np.linalg.norm(E[:, :3, 3], axis=1)), Errors.of(_angle_deg(E[:, :3, :3]))


def rpe(est_cam_from_world: np.ndarray, ref_cam_from_world: np.ndarray) -> tuple[Errors, Errors]:
    """Returns (translation m, rotation deg) relative pose errors between consecutive (K, 4, 4) poses."""
    P = np.array([invert(T) for T in est_cam_from_world]).reshape(-1, 4, 4)
    Q = np.array([invert(T) for T in ref_cam_from_world]).reshape(-1, 4, 4)
    dP = np.linalg.inv(P[:-1]) @ P[1:]
    dQ = np.linalg.inv(Q[:-1]) @ Q[1:]
    E = np.linalg.inv(dQ) @ dP
    return Errors.of(np.linalg.norm(E[:, :3, 3], axis=1)), Errors.of(_angle_deg(E[:, :3, :3]))
