"""How honest a claimed pose's covariance is: the true error measured in the covariance's own sigmas.

A Registration reports a (6, 6) covariance of gtsam's tangent ``xi = (omega rad, v m)`` of
``world_T_cam * Exp(xi)`` (``Registration.covariance``). A robot fusing the pose, or a smoother weighing it
against odometry, trusts it that far. With the true pose known, the error's tangent ``e = Log(est^-1 true)``
gives the NEES (normalised estimation error squared) ``e^T Sigma^-1 e``: for an honest covariance it is
chi-square with 6 degrees of freedom (median 5.35; above ``THREE_SIGMA``, the 3-sigma level of six dimensions,
in 0.27 % of claims). A claim beyond it is right by the benchmark's bounds and still overconfident; a
wrong claim is far beyond it. Every benchmark with ground truth reports both beside each other.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import gtsam
import numpy as np
from scipy.stats import chi2

from ..geometry import invert

# the squared Mahalanobis distance that a 6-D Gaussian error exceeds as rarely as a 1-D one exceeds 3 sigma
THREE_SIGMA = float(chi2.ppf(math.erf(3.0 / math.sqrt(2.0)), 6))


def nees(cam_from_world: np.ndarray, truth: np.ndarray, covariance: np.ndarray | None) -> float:
    """Returns the NEES of an estimated (4, 4) ``cam_from_world`` against the true one under its (6, 6)
    ``covariance`` (gtsam's tangent of world_T_cam, rotation first); NaN when the covariance is missing,
    not finite or not positive definite."""
    if covariance is None:
        return math.nan
    cov = np.asarray(covariance, dtype=np.float64)
    if cov.shape != (6, 6) or not np.isfinite(cov).all():
        return math.nan
    error = gtsam.Pose3.Logmap(
        gtsam.Pose3(invert(np.asarray(cam_from_world, dtype=np.float64))).between(
            gtsam.Pose3(invert(np.asarray(truth, dtype=np.float64)))
        )
    )
    try:
        factor = np.linalg.cholesky(0.5 * (cov + cov.T))
    except np.linalg.LinAlgError:
        return math.nan
    whitened = np.linalg.solve(factor, error)
    return float(whitened @ whitened)


def summary(values: Iterable[float]) -> dict[str, Any]:
    """Returns {"claims": how many NEES values are known, "beyond_3sigma": how many exceed
    ``THREE_SIGMA``, "nees_median": their median (NaN without any)} of the claims' NEES values."""
    known = np.array([v for v in values if np.isfinite(v)], dtype=np.float64)
    return {
        "claims": len(known),
        "beyond_3sigma": int((known > THREE_SIGMA).sum()),
        "nees_median": float(np.median(known)) if len(known) else math.nan,
    }


def summary_line(counts: dict[str, Any]) -> str:
    """Returns the one-line summary the benchmarks print of ``summary``'s counts."""
    if not counts["claims"]:
        return "covariance: no claim to check"
    return (
        f"covariance: {counts['beyond_3sigma']} of {counts['claims']} claims' errors beyond their 3 sigma "
        f"(NEES > {THREE_SIGMA:.1f}; median NEES {counts['nees_median']:.1f}, honest: "
        f"{chi2.median(6):.1f})"
    )
