"""Looking at a procedural building: the street camera, occlusion tests, visible edges, street-level poses.

Split from ``building`` (the surface model): everything here takes a ``Building`` and a viewpoint.
"""

from __future__ import annotations

import logging

import numpy as np

from ..camera import Camera
from ..errors import LineregError
from ..geometry import camera_center, project_points, segment_lengths, transform_points
from .building import Building, block_facades
from .synthetic import MIN_LENGTH_PX, clip_to_box, look_at

logger = logging.getLogger(__name__)


def street_camera() -> Camera:
    """Returns the default camera for building scenes: 640x480, f = 600 (a wider field of view)."""
    return Camera(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480)


def _ray_hits(centre: np.ndarray, rays: np.ndarray, quads: np.ndarray, eps_m: float) -> np.ndarray:
    """Returns (R,) bool: does the open segment centre -> centre + ray cross a quad more than eps_m early?

    rays: (R, 3) from the centre to the tested points; quads: (F, 4, 3) rectangles. Hits on a quad's
    border or at the tested point itself (which lies on its own faces) do not count.
    """
    p0, e1, e2 = quads[:, 0], quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0]
    n = np.cross(e1, e2)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.einsum("fk,fk->f", p0 - centre, n) / (rays @ n.T)  # (R, F) ray parameter of the plane
    s_max = 1.0 - eps_m / np.linalg.norm(rays, axis=1, keepdims=True)
    ok = (s > 0.0) & (s < s_max)
    rel = centre - p0  # hit - p0 = rel + s * ray
    a = (np.einsum("fk,fk->f", rel, e1) + s * (rays @ e1.T)) / np.einsum("fk,fk->f", e1, e1)
    b = (np.einsum("fk,fk->f", rel, e2) + s * (rays @ e2.T)) / np.einsum("fk,fk->f", e2, e2)
    return (ok & (a > 0) & (a < 1) & (b > 0) & (b < 1)).any(axis=1)


def occluded(building: Building, centre: np.ndarray, points: np.ndarray, eps_m: float = 1e-3) -> np.ndarray:
    """Returns (P,) bool: is each world point hidden from ``centre`` by a face of the building?

    Only faces turned towards the centre are tested (blocks are closed solids standing on the ground, so a
    ray meets a front face first), and only for rays that enter the block's bounding box. The ground never
    occludes (the centre is above it).
    """
    rays = points - centre
    hidden = np.zeros(len(points), dtype=bool)
    front = np.einsum("fk,fk->f", centre - building.faces[:, 0], building.normals) > 0
    margin = 1.0  # covers ledges
    for b, (lo, hi) in enumerate(building.blocks):
        t0, t1 = clip_to_box(
            np.broadcast_to(centre, rays.shape),
            rays,
            lo - margin,
            hi + margin,
            np.zeros(len(rays)),
            np.ones(len(rays)),
        )
        todo = np.flatnonzero((t0 < t1) & ~hidden)
        quads = building.faces[front & (building.face_block == b)]
        for chunk in np.array_split(todo, max(1, len(todo) // 2048)):
            hidden[chunk] = _ray_hits(centre, rays[chunk], quads, eps_m)
    return hidden


def _frustum_interval(
    ends_cam: np.ndarray, camera: Camera, min_depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns (t0, t1) (E,): the part ``a + t (b - a)`` of each camera-frame segment that the image shows.

    ends_cam: (E, 6). The view frustum is 5 half-spaces linear in the point, e.g. ``u >= 0 <=> fx X + cx Z >= 0``.
    """
    a, b = ends_cam[:, 0:3], ends_cam[:, 3:6]
    w, h = camera.width - 1.0, camera.height - 1.0
    G = np.array(  # rows: u >= 0, u <= w, v >= 0, v <= h, Z >= min depth (all as G @ P >= 0 plus offset)
        [
            [camera.fx, 0, camera.cx],
            [-camera.fx, 0, w - camera.cx],
            [0, camera.fy, camera.cy],
            [0, -camera.fy, h - camera.cy],
            [0, 0, 1],
        ]
    )
    offset = np.array([0, 0, 0, 0, -min_depth_m])
    ga, gb = a @ G.T + offset, b @ G.T + offset
    n = len(a)
    return clip_to_box(ga, gb - ga, np.zeros(5), np.full(5, np.inf), np.zeros(n), np.ones(n))


def _longest_runs(visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (first, last) (E,) sample indices of each row's longest run of True (last < first: none)."""
    count = np.zeros(len(visible), dtype=np.int64)
    best, best_end = np.zeros_like(count), np.full(len(visible), -1)
    for k in range(visible.shape[1]):
        count = (count + 1) * visible[:, k]
        better = count > best
        best, best_end = np.where(better, count, best), np.where(better, k, best_end)
    return best_end - best + 1, best_end


def visible_segments(
    building: Building, camera: Camera, cam_from_world: np.ndarray, samples: int = 12, refine: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, 6) world sub-segments a camera sees, (K,) int64 edge indices) of the building's edges.

    Each edge is cut to the view frustum, sampled at ``samples`` points tested for occlusion; the longest
    visible run is kept and its occluded ends are located by ``refine`` bisection steps.
    """
    ends = transform_points(cam_from_world, building.edges.reshape(-1, 3)).reshape(-1, 6)
    t0, t1 = _frustum_interval(ends, camera, min_depth_m=0.1)
    idx = np.flatnonzero(t1 - t0 > 1e-9)
    t0, t1, edges = t0[idx], t1[idx], building.edges[idx]
    centre = camera_center(cam_from_world)

    def at(t: np.ndarray) -> np.ndarray:
        return edges[:, 0:3] + t[..., None] * (edges[:, 3:6] - edges[:, 0:3])

    ts = t0[:, None] + (t1 - t0)[:, None] * np.linspace(0.0, 1.0, samples)[None, :]
    pts = np.swapaxes(at(ts.T), 0, 1).reshape(-1, 3)
    vis = ~occluded(building, centre, pts).reshape(-1, samples)
    first, last = _longest_runs(vis)
    keep = last >= first
    rows = np.arange(len(idx))
    lo_in, hi_in = ts[rows, np.maximum(first, 0)], ts[rows, np.maximum(last, 0)]
    lo_out = np.where(first > 0, ts[rows, np.maximum(first - 1, 0)], lo_in)  # occluded neighbours
    hi_out = np.where(last < samples - 1, ts[rows, np.minimum(last + 1, samples - 1)], hi_in)
    for _ in range(refine):  # bisection of each end between its last visible and first hidden sample
        mid_lo, mid_hi = 0.5 * (lo_in + lo_out), 0.5 * (hi_in + hi_out)
        hid = occluded(building, centre, np.r_[at(mid_lo), at(mid_hi)]).reshape(2, -1)
        lo_in, lo_out = np.where(hid[0], lo_in, mid_lo), np.where(hid[0], mid_lo, lo_out)
        hi_in, hi_out = np.where(hid[1], hi_in, mid_hi), np.where(hid[1], mid_hi, hi_out)
    keep &= hi_in > lo_in
    return np.c_[at(lo_in), at(hi_in)][keep], idx[keep].astype(np.int64)


def project_building(
    building: Building, camera: Camera, cam_from_world: np.ndarray, min_length_px: float = MIN_LENGTH_PX
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K, 4) noise-free image segments, (K,) int64 edge indices) of the visible building edges."""
    seg3d, idx = visible_segments(building, camera, cam_from_world)
    cam = transform_points(cam_from_world, seg3d.reshape(-1, 3))
    seg = project_points(camera, cam).reshape(-1, 4)
    keep = segment_lengths(seg) >= min_length_px
    return seg[keep], idx[keep]


def is_free(building: Building, centre: np.ndarray, clearance_m: float = 1.0) -> bool:
    """Returns whether a point is on the ground plane's area and at least clearance_m away from every block."""
    inside_ground = np.all(centre[:2] > building.bounds[0, :2] + clearance_m) and np.all(
        centre[:2] < building.bounds[1, :2] - clearance_m
    )
    lo, hi = building.blocks[:, 0] - clearance_m, building.blocks[:, 1] + clearance_m
    return bool(inside_ground and not np.any(np.all((centre > lo) & (centre < hi), axis=1)))


def street_view(rng: np.random.Generator, building: Building) -> tuple[np.ndarray, np.ndarray]:
    """Returns (camera centre, target point) for a random facade seen from the street, not yet checked."""
    facades = [
        (f, length, blk[1, 2])
        for blk in building.blocks
        for f, length, _ in block_facades(blk[:, :2].ravel())
    ]
    areas = np.array([length * h for _, length, h in facades])
    frame, length, height = facades[rng.choice(len(facades), p=areas / areas.sum())]
    distance_m, s = rng.uniform(8.0, 30.0), rng.uniform(0.2, 0.8) * length
    lateral = distance_m * np.tan(np.radians(rng.uniform(-35.0, 35.0)))  # oblique views too
    centre = frame.lift(s + lateral, rng.uniform(1.5, 2.0), distance_m)
    return centre, frame.lift(s, rng.uniform(0.2, 0.45) * height)


def aim(rng: np.random.Generator, centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Returns (4, 4) cam_from_world looking roughly at target: yaw jitter 10 deg, pitch -5..15 deg, roll 3 deg."""
    to = target - centre
    yaw = np.arctan2(to[1], to[0]) + np.radians(rng.uniform(-10.0, 10.0))
    pitch = np.clip(np.arctan2(to[2], np.linalg.norm(to[:2])), np.radians(-5.0), np.radians(15.0))
    pitch += np.radians(rng.uniform(-3.0, 3.0))
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    return look_at(centre, centre + forward, np.radians(rng.uniform(-3.0, 3.0)))


def camera_poses(
    building: Building,
    rng: np.random.Generator,
    n: int,
    camera: Camera | None = None,
    min_visible_edges: int = 60,
    max_tries: int = 200,
) -> list[np.ndarray]:
    """Returns n (4, 4) cam_from_world of street-level cameras (1.5-2 m high) that see the building well.

    A facade is drawn with probability proportional to its area; the camera stands 8-30 m in front of it
    (up to 35 degrees off its normal), outside every block, with a free line of sight to a facade point it
    aims at, and must see at least ``min_visible_edges`` edges of 20 px or more (occlusion handled).
    """
    camera = camera or street_camera()
    poses: list[np.ndarray] = []
    for _ in range(max_tries * max(n, 1)):
        if len(poses) == n:
            break
        centre, target = street_view(rng, building)
        if not is_free(building, centre) or occluded(building, centre, target[None])[0]:
            continue
        cam_from_world = aim(rng, centre, target)
        if _sees_enough(building, camera, cam_from_world, min_visible_edges):
            poses.append(cam_from_world)
    if len(poses) < n:
        raise LineregError(f"camera_poses: found {len(poses)} of {n} street views in {max_tries * n} tries")
    return poses


def _sees_enough(building: Building, camera: Camera, cam_from_world: np.ndarray, min_edges: int) -> bool:
    """Returns whether the view shows at least min_edges edges of MIN_LENGTH_PX or more (occlusion handled).

    A half-resolution z-buffer count decides when it is far from the threshold (below half of it or
    above 1.5 times it); only views near the threshold pay for the exact, several times slower ray-cast
    count of ``project_building``, so the choice of views is the same as with ray casting alone.
    """
    from .render import rasterize, scaled_camera, visible_edge_lengths  # render imports this module

    face_id, inv_depth = rasterize(building, cam_from_world, scaled_camera(camera, 0.5))
    quick = int(
        (visible_edge_lengths(building, cam_from_world, camera, face_id, inv_depth) >= MIN_LENGTH_PX).sum()
    )
    if quick >= 1.5 * min_edges or quick < 0.5 * min_edges:
        return quick >= min_edges
    return len(project_building(building, camera, cam_from_world)[0]) >= min_edges
