"""Edges of a single sweep's intensity: where the surface's reflectance steps along the scan rings.

Road markings, kerbs' paint, signs and window frames change the return intensity where the geometry goes
on flat: edges a camera sees that no geometric map holds (opt-in, ``MapBuildConfig.intensity_edges``: the
paper's maps are untextured). Along each ring (points sorted by azimuth about the sensor, neighbours no
wider apart than a few azimuth steps and without a range jump), the mean intensity of the ``window``
points after a gap minus that of the ``window`` before it is the step there; a step of at least
``contrast`` of the sweep's intensity spread (its 5-95 % range) that is the largest within ``window``
points, and stands ``noise_sigmas`` of its own noise (the returns' scatter along a ring) above zero, is an
edge point, placed between the two points. Edge points of neighbouring rings are linked and
cut into straight lines as the sweep's geometric edges are (``sensor_edges.lines_across_rings``).

A ring crosses an edge that runs across it; an edge running along a ring (a marking seen side-on at the
sensor's height) gives no steps and is not found.
"""

from __future__ import annotations

import numpy as np

from ..config import IntensityEdgesConfig, SensorEdgesConfig
from .sensor_edges import along_rings, lines_across_rings


def intensity_edges(
    points: np.ndarray,
    intensity: np.ndarray,
    ring: np.ndarray,
    sensor: np.ndarray,
    config: IntensityEdgesConfig | None = None,
    lines: SensorEdgesConfig | None = None,
) -> np.ndarray:
    """Returns (E, 6) float64 intensity edge segments of (P, 3) points with (P,) intensities and (P,) int64
    ring ids (-1: none) scanned from (3,) ``sensor``; ``lines`` configures the linking and line fitting."""
    config = config or IntensityEdgesConfig()
    lines = lines or SensorEdgesConfig()
    between, rings = step_points(points, intensity, ring, sensor, config)
    found = [line for line, _ in lines_across_rings(between, rings, sensor, lines)]
    return np.array(found, dtype=np.float64).reshape(-1, 6)


def step_points(
    points: np.ndarray,
    intensity: np.ndarray,
    ring: np.ndarray,
    sensor: np.ndarray,
    config: IntensityEdgesConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((n, 3) points midway between two ring neighbours across an intensity step, (n,) their
    rings)."""
    value = np.asarray(intensity, dtype=np.float64).reshape(-1)
    usable = (ring >= 0) & np.isfinite(value)
    if usable.sum() < 2 * config.window + 2:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    spread = float(np.subtract(*np.percentile(value[usable], [95, 5])))
    if not spread > 0:  # one intensity everywhere: nothing steps
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    order, rr, linked = along_rings(points, ring, sensor, usable)
    rg, v = ring[order], value[order]
    # neighbours on one surface: ring neighbours without a range jump
    linked &= np.abs(rr[1:] - rr[:-1]) <= config.max_range_step_fraction * np.minimum(rr[1:], rr[:-1])
    n, w = len(order), config.window
    run = np.cumsum(np.r_[0, ~linked])  # run id of each point: a window must not leave its run
    gap = np.arange(n - 1)  # the gap between points g and g + 1
    first, last = gap - w + 1, gap + w  # the window's first and last point
    inside = (first >= 0) & (last < n)
    inside &= run[np.clip(first, 0, n - 1)] == run[gap]
    inside &= run[np.clip(last, 0, n - 1)] == run[gap]
    total = np.r_[0.0, np.cumsum(v)]
    before = (total[gap + 1] - total[np.clip(first, 0, n)]) / w
    after = (total[np.clip(last + 1, 0, n)] - total[gap + 1]) / w
    jump = np.where(inside, np.abs(after - before), 0.0)
    # the noise of one return (robust, from neighbours on one surface): a step of two window means must
    # stand ``noise_sigmas`` of its own noise above it, as well as reach the contrast
    sigma = 1.4826 * float(np.median(np.abs(np.diff(v)[linked]))) / np.sqrt(2.0) if linked.any() else 0.0
    edge = jump >= max(config.contrast * spread, config.noise_sigmas * sigma * np.sqrt(2.0 / w))
    for k in range(1, w + 1):  # the largest step within the window
        edge[k:] &= jump[k:] >= jump[:-k]
        edge[:-k] &= jump[:-k] > jump[k:]
    g = np.flatnonzero(edge)
    a, b = points[order[g]], points[order[g + 1]]
    return 0.5 * (a + b), rg[g]
