"""The benchmarks' covariance check (``bench/honesty.py``): a claim's error in its own sigmas."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from linereg.bench import honesty
from linereg.geometry import invert, make_cam_from_world


def _pose(rng: np.random.Generator) -> np.ndarray:
    R = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
    return make_cam_from_world(R, rng.normal(size=3) * 5.0)


def _moved(cam_from_world: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Returns the pose ``world_T_cam * Exp(xi)`` as cam_from_world (the Registration's tangent)."""
    world_T_cam = gtsam.Pose3(invert(cam_from_world)).compose(gtsam.Pose3.Expmap(xi))
    return invert(world_T_cam.matrix())


def _covariance(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(6, 6)) * np.r_[0.01, 0.01, 0.01, 0.05, 0.05, 0.05]
    return a @ a.T + 1e-6 * np.eye(6)


def test_nees_is_the_squared_mahalanobis_distance_of_the_tangent_error():
    rng = np.random.default_rng(0)
    for _ in range(5):
        est, cov = _pose(rng), _covariance(rng)
        xi = rng.normal(size=6) * 0.02
        expected = float(xi @ np.linalg.solve(cov, xi))
        assert honesty.nees(est, _moved(est, xi), cov) == pytest.approx(expected, rel=1e-6)
    assert honesty.nees(est, est, cov) == pytest.approx(0.0, abs=1e-12)


def test_an_honest_covariance_has_the_chi_square_distribution_of_six_dimensions():
    rng = np.random.default_rng(1)
    est, cov = _pose(rng), _covariance(rng)
    draws = rng.multivariate_normal(np.zeros(6), cov, size=2000)
    values = [honesty.nees(est, _moved(est, xi), cov) for xi in draws]
    counts = honesty.summary(values)
    assert counts["claims"] == 2000
    assert counts["nees_median"] == pytest.approx(5.35, abs=0.5)
    assert counts["beyond_3sigma"] <= 20  # 0.27 % expected: 5 of 2000
    # a covariance 3x too small in sigma puts most errors beyond it
    tight = honesty.summary(honesty.nees(est, _moved(est, xi), cov / 9.0) for xi in draws[:200])
    assert tight["beyond_3sigma"] > 100


def test_nees_is_nan_without_a_usable_covariance():
    rng = np.random.default_rng(2)
    est = _pose(rng)
    assert math.isnan(honesty.nees(est, est, None))
    assert math.isnan(honesty.nees(est, est, np.full((6, 6), np.nan)))
    assert math.isnan(honesty.nees(est, est, np.zeros((6, 6))))  # not positive definite
    assert math.isnan(honesty.nees(est, est, np.eye(3)))


def test_summary_counts_known_values_only():
    counts = honesty.summary([1.0, float("nan"), 30.0, 4.0])
    assert counts == {"claims": 3, "beyond_3sigma": 1, "nees_median": 4.0}
    assert "1 of 3 claims" in honesty.summary_line(counts)
    empty = honesty.summary([])
    assert empty["claims"] == 0 and math.isnan(empty["nees_median"])
    assert honesty.summary_line(empty) == "covariance: no claim to check"
    assert honesty.THREE_SIGMA == pytest.approx(20.06, abs=0.01)
