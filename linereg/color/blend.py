"""What one photo says about the points of a chunk: which it sees, their colour there, and how much to trust it.

A photo's colour at a point is weighted by (each factor in [0, 1] or relative between photos):

    w = (cos_angle ^ a * (1 / range) ^ r * border * sharpness) ^ p

``cos_angle`` between the viewing ray and the surface normal (0 below ``min_cos``), ``border`` a ramp from
0 at the image border, ``sharpness`` the photo's focus measure relative to the sharpest photo's, ``p``
the blend power (``WeightConfig``). Colours are RGB float32 in [0, 255]; photos are BGR as
``linereg.io.read_image`` returns them (grey photos are taken as grey colours).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import Camera
from .config import ColorizeConfig
from .depth import behind_m, footprint_radius_px, tolerance_m
from .project import ViewPoints, view_points

REMAP_COLUMNS = 1024  # cv2.remap takes maps of fewer than 32767 rows: lookups are laid out this wide


@dataclass(frozen=True)
class Photo:
    """A localized photo: (H, W, 3) uint8 BGR or (H, W) grey ``image`` of ``camera`` at ``cam_from_world``.

    sharpness: its weight factor in (0, 1] (``sharpness_weights``); gain: (3,) float32 RGB exposure gain
    its colours are divided by (``linereg.color.gains``).
    """

    image: np.ndarray
    camera: Camera
    cam_from_world: np.ndarray
    sharpness: float = 1.0
    gain: np.ndarray | None = None


@dataclass(frozen=True)
class Observation:
    """The chunk points one photo sees: rows ``index`` (n,) int64, ``rgb`` (n, 3) float32, ``weight`` (n,)."""

    index: np.ndarray
    rgb: np.ndarray
    weight: np.ndarray


def focus_measure(image: np.ndarray) -> float:
    """Returns a photo's sharpness: the mean of the 10 % strongest |Laplacian| responses of its grey image.

    Blur lowers the response at edges, which every photo of a built scene has; the strongest decile is
    little affected by how much of the photo is sky or plain wall.
    """
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    response = np.abs(cv2.Laplacian(grey.astype(np.float32), cv2.CV_32F, ksize=3)).ravel()
    top = response[np.argpartition(response, int(0.9 * len(response)))[int(0.9 * len(response)) :]]
    return float(top.mean())


def sharpness_weights(measures: np.ndarray, power: float) -> np.ndarray:
    """Returns (K,) float64 in (0, 1]: each photo's focus measure over the sharpest one's, ^ power."""
    measures = np.maximum(np.asarray(measures, dtype=np.float64), 1e-6)
    return (measures / measures.max()) ** power


def observe(
    photo: Photo,
    depth: np.ndarray,
    points: np.ndarray,
    spacing: np.ndarray,
    normals: np.ndarray,
    config: ColorizeConfig,
    rows: np.ndarray | None = None,
    *,
    check_normals: np.ndarray | None = None,
) -> Observation:
    """Returns the Observation of a chunk by one photo whose (H, W) float32 depth map is ``depth``.

    points: (P, 3) float64 world; spacing: (P,) float32 m; normals: (P, 3) float32 (NaN: unknown);
    rows: (n,) int64 the rows that may be in view (``cull.rows_in_view``), default all.
    check_normals: (P, 3) float32 a second estimate of the normals (``local_surface(shifted=True)``): a
    point is seen only if it passes with both. A voxel holding two faces (a block's corner) gives a normal
    off both; a point on the face seen edge-on then looks less grazing than it is (above ``min_cos``) and
    its tilted tangent plane can come level with an occluder's splats. The other grid's voxel mostly
    holds one face, and where both grids hold one face they agree.
    """
    vis = config.visibility
    pr = view_points(points, normals, spacing, photo.camera, photo.cam_from_world, vis, rows)
    keep = np.flatnonzero(_passes(pr, depth, photo.camera, config))
    if check_normals is not None and len(keep):
        # the same rows project to the same pixels in the same order: only the slopes and cos differ
        again = view_points(
            points, check_normals, spacing, photo.camera, photo.cam_from_world, vis, pr.index[keep]
        )
        keep = keep[_passes(again, depth, photo.camera, config)]
    wts = config.weights
    u, v, cos, distance = pr.u[keep], pr.v[keep], pr.cos[keep], pr.distance[keep]
    weight = cos**wts.angle_power * distance ** (-wts.range_power) * photo.sharpness
    weight *= _border_ramp(u, v, photo.camera, wts.border_px)
    weight = weight**wts.blend_power
    rgb = sample_rgb(photo.image, u, v)
    if photo.gain is not None:
        rgb /= photo.gain
    good = np.flatnonzero(weight > 0)
    return Observation(pr.index[keep[good]], rgb[good], weight[good].astype(np.float32))


def _passes(pr: ViewPoints, depth: np.ndarray, camera: Camera, config: ColorizeConfig) -> np.ndarray:
    """Returns (n,) bool: the projected points seen at ``min_cos`` or less grazing whose tangent plane lies
    within the tolerance of the depth map over the pixels within half their splat diameter."""
    vis, cos = config.visibility, pr.cos
    tan = np.minimum(np.sqrt(np.maximum(1.0 - cos * cos, 0.0)) / np.maximum(cos, 1e-3), vis.max_slope)
    behind = behind_m(depth, pr.u, pr.v, pr.z, pr.slope, footprint_radius_px(pr.diameter, vis))
    return (behind <= tolerance_m(pr.z, pr.diameter, tan, camera, vis)) & (cos >= config.weights.min_cos)


def sample_rgb(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Returns (n, 3) float32 RGB in [0, 255], bilinear at pixels (u, v) of a BGR or grey image."""
    n = len(u)
    rows = max(-(-n // REMAP_COLUMNS), 1)
    map_u = np.zeros(rows * REMAP_COLUMNS, dtype=np.float32)
    map_v = np.zeros(rows * REMAP_COLUMNS, dtype=np.float32)
    map_u[:n], map_v[:n] = u, v
    shape = (rows, REMAP_COLUMNS)
    out = []
    for r in range(0, rows, 32_000):  # remap's row limit
        out.append(
            cv2.remap(
                image,
                map_u.reshape(shape)[r : r + 32_000],
                map_v.reshape(shape)[r : r + 32_000],
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
        )
    values = np.concatenate(out).reshape(rows * REMAP_COLUMNS, -1)[:n].astype(np.float32)
    if values.shape[1] == 1:
        return np.repeat(values, 3, axis=1)
    return np.ascontiguousarray(values[:, 2::-1])  # BGR -> RGB


def _border_ramp(u: np.ndarray, v: np.ndarray, camera: Camera, border_px: float) -> np.ndarray:
    """Returns (n,) float32 in [0, 1]: 0 on the image border, 1 from ``border_px`` inside (smoothstep)."""
    inside = np.minimum(
        np.minimum(u + 0.5, camera.width - 0.5 - u), np.minimum(v + 0.5, camera.height - 0.5 - v)
    )
    t = np.clip(inside / max(border_px, 1e-6), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def accumulate(total: np.ndarray, weights: np.ndarray, count: np.ndarray, obs: Observation) -> None:
    """Adds an Observation to a chunk's (P, 3) float64 weighted colour sums, (P,) weights and (P,) counts."""
    total[obs.index] += obs.weight[:, None] * obs.rgb
    weights[obs.index] += obs.weight
    count[obs.index] += 1


def blended(total: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Returns (P, 3) uint8 RGB: the weighted means, 0 where no photo contributed."""
    seen = weights > 0
    rgb = np.zeros(total.shape, dtype=np.float64)
    rgb[seen] = total[seen] / weights[seen, None]
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
