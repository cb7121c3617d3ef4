"""What kind of cloud it is, measured, and the map-building parameters that follow from it.

Measured (``profile_cloud``): the median nearest-neighbour spacing s and its spread, the noise (rms
distance of points to the plane of their neighbours), scan rings about the sensor origin (a spinning
LiDAR's sweep: runs of points in scan order whose azimuth advances in small steps, else elevations
quantised into a few values) and the gap between rings. The kind follows: ``lidar_sweep`` (rings),
``scan`` (uneven: density falls with range from a scanner), ``rgbd`` (even and dense: an RGB-D fusion,
a room), ``map`` (even and coarser: a mobile-mapping or SLAM map, voxelised).

Chosen (``adapted_config``): the shortest segment ``12 s`` and the smallest region ``(15 s)^2``, clipped to
[0.15, 0.3] m and [0.03, 0.1] m^2 (a region must span some 15 points a side to give straight contours; a
room's structure, furniture, door frames and shelves, has faces of 0.03-0.1 m^2 and edges of 0.15-0.3 m);
plane-fit voxels of ``6 s`` in [0.05, 0.1] m; the plane distance from the noise; for a sweep the raster
cell of a region at least a share of the ring gap at its range. Fields the caller set to other values
than ``Lines3DConfig``'s defaults are kept.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..config import Lines3DConfig, MapProfileConfig
from .lines3d import check_points

KINDS = ("empty", "lidar_sweep", "scan", "rgbd", "map")


@dataclass(frozen=True)
class CloudProfile:
    """What a cloud is: ``kind`` (one of KINDS), point count, median spacing and its 10 / 90 % quantiles
    (m), noise rms (m), rings (0: none) and the median angle between neighbouring rings (deg), how the
    rings were found ("scan order", "elevation" or ""), the sensor origin used (or None)."""

    kind: str
    num_points: int
    spacing_m: float
    spacing_p10_m: float
    spacing_p90_m: float
    noise_m: float
    rings: int
    ring_gap_deg: float
    ring_source: str
    sensor_origin: tuple[float, float, float] | None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def point_spacing_m(points: np.ndarray, seed: int = 0, config: MapProfileConfig | None = None) -> float:
    """Returns the median nearest-neighbour distance (m) of (P, 3) points, estimated on a sample of
    ``config.spacing_sample`` of them (0.0 for fewer than two points)."""
    return _spacing(check_points(points), config or MapProfileConfig(), seed)[0]


def _spacing(
    points: np.ndarray, config: MapProfileConfig, seed: int = 0
) -> tuple[float, float, float, float]:
    """Returns (median, 10 %, 90 % nearest-neighbour distance, noise rms) of (P, 3) points."""
    if len(points) < 2:
        return 0.0, 0.0, 0.0, 0.0
    rng = np.random.default_rng(seed)
    tree = cKDTree(points)
    sample = points[rng.choice(len(points), min(config.spacing_sample, len(points)), replace=False)]
    distances, _ = tree.query(sample, k=2)
    nn = distances[:, 1]
    k = min(16, len(points))
    few = sample[: config.noise_sample]
    _, idx = tree.query(few, k=k)
    nb = points[idx]  # (n, k, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    smallest = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", centred, centred) / k)[:, 0]
    noise = float(np.sqrt(np.median(np.maximum(smallest, 0.0)))) if k >= 4 else 0.0
    return float(np.median(nn)), float(np.percentile(nn, 10)), float(np.percentile(nn, 90)), noise


def scan_rings(
    points: np.ndarray, origin: np.ndarray, config: MapProfileConfig | None = None
) -> tuple[np.ndarray, str]:
    """Returns ((P,) int64 ring of each point about (3,) ``origin``, -1 for none; how they were found:
    "scan order", "elevation" or "" (no rings)).

    Scan order: a spinning LiDAR's points, stored as fired or ring by ring, advance in azimuth by a small
    step; a ring is a run of such points (``ring_step_deg``) of at least ``min_ring_points``. Elevation: a
    sensor whose lasers fire in columns stores them interleaved, but each laser keeps one elevation, so
    most points fall in a few narrow elevation bins.
    """
    config = config or MapProfileConfig()
    rel = points - origin
    none = np.full(len(points), -1, dtype=np.int64)
    if len(points) < config.min_ring_points * config.min_rings:
        return none, ""
    azimuth = np.arctan2(rel[:, 1], rel[:, 0])
    signed = np.angle(np.exp(1j * np.diff(azimuth)))
    step = np.abs(signed)
    # a new ring: the azimuth steps back against the rotation (a cropped sweep) or crosses the back
    # (+-180 deg, where a full turn starts); forward gaps (no returns: sky, glass) stay in the ring
    rotation = np.sign(np.median(signed)) or 1.0
    cut = (
        np.flatnonzero(
            (rotation * signed < -np.radians(config.ring_step_deg)) | (np.abs(np.diff(azimuth)) > np.pi)
        )
        + 1
    )
    starts = np.r_[0, cut]
    lengths = np.diff(np.r_[starts, len(points)])
    # a ring sweeps a wide azimuth (a full turn, or the camera's field of view when cropped); a fused or
    # voxelised cloud stored in grid order has short runs that turn a few degrees
    turned = np.add.reduceat(np.r_[step, 0.0], starts) - np.r_[step[cut - 1], 0.0]
    long = (lengths >= config.min_ring_points) & (turned >= np.radians(config.min_ring_span_deg))
    if config.min_rings <= long.sum() <= config.max_rings and lengths[long].sum() >= 0.8 * len(points):
        run = np.repeat(np.arange(len(starts)), lengths)
        ring = np.cumsum(long) - 1
        return np.where(long[run], ring[run], -1).astype(np.int64), "scan order"
    elevation = np.degrees(np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1])))
    far = np.linalg.norm(rel, axis=1) > 1.0  # near the sensor its lasers' offsets blur the elevations
    edges = np.arange(elevation[far].min(), elevation[far].max() + 2 * config.elevation_bin_deg,
                      config.elevation_bin_deg) if far.any() else np.zeros(0)  # fmt: skip
    if len(edges) < 20:
        return none, ""
    hist, _ = np.histogram(elevation[far], edges)
    top = np.sort(hist)[::-1]
    if np.cumsum(top)[len(top) // 10] < config.elevation_peak_share * far.sum():
        return none, ""
    # the rings are the runs of full bins (a bin above a tenth of the median full bin)
    full = hist > 0.1 * np.median(hist[hist > 0])
    label = np.cumsum(np.r_[full[0], full[1:] & ~full[:-1]]) - 1
    which = np.clip(np.searchsorted(edges, elevation, side="right") - 1, 0, len(hist) - 1)
    ring = np.where(full[which] & far, label[which], -1)
    counts = np.bincount(ring[ring >= 0], minlength=int(label.max()) + 1)
    if (counts >= config.min_ring_points).sum() < config.min_rings:
        return none, ""
    return np.where(
        (ring >= 0) & (counts[np.maximum(ring, 0)] >= config.min_ring_points), ring, -1
    ), "elevation"


def ring_gap_deg(points: np.ndarray, ring: np.ndarray, origin: np.ndarray, sample: int = 5000) -> float:
    """Returns the median elevation gap (deg) from a point to the nearest point of another ring at nearly
    the same azimuth (0.0: no rings). Local, so a ring stored as several runs does not halve it."""
    ok = np.flatnonzero(ring >= 0)
    if len(ok) < 2:
        return 0.0
    rel = points[ok] - origin
    az = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]))
    el = np.degrees(np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1])))
    # azimuth weighted 10x: neighbours straight above or below come first
    tree = cKDTree(np.c_[10.0 * az, el])
    pick = np.random.default_rng(0).choice(len(ok), min(sample, len(ok)), replace=False)
    k = min(24, len(ok))
    _, idx = tree.query(np.c_[10.0 * az[pick], el[pick]], k=k)
    d_el = np.abs(el[idx] - el[pick, None])
    other = (ring[ok][idx] != ring[ok][pick, None]) & (np.abs(az[idx] - az[pick, None]) < 0.5) & (d_el > 0.02)
    gap = np.where(other, d_el, np.inf).min(axis=1)
    gap = gap[np.isfinite(gap)]
    return float(np.median(gap)) if len(gap) else 0.0


def profile_cloud(
    points: np.ndarray, sensor_origin: np.ndarray | None = None, config: MapProfileConfig | None = None
) -> CloudProfile:
    """Returns the CloudProfile of (P, 3) points; rings are looked for about ``sensor_origin`` (None: the
    origin of the points' frame, where a single sweep in its sensor's frame has its sensor)."""
    config = config or MapProfileConfig()
    points = check_points(points)
    if len(points) == 0:
        return CloudProfile("empty", 0, 0.0, 0.0, 0.0, 0.0, 0, 0.0, "", None)
    origin = np.zeros(3) if sensor_origin is None else np.asarray(sensor_origin, dtype=np.float64).reshape(3)
    spacing, p10, p90, noise = _spacing(points, config)
    ring, source = scan_rings(points, origin, config)
    rings = int(ring.max()) + 1 if source else 0
    gap = ring_gap_deg(points, ring, origin) if rings else 0.0
    if gap <= 0.0:  # runs of points at one elevation (a grid's rows) are no laser rings
        rings, source = 0, ""
    if rings:
        kind = "lidar_sweep"
    elif p90 > config.uneven_ratio * max(p10, 1e-9):
        kind = "scan"
    else:
        kind = "rgbd" if spacing <= config.dense_spacing_m else "map"
    known = rings > 0 or sensor_origin is not None
    origin_out = tuple(float(v) for v in origin) if known else None
    return CloudProfile(kind, len(points), spacing, p10, p90, noise, rings, gap, source, origin_out)  # type: ignore[arg-type]


def adapted_config(
    profile: CloudProfile, base: Lines3DConfig | None = None, config: MapProfileConfig | None = None
) -> Lines3DConfig:
    """Returns ``base`` (default ``Lines3DConfig()``) with its cloud-dependent fields chosen from the
    profile (see the module docstring); fields of ``base`` that differ from the defaults are kept."""
    base = base or Lines3DConfig()
    config = config or MapProfileConfig()
    s = profile.spacing_m
    if s <= 0.0:
        return base
    chosen: dict[str, Any] = {
        "min_length_m": float(np.clip(config.length_spacings * s, *config.min_length_range_m)),
        "min_region_area_m2": float(np.clip((config.area_spacings * s) ** 2, *config.min_area_range_m2)),
        "voxel_m": float(np.clip(config.voxel_spacings * s, *config.voxel_range_m)),
        "distance_m": float(np.clip(config.noise_distances * profile.noise_m, *config.distance_range_m)),
    }
    if profile.kind in ("lidar_sweep", "scan"):
        # a scanner's spacing grows with range: the near ground's tiny spacing says nothing of the facades
        chosen |= {"min_length_m": base.min_length_m, "min_region_area_m2": base.min_region_area_m2}
        chosen |= {"voxel_m": base.voxel_m}
    if profile.rings:
        chosen["ring_cell_deg"] = config.ring_cell_share * profile.ring_gap_deg
    defaults = Lines3DConfig()
    keep = {f.name for f in fields(base) if getattr(base, f.name) != getattr(defaults, f.name)}
    return replace(base, **{k: v for k, v in chosen.items() if k not in keep})


def lines3d_config_for(
    points: np.ndarray, base: Lines3DConfig | None = None, config: MapProfileConfig | None = None
) -> Lines3DConfig:
    """Returns ``adapted_config`` of the profile of (P, 3) points (kept for callers of the first version)."""
    return adapted_config(profile_cloud(points, config=config), base, config)
