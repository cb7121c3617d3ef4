"""Exposure and white balance: one multiplicative gain per photo and colour channel.

Model: the colour photo k records at point p is ``c_kp = g_k * a_p`` (per channel; a camera's tone curve is
a power law, which keeps a gain a gain). In logs it is linear, ``log c_kp = log g_k + log a_p``, and is solved
by weighted least squares over the points several photos see, alternating between the points' ``a`` and
the photos' ``g`` (block coordinate descent) with Huber weights on the residuals (a misregistered pixel or
an occluder the depth test missed is an outlier, not a gain). Each photo's gain has a prior of
``prior_points`` observations at gain 1, and the median gain is 1: a photo whose overlap with the others
is small or view-dependent (glass mirrors the sky differently from each viewpoint) moves only itself,
never the exposure of every other photo.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from ..geometry import camera_center
from .blend import Observation, Photo
from .config import ColorizeConfig, GainConfig
from .project import project

log = logging.getLogger(__name__)

HUBER_LOG = 0.1  # residuals beyond 10 % of a colour value weigh less (Huber)
CLEAR_PX = 2  # gains come from points with no nearer surface this many pixels round them


def estimate_gains(observations: list[Observation], num_points: int, config: GainConfig) -> np.ndarray:
    """Returns (K, 3) float32 RGB gains of K photos from their Observations of the same ``num_points``.

    A photo that shares no point with another keeps gain 1.
    """
    k = len(observations)
    gains = np.ones((k, 3), dtype=np.float32)
    if k < 2 or not config.enabled:
        return gains
    point = np.concatenate([o.index for o in observations])
    photo = np.concatenate([np.full(len(o.index), i) for i, o in enumerate(observations)])
    rgb = np.concatenate([o.rgb for o in observations]).astype(np.float64)
    weight = np.concatenate([o.weight for o in observations]).astype(np.float64)
    # each point's photos weigh relative to its best one: far points count as much as near ones
    best = np.zeros(num_points)
    np.maximum.at(best, point, weight)
    weight = weight / np.maximum(best[point], 1e-300)
    shared = np.bincount(point, minlength=num_points)[point] >= 2
    valid = (rgb >= config.dark) & (rgb <= 255 - config.dark) & shared[:, None]
    for channel in range(3):
        w = weight * valid[:, channel]
        if w.sum() == 0:
            continue
        log_gain = _solve(point, photo, np.log(np.maximum(rgb[:, channel], 1.0)), w, num_points, k, config)
        gains[:, channel] = np.exp(log_gain)
    limit = np.log(config.max_gain)
    gains = np.exp(np.clip(np.log(gains), -limit, limit)).astype(np.float32)
    log.info("gains per photo (RGB): min %s, max %s", gains.min(axis=0).round(3), gains.max(axis=0).round(3))
    return gains


def clear_observations(
    photo: Photo,
    depth: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    obs: Observation,
    config: ColorizeConfig,
) -> Observation:
    """Returns the part of ``obs`` fit to estimate gains on: surfaces seen at most ``acos(min_cos)`` from
    head-on with no nearer surface within ``CLEAR_PX`` pixels in the depth map.

    Points beside a depth edge (a window reveal, a pillar's silhouette) may take the colour of the edge
    itself at a slight misregistration or through a gap in the splats: for the blend a small error, for a
    gain a bias (the overlap between two photos can be mostly such points). points: (P, 3) float64 world,
    normals: (P, 3) float32, the rows ``obs.index`` refers to; depth: (H, W) float32 m.
    """
    vis, cfg = config.visibility, config.gains
    rows = obs.index
    to_eye = camera_center(photo.cam_from_world) - points[rows]
    cos = np.abs(np.einsum("nk,nk->n", normals[rows], to_eye)) / np.linalg.norm(to_eye, axis=1)
    pr = project(points, photo.camera, photo.cam_from_world, vis.near_m, rows)
    kernel = np.ones((2 * CLEAR_PX + 1, 2 * CLEAR_PX + 1), np.uint8)
    nearest = cv2.erode(depth, kernel, borderType=cv2.BORDER_REPLICATE)  # the nearest depth round each pixel
    slope = np.sqrt(1.0 - cfg.min_cos**2) / cfg.min_cos
    reach_m = (CLEAR_PX + 1.0) * pr.z / max(photo.camera.fx, photo.camera.fy) * slope
    tolerance = vis.depth_tol_m + vis.depth_tol_rel * pr.z + reach_m
    row, col = np.floor(pr.v + 0.5).astype(np.int64), np.floor(pr.u + 0.5).astype(np.int64)
    clear = np.zeros(len(points), bool)
    clear[pr.index[nearest[row, col] >= pr.z - tolerance]] = True
    keep = np.flatnonzero(clear[rows] & (np.nan_to_num(cos, nan=0.0) >= cfg.min_cos))
    return Observation(rows[keep], obs.rgb[keep], obs.weight[keep])


def _solve(
    point: np.ndarray, photo: np.ndarray, value: np.ndarray, w: np.ndarray, num_points: int, k: int, cfg
) -> np.ndarray:
    """Returns (K,) log gains minimising sum w huber(value - log_gain[photo] - log_a[point])."""
    log_gain = np.zeros(k)
    robust = w.copy()
    has_data = np.bincount(photo, weights=w, minlength=k) > 0
    for _ in range(cfg.iterations):
        point_w = np.bincount(point, weights=robust, minlength=num_points)
        log_a: np.ndarray = np.bincount(
            point, weights=robust * (value - log_gain[photo]), minlength=num_points
        )
        log_a = log_a / np.maximum(point_w, 1e-300)
        photo_w = np.bincount(photo, weights=robust, minlength=k)
        numerator = np.bincount(photo, weights=robust * (value - log_a[point]), minlength=k)
        # the prior: ``prior_points`` observations at gain 1 (a photo that shares little keeps gain ~1)
        log_gain = numerator / (photo_w + cfg.prior_points)
        log_gain[has_data] -= np.median(log_gain[has_data])
        residual = np.abs(value - log_gain[photo] - log_a[point])
        robust = w * np.minimum(1.0, HUBER_LOG / np.maximum(residual, 1e-12))
    return log_gain
