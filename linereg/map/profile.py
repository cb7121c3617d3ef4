"""What kind of cloud it is, measured, and the map-building parameters that follow from it.

Measured (``profile_cloud``): the median nearest-neighbour spacing s and its spread, how much the density
varies over the cloud (the spread of the distance to the 8th nearest neighbour), the noise (rms distance
of points to the plane of their neighbours), scan rings about the sensor origin (a spinning
LiDAR's sweep: runs of points in scan order whose azimuth advances in small steps, else one cone of
elevations per laser, about the point where the cones are sharpest: the sensor) and the gap between
rings. The kind follows: ``lidar_sweep`` (rings), ``scan`` (uneven: density falls with range from a
scanner), ``rgbd`` (even and dense: an RGB-D fusion, a room), ``map`` (even and coarser: a mobile-mapping
or SLAM map, voxelised).

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
    (m), the density spread (the 90th over the 10th percentile of the distance to the 8th nearest
    neighbour: 1.2-2 on RGB-D fusions, voxelised maps and such clouds thinned at random, 2.3-2.5 on the
    demo's four-station scan thinned to 10^6 points, 3.6 on a merged solid-state LiDAR courtyard, 4-16 on
    single sweeps), noise rms (m), rings (0: none) and the median angle between neighbouring rings (deg),
    how the rings were found ("scan order", "elevation" or ""), the sensor origin (given, or where the
    lasers' cones are sharpest when the rings were found by elevation; None: unknown)."""

    kind: str
    num_points: int
    spacing_m: float
    spacing_p10_m: float
    spacing_p90_m: float
    density_spread: float
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
) -> tuple[float, float, float, float, float]:
    """Returns (median, 10 %, 90 % nearest-neighbour distance, density spread, noise rms) of (P, 3) points.

    The density spread is taken on the distance to the ``density_neighbours``-th neighbour, not the
    nearest: points thinned at random (or sampled by any process without a grid) lie 4-5x farther from
    their nearest neighbour at the 90th percentile than at the 10th wherever the density is the same
    (the nearest distance on a surface of even density is Rayleigh-distributed), while the 8th neighbour's
    distance spreads 1.6x; a scanner's density falling with range spreads both."""
    if len(points) < 2:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    rng = np.random.default_rng(seed)
    tree = cKDTree(points)
    sample = points[rng.choice(len(points), min(config.spacing_sample, len(points)), replace=False)]
    kth = min(config.density_neighbours, len(points) - 1)
    distances, _ = tree.query(sample, k=kth + 1)
    nn = distances[:, 1]
    far = distances[:, kth]
    spread = float(np.percentile(far, 90) / max(float(np.percentile(far, 10)), 1e-12))
    k = min(16, len(points))
    few = sample[: config.noise_sample]
    _, idx = tree.query(few, k=k)
    nb = points[idx]  # (n, k, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    smallest = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", centred, centred) / k)[:, 0]
    noise = float(np.sqrt(np.median(np.maximum(smallest, 0.0)))) if k >= 4 else 0.0
    return float(np.median(nn)), float(np.percentile(nn, 10)), float(np.percentile(nn, 90)), spread, noise


def scan_rings(
    points: np.ndarray, origin: np.ndarray, config: MapProfileConfig | None = None
) -> tuple[np.ndarray, str, np.ndarray]:
    """Returns ((P,) int64 ring of each point, -1 for none; how they were found: "scan order",
    "elevation" or "" (no rings); (3,) the sensor origin they were found about).

    Scan order: a spinning LiDAR's points, stored as fired or ring by ring, advance in azimuth by a small
    step; a ring is a run of such points (``ring_step_deg``) of at least ``min_ring_points``, about the
    given ``origin``. Elevation: a sensor whose lasers fire in columns stores them interleaved, but each
    laser sweeps one cone about the sensor (``_laser_cones``), which also places the sensor.
    """
    config = config or MapProfileConfig()
    rel = points - origin
    none = np.full(len(points), -1, dtype=np.int64)
    if len(points) < config.min_ring_points * config.min_rings:
        return none, "", origin
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
        return np.where(long[run], ring[run], -1).astype(np.int64), "scan order", origin
    cones = _laser_cones(points, origin, config)
    if cones is None:
        return none, "", origin
    return cones[0], "elevation", cones[1]


def _laser_cones(
    points: np.ndarray, origin: np.ndarray, config: MapProfileConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """Returns ((P,) int64 ring of each point, -1 for none; (3,) the sensor origin) of a sweep whose lasers
    keep fixed elevations, or None when the points' elevations do not fall on ``min_rings`` such cones.

    Each laser sweeps a cone about the sensor: seen from there its returns share one elevation. A cloud
    whose frame origin lies off the lasers' (a sensor frame placed at the housing's base or centre, a
    vehicle's frame) blurs the near returns' elevations by the offset over the range (nuScenes' 32-laser
    sweep: 0.22 m, the near ground's rings smeared over degrees) while the far ones stay sharp. So the
    cones' elevations are taken first from the far half of the points, every point within ``cone_share``
    of the ring gap of one is given to it, the origin moved to where the given points' elevations match
    their cones best (Gauss-Newton), and again, from all points, until the origin stays put. Accepted when
    ``elevation_peak_share`` of the points beyond a metre lie on a cone of ``min_ring_points``."""
    if config.cone_rounds < 1:
        return None
    start = origin
    cones = nearest = given = distance = np.zeros(0)
    for round_ in range(config.cone_rounds):
        rel = points - origin
        horizontal = np.hypot(rel[:, 0], rel[:, 1])
        elevation = np.arctan2(rel[:, 2], horizontal)
        distance = np.linalg.norm(rel, axis=1)
        far = distance > 1.0  # within a metre the lasers' own spread on the housing blurs everything
        if round_ == 0 and far.any():  # first the far half, whose elevations an offset origin hardly blurs
            far &= distance >= np.median(distance[far])
        found = _cone_elevations(np.degrees(elevation[far]), config)
        if found is None:
            return None
        cones = found
        gap = float(np.median(np.diff(cones)))
        nearest, off = _nearest(np.degrees(elevation), cones)
        given = (np.abs(off) <= config.cone_share * gap) & (distance > 1.0)
        if round_ == config.cone_rounds - 1:
            break
        # d elevation / d origin of a point at rel = (x, y, z) about the origin
        x, y, z = rel[given].T
        r2 = np.maximum(distance[given] ** 2, 1e-12)
        h = np.maximum(horizontal[given], 1e-9)
        J = np.c_[z * x / (h * r2), z * y / (h * r2), -h / r2]
        e = elevation[given] - np.radians(cones[nearest[given]])
        H = J.T @ J
        move = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(3), J.T @ e)
        origin = origin + move
        if np.linalg.norm(origin - start) > config.max_origin_shift_m:
            return None
        if np.linalg.norm(move) < 1e-3:
            break
    counts = np.bincount(nearest[given], minlength=len(cones))
    kept = given & (counts[nearest] >= config.min_ring_points)
    if (counts >= config.min_ring_points).sum() < config.min_rings:
        return None
    if kept.sum() < config.elevation_peak_share * max((distance > 1.0).sum(), 1):
        return None
    label = np.cumsum(counts >= config.min_ring_points) - 1
    return np.where(kept, label[nearest], -1).astype(np.int64), origin


def rings_from_field(
    points: np.ndarray,
    field: np.ndarray,
    origin: np.ndarray,
    fit_origin: bool,
    config: MapProfileConfig | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Returns ((P,) int64 ring of each point, -1 for none, numbered by elevation from the lowest; (3,) the
    sensor origin) of a sweep whose (P,) ``field`` gives each point's laser (negative: none), or None.

    A file's ring field says which laser fired, not where the sensor was: a sweep stored in a vehicle's
    frame has its lasers metres from the frame's origin, where no elevation is constant along a ring.
    Each laser sweeps one cone about the sensor, so with ``fit_origin`` the origin and the lean of the
    sensor's axis (a vehicle's frame is seldom level with it: nuScenes' by 0.75 deg) are fitted
    (least squares on a sample of the returns, from ``origin`` and from above it, each ring's cone
    elevation estimated with them) where every ring's returns beyond a metre share one elevation, and the rings are
    kept when ``elevation_peak_share`` of those returns lie within ``cone_share`` of the median gap between
    the cones of their own: a field of something else (a return number, a grid's column) has no such cones,
    nor has a sensor whose lasers fit no single apex (KITTI's HDL-64 sweeps, to no better than half their
    ring gap), whose rings are then looked for as without a field. Without ``fit_origin`` the caller gave the sensor's position and the
    field is taken as it is. Either way at least ``min_rings`` lasers of ``min_ring_points`` returns."""
    config = config or MapProfileConfig()
    field = np.asarray(field).reshape(-1)
    usable = field >= 0
    values, raw = np.unique(field[usable], return_inverse=True)
    counts = np.bincount(raw, minlength=len(values))
    large = counts >= config.min_ring_points
    if not config.min_rings <= int(large.sum()) <= config.max_rings:
        return None
    label = np.full(len(points), -1, dtype=np.int64)
    label[np.flatnonzero(usable)[large[raw]]] = (np.cumsum(large) - 1)[raw[large[raw]]]
    n = int(large.sum())
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    if fit_origin:
        # from the frame's origin and above it (a vehicle's frame lies at the road or an axle, its lasers
        # a metre or two up: from the road every ground ring keeps one elevation, a false fit), the best
        starts = [origin + np.array([0.0, 0.0, h]) for h in config.field_heights_m]
        labelled = np.flatnonzero(label >= 0)  # fitted on a sample, judged on all below
        pick = np.random.default_rng(0).choice(
            labelled, min(config.spacing_sample, len(labelled)), replace=False
        )
        sample, at = points[pick], label[pick]
        fits: list[tuple[np.ndarray, float]] = []
        for start in starts:
            fits.append(_fit_cone_origin(sample, at, n, start, config.field_rounds, config.field_reach_m))
            if fits[-1][1] <= np.radians(config.field_sharp_deg) ** 2:
                break  # sharp already: the lasers' own scatter
        pose = min(fits, key=lambda f: f[1])[0]
    else:
        pose = np.r_[origin, 0.0, 0.0]
    origin = pose[:3]
    fit = _cones(points, label, n, pose)
    if fit is None or (fit[2] > 0).sum() < config.min_rings:
        return None
    cones, error, per = fit[0], fit[1], fit[2]
    seen = per > 0
    order = np.argsort(cones[seen])
    gap = float(np.median(np.diff(cones[seen][order])))
    if gap <= 0.0:
        return None
    if fit_origin and (np.abs(error) <= config.cone_share * gap).mean() < config.elevation_peak_share:
        return None
    rank = np.full(n, -1, dtype=np.int64)
    rank[np.flatnonzero(seen)[order]] = np.arange(int(seen.sum()))
    ring = np.where(label >= 0, rank[np.maximum(label, 0)], -1)
    return ring, origin


def _cones(
    points: np.ndarray, label: np.ndarray, n: int, pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Returns ((n,) each ring's mean elevation (rad), (k,) the elevation errors of the labelled points
    beyond a metre, (n,) their count per ring) about a sensor at ``pose[:3]`` whose axis leans by the small
    angles ``pose[3:5]`` (rad, about x then y); None with no point beyond a metre."""
    rel = points - pose[:3]
    if pose[3] or pose[4]:
        ca, sa, cb, sb = np.cos(pose[3]), np.sin(pose[3]), np.cos(pose[4]), np.sin(pose[4])
        tilt = np.array([[1.0, 0, 0], [0, ca, -sa], [0, sa, ca]]) @ np.array(
            [[cb, 0, sb], [0, 1.0, 0], [-sb, 0, cb]]
        )
        rel = rel @ tilt
    distance = np.linalg.norm(rel, axis=1)
    use = (label >= 0) & (distance > 1.0)  # within a metre the housing's own spread blurs them
    if not use.any():
        return None
    lab = label[use]
    per = np.bincount(lab, minlength=n)
    elevation = np.arctan2(rel[use, 2], np.hypot(rel[use, 0], rel[use, 1]))
    cones = np.bincount(lab, elevation, minlength=n) / np.maximum(per, 1)
    return cones, elevation - cones[lab], per


def _fit_cone_origin(
    points: np.ndarray, label: np.ndarray, n: int, origin: np.ndarray, rounds: int, reach_m: float
) -> tuple[np.ndarray, float]:
    """Returns ((5,) the sensor's position, within ``reach_m`` of ``origin`` in each axis, and its axis's
    lean (``_cones``) about which the labelled rings' elevations are most nearly constant, found by least
    squares (trust region) from ``origin`` and a level axis in at most ``rounds`` x 6 evaluations; the mean
    squared elevation error there, inf when none)."""
    from scipy.optimize import least_squares

    def errors(pose: np.ndarray) -> np.ndarray:
        fit = _cones(points, label, n, pose)
        # a pose leaving every point within a metre is no fit: errors of a right angle
        return np.full(len(points), np.pi / 2) if fit is None else np.resize(fit[1], len(points))

    start = np.r_[np.asarray(origin, dtype=np.float64).reshape(3), 0.0, 0.0]
    # bounded: a sensor ever farther away sees every return at one elevation (a false, perfect fit)
    reach = np.r_[np.full(3, reach_m), np.full(2, np.radians(30.0))]
    try:
        found = least_squares(
            errors,
            start,
            bounds=(start - reach, start + reach),
            max_nfev=6 * rounds,
            x_scale=[1, 1, 1, 0.01, 0.01],
        )
    except (ValueError, np.linalg.LinAlgError):
        return start, np.inf
    fit = _cones(points, label, n, found.x)
    return found.x, np.inf if fit is None else float(np.mean(fit[1] ** 2))


def _nearest(values: np.ndarray, sorted_values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N,) index of the nearest of the ascending (K >= 2,) ``sorted_values`` to each value, (N,)
    value minus it)."""
    right = np.clip(np.searchsorted(sorted_values, values), 1, len(sorted_values) - 1)
    left = right - 1
    pick = np.where(values - sorted_values[left] <= sorted_values[right] - values, left, right)
    return pick, values - sorted_values[pick]


def _cone_elevations(elevation_deg: np.ndarray, config: MapProfileConfig) -> np.ndarray | None:
    """Returns the ascending elevations (deg) of the peaks of a histogram of elevations (runs of bins
    above a tenth of the median occupied bin, each at its weighted mean; peaks closer than half the
    median spacing merged), or None for fewer than ``min_rings``."""
    if len(elevation_deg) == 0:
        return None
    b = config.elevation_bin_deg
    edges = np.arange(elevation_deg.min(), elevation_deg.max() + 2 * b, b)
    if len(edges) < 20:
        return None
    hist, _ = np.histogram(elevation_deg, edges)
    full = hist > 0.1 * np.median(hist[hist > 0])
    run = np.cumsum(np.r_[full[0], full[1:] & ~full[:-1]]) - 1
    centre = 0.5 * (edges[1:] + edges[:-1])
    weight = np.bincount(run[full], hist[full], minlength=run.max() + 1)
    mean = np.bincount(run[full], hist[full] * centre[full], minlength=run.max() + 1)
    ok = weight > 0
    peaks, weight = mean[ok] / weight[ok], weight[ok]
    if len(peaks) < config.min_rings:
        return None
    spacing = float(np.median(np.diff(peaks)))
    merged, mass = [peaks[0]], [weight[0]]
    for p, w in zip(peaks[1:], weight[1:], strict=True):
        if p - merged[-1] < 0.5 * spacing:
            merged[-1] = (merged[-1] * mass[-1] + p * w) / (mass[-1] + w)
            mass[-1] += w
        else:
            merged.append(p)
            mass.append(w)
    return np.array(merged) if len(merged) >= config.min_rings else None


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
    return profile_and_rings(points, sensor_origin, config)[0]


def profile_and_rings(
    points: np.ndarray,
    sensor_origin: np.ndarray | None = None,
    config: MapProfileConfig | None = None,
    rings: np.ndarray | None = None,
) -> tuple[CloudProfile, np.ndarray]:
    """Returns (``profile_cloud``'s CloudProfile, (P,) int64 ring of each point, -1 for none: all -1 when
    the profile has no rings), so that a map build finds the rings once. ``rings`` (P,) int: each point's
    laser number as the file gives it (a driver's ``ring`` field; -1: none), used when they are one
    sensor's cones (``rings_from_field``: source "field"), else the rings are looked for as without."""
    config = config or MapProfileConfig()
    points = check_points(points)
    if len(points) == 0:
        return CloudProfile("empty", 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0.0, "", None), np.zeros(0, np.int64)
    origin = np.zeros(3) if sensor_origin is None else np.asarray(sensor_origin, dtype=np.float64).reshape(3)
    spacing, p10, p90, spread, noise = _spacing(points, config)
    given = None if rings is None else rings_from_field(points, rings, origin, sensor_origin is None, config)
    if given is not None:
        ring, source, found = given[0], "field", given[1]
    else:
        ring, source, found = scan_rings(points, origin, config)
    count = int(ring.max()) + 1 if source else 0
    gap = ring_gap_deg(points, ring, found) if count else 0.0
    if gap <= 0.0:  # runs of points at one elevation (a grid's rows) are no laser rings
        count, source = 0, ""
        ring = np.full(len(points), -1, dtype=np.int64)
    if count:
        kind = "lidar_sweep"
    elif spread > config.uneven_ratio:
        kind = "scan"
    else:
        kind = "rgbd" if spacing <= config.dense_spacing_m else "map"
    known = count > 0 or sensor_origin is not None
    at = found if count else origin
    origin_out = (float(at[0]), float(at[1]), float(at[2])) if known else None
    profile = CloudProfile(
        kind, len(points), spacing, p10, p90, spread, noise, count, gap, source, origin_out
    )
    return profile, ring


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
