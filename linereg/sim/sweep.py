"""A simulated single sweep of a spinning LiDAR: rings of laser returns off rectangles, with intensities.

The lasers sit at fixed elevations and turn together in azimuth; each return is the nearest rectangle hit
(open3d's ray casting), its range perturbed by Gaussian noise, its intensity the rectangle's reflectance
plus noise. Points come in firing order, ring after ring, in the sensor's frame (the sensor at the origin):
what a driver writes for one revolution. Tests of the sweep's own edges (``map.sensor_edges``,
``map.intensity_edges``) and of the cloud profile run on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._open3d import open3d


@dataclass(frozen=True)
class SweepConfig:
    """A 64-laser spinning LiDAR (the elevations of a Velodyne HDL-64E, spaced evenly)."""

    rings: int = 64
    elevation_deg: tuple[float, float] = (-24.8, 2.0)  # lowest and highest laser
    azimuth_step_deg: float = 0.2
    max_range_m: float = 80.0
    range_noise_m: float = 0.01
    intensity_noise: float = 0.02


def box_quads(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> np.ndarray:
    """Returns the (6, 4, 3) faces of the axis-aligned box [lo, hi] (corners in order round each face)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    c = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], dtype=np.float64)
    faces = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    return c[np.array(faces)]


def ground_quad(
    z: float, half_m: float, x: tuple[float, float] | None = None, y: tuple[float, float] | None = None
) -> np.ndarray:
    """Returns a (1, 4, 3) horizontal rectangle at height z: [x0, x1] x [y0, y1] (default +-half_m)."""
    x0, x1 = x or (-half_m, half_m)
    y0, y1 = y or (-half_m, half_m)
    return np.array([[[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]], dtype=np.float64)


def spinning_sweep(
    quads: np.ndarray,
    reflectance: np.ndarray,
    rng: np.random.Generator,
    config: SweepConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ((P, 3) points, (P,) intensities, (P,) int64 ring of each) of one revolution seen from the
    origin against (Q, 4, 3) planar convex quads with (Q,) reflectances (where quads overlap, the ray meets
    the nearer: paint is a quad a millimetre above the road)."""
    config = config or SweepConfig()
    quads = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 3)
    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    vertices = quads.reshape(-1, 3).astype(np.float32)
    base = 4 * np.arange(len(quads), dtype=np.uint32)[:, None]
    triangles = np.concatenate([base + np.array([0, 1, 2]), base + np.array([0, 2, 3])]).astype(np.uint32)
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
    elevation = np.radians(np.linspace(*config.elevation_deg, config.rings))
    azimuth = np.radians(np.arange(0.0, 360.0, config.azimuth_step_deg))
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")  # ring after ring, azimuth increasing
    directions = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    rays = np.concatenate([np.zeros_like(directions), directions], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(np.float64)
    face = hit["primitive_ids"].numpy().astype(np.int64) % len(quads)
    ok = np.isfinite(t) & (t <= config.max_range_m)
    t = np.where(ok, t, 0.0) + rng.normal(0.0, config.range_noise_m, len(t))
    points = directions * t[:, None]
    value = np.asarray(reflectance, dtype=np.float64)[face] + rng.normal(0.0, config.intensity_noise, len(t))
    ring = np.repeat(np.arange(config.rings), len(azimuth))
    return points[ok], value[ok], ring[ok]


STREET_GROUND = -1.7  # ``street``: the sensor 1.7 m above the road, at the origin of its own frame
STREET_PAINT_Y = (-2.3, -2.0)  # ... a 30 cm road marking running ahead of the car, from 4 to 14 m


def street() -> tuple[np.ndarray, np.ndarray]:
    """Returns ((Q, 4, 3) quads, (Q,) reflectances) of a road seen from a car: the ground 1.7 m below the
    sensor, a road marking a hair above it, a building beside the road (x 10-20 m, y 2-12 m, 8 m tall)."""
    quads = np.concatenate(
        [
            ground_quad(STREET_GROUND, 60.0),
            ground_quad(STREET_GROUND + 0.002, 0.0, x=(4.0, 14.0), y=STREET_PAINT_Y),
            box_quads((10.0, 2.0, STREET_GROUND), (20.0, 12.0, STREET_GROUND + 8.0)),
        ]
    )
    return quads, np.r_[0.15, 0.8, np.full(6, 0.4)]
