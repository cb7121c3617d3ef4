"""Which map segments a camera sees: in front of it, inside its image, not hidden by the map's surfaces.

``visible_parts``: each segment is clipped to the near plane, sampled every ``sample_px`` pixels of its
image and each sample ray-cast from the camera centre against the surface mesh (open3d's
``RaycastingScene``); runs of visible samples are the visible sub-segments. A segment lying ON a surface
(a plane's boundary, a crease) meets it at its own range, so a sample is hidden only by a surface nearer
than its range by a tolerance that grows with range. Before any of it, chunks of nearby segments whose box
lies wholly outside the view's pyramid are left out (``chunks.Chunks``): on a large map most of them.

``potentially_visible``: the segments visible from SOME point of an axis-aligned box, conservatively. A
piece of a segment is hidden from the whole box by one convex occluder (a surface rectangle) exactly when
the box and the piece lie strictly on opposite sides of the occluder's plane and the 8 x 2 crossings of
that plane by the lines from the box corners to the piece ends fall inside the occluder: the crossing of
any line from the box to the piece lies in the convex hull of those 16 (central projection keeps segments
straight). A segment is left out only when all its pieces are hidden, each by one occluder.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from ..camera import Camera
from ..chunks import Chunks, side_normals
from ..config import VisibilityConfig
from ..geometry import camera_center
from .surfaces import Surfaces

UNIONS_KEPT = 64  # cached unions of cell sets (``potentially_visible``): a tracker's boxes of recent frames


class Visibility:
    """Visibility queries over (M, 6) float64 ``segments`` and the ``surfaces`` (or None) that may hide
    them; the ray-casting scene, the occluders and the potentially-visible sets are built on first use."""

    def __init__(
        self, segments: np.ndarray, surfaces: Surfaces | None, config: VisibilityConfig | None = None
    ):
        self.segments = np.ascontiguousarray(segments, dtype=np.float64)  # as the compiled sampling reads it
        self.surfaces = surfaces if surfaces is not None and len(surfaces) else None
        self.config = config or VisibilityConfig()
        self._scene: Any = None
        self._occluders: tuple[np.ndarray, np.ndarray] | None = None
        self._pieces: tuple[np.ndarray, np.ndarray] | None = None
        self._pvs: dict[tuple[int, ...], np.ndarray] = {}
        self._chunks: Chunks | None = None
        # the unions of the cells of a box, newest last: a tracker asks for the same few boxes each frame
        self._unions: dict[tuple[int, ...], np.ndarray] = {}

    # ------------------------------------------------------------------------------------ one camera

    def visible_parts(
        self, camera: Camera, cam_from_world: np.ndarray, index: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((K, 6) float64 visible world sub-segments, (K,) int64 row of the segment each came
        from) of the rows ``index`` (None: all) seen by the pinhole ``camera`` at (4, 4) ``cam_from_world``."""
        cfg = self.config
        cam_from_world = np.asarray(cam_from_world, dtype=np.float64)
        # the chunks of nearby segments wholly outside the view's pyramid first: a query's work then follows
        # what its view reaches, not the map's size (on a city of tiled blocks most chunks lie aside)
        rows = self._chunk_set().rows_in_view(camera, cam_from_world, cfg.min_depth_m, index)
        R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
        seg = self.segments[rows]
        a, b = seg[:, :3] @ R.T + t, seg[:, 3:] @ R.T + t
        # in one compiled pass (``_samples``): a segment wholly outside one face of the view's pyramid
        # (widened by a pixel) is left out before the exact clipping to the near plane and the image, which
        # would leave it out too; the rest are sampled every ``sample_px`` of their image
        kept, count, owner, tt, points = _samples(
            self.segments, rows, a, b, cfg.min_depth_m, camera.fx, camera.fy, camera.cx,
            camera.cy, float(camera.width), float(camera.height), cfg.sample_px, cfg.max_samples,
        )  # fmt: skip
        rows = rows[kept]
        seen = self._unoccluded(points, camera_center(cam_from_world))
        return _runs(self.segments[rows], rows, owner, tt, seen, count)

    def prepare(self) -> None:
        """Builds what every ``visible_parts`` call needs (the chunks, the ray-casting scene) now."""
        self._chunk_set()
        if self.surfaces is not None:
            self._raycasting_scene()

    def _chunk_set(self) -> Chunks:
        if self._chunks is None:
            self._chunks = Chunks.build(self.segments)
        return self._chunks

    def footprint(self, camera: Camera, cam_from_world: np.ndarray, cell_px: float) -> np.ndarray | None:
        """Returns (h, w) bool cells of ``cell_px`` pixels (cell (r, c) centred on pixel
        ((c + 0.5) cell_px - 0.5, (r + 0.5) cell_px - 0.5)) whose ray from the camera meets one of the
        map's surfaces: where the map holds something to explain an image line. None without surfaces."""
        if self.surfaces is None:
            return None
        from .._open3d import open3d

        o3d = open3d()
        h, w = int(np.ceil(camera.height / cell_px)), int(np.ceil(camera.width / cell_px))
        u = ((np.arange(w) + 0.5) * cell_px - 0.5 - camera.cx) / camera.fx
        v = ((np.arange(h) + 0.5) * cell_px - 0.5 - camera.cy) / camera.fy
        rays = np.empty((h, w, 6), dtype=np.float32)
        rays[..., :3] = camera_center(cam_from_world) - self.surfaces.origin
        R = np.asarray(cam_from_world, dtype=np.float64)[:3, :3]
        # world direction R^T (u, v, 1) of each cell's pixel
        rays[..., 3:] = u[None, :, None] * R[0] + v[:, None, None] * R[1] + R[2]
        hit = self._raycasting_scene().cast_rays(o3d.core.Tensor(rays.reshape(-1, 6)))["t_hit"].numpy()
        return np.isfinite(hit).reshape(h, w)

    def _unoccluded(self, points: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """Returns (S,) bool: is no surface nearer than each (S, 3) point along its ray from (3,) centre?"""
        if self.surfaces is None or len(points) == 0:
            return np.ones(len(points), dtype=bool)
        from .._open3d import open3d

        o3d = open3d()
        scene = self._raycasting_scene()
        # rays from the centre (in the mesh's frame) to each point, unnormalised: the point lies at t = 1
        rays, dist = _rays_to(points, np.asarray(centre, dtype=np.float64), self.surfaces.origin)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        cfg = self.config
        return _not_behind(hit, dist, cfg.depth_tolerance_m, cfg.depth_tolerance_fraction)

    def _raycasting_scene(self) -> Any:
        if self._scene is None:
            from .._open3d import open3d

            o3d = open3d()
            scene = o3d.t.geometry.RaycastingScene()
            assert self.surfaces is not None
            scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(self.surfaces.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(self.surfaces.triangles, dtype=np.uint32)),
            )
            self._scene = scene
        return self._scene

    # ------------------------------------------------------------------------------------ a box of centres

    def cell_m(self) -> float:
        """Returns the edge (m) of the cells whose potentially-visible sets are cached."""
        if self.config.pvs_cell_m > 0:
            return self.config.pvs_cell_m
        ends = self.segments.reshape(-1, 3)
        extent = float(np.ptp(ends, axis=0).max()) if len(ends) else 0.0
        return max(extent / 16.0, 0.5)

    def potentially_visible(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Returns (k,) int64 sorted rows of the segments that may be visible from some point of the box
        [lo, hi] ((3,) each): never leaves out a segment visible from a point of the box."""
        lo, hi = np.asarray(lo, dtype=np.float64).reshape(3), np.asarray(hi, dtype=np.float64).reshape(3)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (hi < lo).any():
            from ..errors import InvalidInputError

            raise InvalidInputError(f"potentially_visible needs finite lo <= hi, got {lo}, {hi}")
        if self.surfaces is None or len(self.segments) == 0:
            return np.arange(len(self.segments))
        size = self.cell_m()
        c0, c1 = np.floor(lo / size).astype(np.int64), np.floor(hi / size).astype(np.int64)
        if np.prod(c1 - c0 + 1) > 27:  # a big box: one test of the box rounded out to cells (conservative)
            return self._box_set((*c0, *c1), c0 * size, (c1 + 1) * size)
        key = (*c0, *c1)
        if key not in self._unions:
            cells = np.stack(np.meshgrid(*[np.arange(i, j + 1) for i, j in zip(c0, c1, strict=True)]), -1)
            sets = [self._box_set((*c, *c), c * size, (c + 1) * size) for c in cells.reshape(-1, 3)]
            if len(self._unions) >= UNIONS_KEPT:
                self._unions.pop(next(iter(self._unions)), None)
            union = np.unique(np.concatenate(sets))
            union.setflags(write=False)
            self._unions[key] = union
        return self._unions[key]

    def _box_set(self, key: tuple[int, ...], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        if key not in self._pvs:
            rows = self._not_hidden(lo, hi)
            rows.setflags(write=False)  # shared by every caller
            self._pvs[key] = rows
        return self._pvs[key]

    def _not_hidden(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Returns (k,) int64 rows of the segments not hidden, piece by piece, by single occluders from
        every point of the box [lo, hi]."""
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1).reshape(8, 3)
        polygons, normals = self._occluder_set()
        ends, owner = self._piece_set()
        cfg = self.config
        open_ = _open_pieces(
            corners, lo, hi, polygons, normals, ends, cfg.pvs_margin_m, cfg.depth_tolerance_m,
            cfg.depth_tolerance_fraction,
        )  # fmt: skip
        return np.unique(owner[open_])

    def _occluder_set(self) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((Q, 4, 3) convex polygons in the map frame, (Q, 3) unit normals): the mesh's
        rectangles (triangle pairs 2k, 2k + 1 sharing an edge) and lone triangles, largest first."""
        if self._occluders is None:
            assert self.surfaces is not None
            v = self.surfaces.world_vertices()[self.surfaces.triangles]  # (T, 3, 3)
            polys = _quads(v, self.surfaces.triangles)
            n = np.cross(polys[:, 1] - polys[:, 0], polys[:, 2] - polys[:, 0])
            area = np.linalg.norm(n, axis=1)
            keep = np.argsort(-area, kind="stable")[: self.config.pvs_max_occluders]
            keep = keep[area[keep] > 1e-9]
            self._occluders = (polys[keep], n[keep] / area[keep, None])
        return self._occluders

    def _piece_set(self) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((N, 2, 3) piece ends, (N,) int64 segment of each): segments cut into pvs_piece_m."""
        if self._pieces is None:
            a, b = self.segments[:, :3], self.segments[:, 3:]
            count = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / self.config.pvs_piece_m), 1)
            count = count.astype(np.int64)
            owner = np.repeat(np.arange(len(a)), count)
            k = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
            f0, f1 = k / count[owner], (k + 1) / count[owner]
            d = (b - a)[owner]
            ends = np.stack([a[owner] + f0[:, None] * d, a[owner] + f1[:, None] * d], axis=1)
            self._pieces = (ends, owner)
        return self._pieces


# ---------------------------------------------------------------------------------------------- helpers


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _samples(
    segments: np.ndarray,
    rows: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    near: float,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: float,
    height: float,
    sample_px: float,
    max_samples: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns (kept (n,) positions in ``rows`` of the segments some part of which projects into the image,
    (n,) samples of each, (S,) owner (position in kept) of each sample, (S,) its parameter along its world
    segment, (S, 3) its world point) of the map ``segments`` ``rows`` whose camera-frame ends are ``a``,
    ``b`` (K, 3): segments both of whose ends lie outside one side face of the view's pyramid (widened by a
    pixel) or nearer than ``near`` are left out, the rest clipped to the near plane and to the image
    (Liang-Barsky on the 2D segment, its parameters mapped back to 3D) and sampled uniformly in the image,
    every ``sample_px`` (at most ``max_samples`` + 1 per segment; a 2D parameter s maps to t = s z_a / (z_b
    (1 - s) + s z_a)). The rules written plainly with numpy, which this reproduces to the bit:
    ``tests/plain_visibility.py``."""
    n_in = len(rows)
    inward = side_normals(fx, fy, cx, cy, width, height)
    kept = np.empty(n_in, np.int64)
    lo_t, hi_t, count = np.empty(n_in), np.empty(n_in), np.empty(n_in, np.int64)
    n = 0
    total = 0
    for k in range(n_in):
        ax, ay, az, bx, by, bz = a[k, 0], a[k, 1], a[k, 2], b[k, 0], b[k, 1], b[k, 2]
        if az < near and bz < near:  # wholly nearer than the near plane
            continue
        outside = False
        for f in range(4):
            da = ax * inward[f, 0] + ay * inward[f, 1] + az * inward[f, 2]
            db = bx * inward[f, 0] + by * inward[f, 1] + bz * inward[f, 2]
            if da < 0.0 and db < 0.0:
                outside = True
                break
        if outside:
            continue
        # the near plane
        t0, t1 = 0.0, 1.0
        cross = (near - az) / (bz - az)
        if az < near and bz >= near:
            t0 = cross
        if bz < near and az >= near:
            t1 = cross
        # the image: Liang-Barsky on the 2D segment, its parameters mapped back to 3D
        dx, dy, dz = bx - ax, by - ay, bz - az
        pax, pay, paz = ax + t0 * dx, ay + t0 * dy, az + t0 * dz
        pbx, pby, pbz = ax + t1 * dx, ay + t1 * dy, az + t1 * dz
        p0x, p0y = fx * pax / paz + cx, fy * pay / paz + cy
        p1x, p1y = fx * pbx / pbz + cx, fy * pby / pbz + cy
        ddx, ddy = p1x - p0x, p1y - p0y
        s0, s1 = 0.0, 1.0
        ok = True
        for e in range(4):
            if e == 0:
                q, r = 1.0 * (p0x - -0.5), 1.0 * ddx
            elif e == 1:
                q, r = -1.0 * (p0x - (width - 0.5)), -1.0 * ddx
            elif e == 2:
                q, r = 1.0 * (p0y - -0.5), 1.0 * ddy
            else:
                q, r = -1.0 * (p0y - (height - 0.5)), -1.0 * ddy
            cut = -q / r
            if r > 0:
                s0 = _nan_max(s0, cut)
            if r < 0:
                s1 = _nan_min(s1, cut)
            if r == 0 and q < 0:
                ok = False
        if not (ok and s1 > s0 and np.isfinite(s0) and np.isfinite(s1)):
            continue
        za, zb = paz, pbz
        u0 = s0 * za / (zb * (1 - s0) + s0 * za)
        u1 = s1 * za / (zb * (1 - s1) + s1 * za)
        span = t1 - t0
        t0, t1 = t0 + u0 * span, t0 + u1 * span
        # the samples' count: every sample_px of the clipped segment's image
        qax, qay, qaz = ax + t0 * dx, ay + t0 * dy, az + t0 * dz
        qbx, qby, qbz = ax + t1 * dx, ay + t1 * dy, az + t1 * dz
        ux, uy = fx * qax / qaz + cx, fy * qay / qaz + cy
        vx, vy = fx * qbx / qbz + cx, fy * qby / qbz + cy
        ex, ey = vx - ux, vy - uy
        c = min(max(np.ceil(np.sqrt(ex * ex + ey * ey) / sample_px), 1.0), float(max_samples))
        kept[n], lo_t[n], hi_t[n], count[n] = k, t0, t1, int(c) + 1
        n += 1
        total += int(c) + 1
    owner, tt, points = np.empty(total, np.int64), np.empty(total), np.empty((total, 3))
    j = 0
    for i in range(n):
        k = kept[i]
        ax, ay, az, bx, by, bz = a[k, 0], a[k, 1], a[k, 2], b[k, 0], b[k, 1], b[k, 2]
        t0, t1 = lo_t[i], hi_t[i]
        za, zb = az + t0 * (bz - az), az + t1 * (bz - az)
        world = segments[rows[k]]
        for m in range(count[i]):
            s = m / (count[i] - 1)
            u = s * za / (zb * (1.0 - s) + s * za)
            t = t0 + u * (t1 - t0)
            owner[j], tt[j] = i, t
            for d in range(3):
                points[j, d] = world[d] + t * (world[3 + d] - world[d])
            j += 1
    return kept[:n].copy(), count[:n].copy(), owner, tt, points


@numba.njit(cache=True, nogil=True)
def _rays_to(
    points: np.ndarray, centre: np.ndarray, origin: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns ((S, 6) float32 rays: ``centre - origin``, then ``points - centre``; (S,) each point's
    distance from the centre, as ``np.linalg.norm`` gives it)."""
    rays = np.empty((len(points), 6), np.float32)
    dist = np.empty(len(points))
    for i in range(len(points)):
        dx, dy, dz = points[i, 0] - centre[0], points[i, 1] - centre[1], points[i, 2] - centre[2]
        rays[i, 0], rays[i, 1], rays[i, 2] = (
            centre[0] - origin[0],
            centre[1] - origin[1],
            centre[2] - origin[2],
        )
        rays[i, 3], rays[i, 4], rays[i, 5] = dx, dy, dz
        dist[i] = np.sqrt(dx * dx + dy * dy + dz * dz)
    return rays, dist


@numba.njit(cache=True, nogil=True)
def _not_behind(
    hit: np.ndarray, dist: np.ndarray, tolerance_m: float, tolerance_fraction: float
) -> np.ndarray:  # pragma: no cover - numba
    """Returns (S,) bool: no surface hit (at ``hit``, in units of the ray) nearer than each sample (at 1,
    ``dist`` metres away) by more than ``tolerance_m`` + ``tolerance_fraction`` of its distance."""
    out = np.empty(len(hit), np.bool_)
    for i in range(len(hit)):
        tol = tolerance_m + tolerance_fraction * dist[i]
        out[i] = hit[i] >= 1.0 - tol / max(dist[i], 1e-9)
    return out


@numba.njit(cache=True, nogil=True)
def _nan_max(x: float, y: float) -> float:  # pragma: no cover - numba
    """np.maximum of two floats: NaN if either is."""
    if x != x or y != y:
        return np.nan
    return x if x >= y else y


@numba.njit(cache=True, nogil=True)
def _nan_min(x: float, y: float) -> float:  # pragma: no cover - numba
    """np.minimum of two floats: NaN if either is."""
    if x != x or y != y:
        return np.nan
    return x if x <= y else y


def _runs(
    segments: np.ndarray,
    rows: np.ndarray,
    owner: np.ndarray,
    tt: np.ndarray,
    seen: np.ndarray,
    count: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns the runs of >= 2 consecutive visible samples of each segment as (K, 6) sub-segments and their
    (K,) rows; samples (S,) of segment ``owner`` at parameter ``tt`` (sorted per segment)."""
    seen_i = seen.astype(np.int8)
    last = np.r_[owner[1:] != owner[:-1], True]
    starts = seen & np.r_[True, ~seen[:-1] | (owner[1:] != owner[:-1])]
    ends = seen & (last | np.r_[seen_i[1:] == 0, False])
    i0, i1 = np.flatnonzero(starts), np.flatnonzero(ends)
    long = i1 > i0
    i0, i1 = i0[long], i1[long]
    g = owner[i0]
    a, b = segments[g, :3], segments[g, 3:]
    out = np.concatenate([a + tt[i0, None] * (b - a), a + tt[i1, None] * (b - a)], axis=1)
    return out, rows[g].astype(np.int64)


def _quads(v: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Returns (Q, 4, 3) convex polygons (a triangle repeats its last vertex) of (T, 3, 3) triangle
    corners: pairs (2k, 2k + 1) sharing their first and third vertices (``surfaces.raster_mesh``) form
    one rectangle."""
    t = len(triangles)
    pair = np.zeros(t // 2, dtype=bool)
    if t >= 2:
        first, second = triangles[0 : t - t % 2 : 2], triangles[1 : t - t % 2 : 2]
        pair = (first[:, 0] == second[:, 0]) & (first[:, 2] == second[:, 1])
    polys = [np.concatenate([v[0 : 2 * len(pair) : 2][pair], v[1 : 2 * len(pair) : 2][pair][:, 2:3]], axis=1)]
    lone = np.ones(t, dtype=bool)
    lone[np.flatnonzero(pair) * 2] = False
    lone[np.flatnonzero(pair) * 2 + 1] = False
    polys.append(np.concatenate([v[lone], v[lone][:, 2:3]], axis=1))
    return np.concatenate(polys).reshape(-1, 4, 3)


@numba.njit(cache=True, nogil=True)
def _open_pieces(
    corners: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    polygons: np.ndarray,
    normals: np.ndarray,
    ends: np.ndarray,
    margin: float,
    tolerance_m: float,
    tolerance_fraction: float,
) -> np.ndarray:  # pragma: no cover - numba
    """Returns (N,) bool: the (N, 2, 3) pieces no single convex occluder (polygons (Q, 4, 3), unit normals
    (Q, 3)) hides from every point of the box [lo, hi] (its (8, 3) ``corners``).

    An occluder hides a piece when the box lies more than ``margin`` on one side of its plane, the piece
    behind it by more than the ray test's tolerance (``_unoccluded``: ``tolerance_m`` + ``tolerance_fraction``
    x the farthest the piece is from the box, at least ``margin``), and the 16 crossings of the plane by the
    lines from the box corners to the piece ends lie inside the polygon (the crossing of any line from the
    box to the piece then does: central projection keeps segments straight and the polygon is convex)."""
    n_pieces = len(ends)
    open_ = np.ones(n_pieces, np.bool_)
    side_box = np.empty(8)
    inward = np.empty((4, 3))
    edge_tol = np.empty(4)
    use = np.empty(4, np.bool_)
    for q in range(len(polygons)):
        poly, n = polygons[q], normals[q]
        above = below = True
        for c in range(8):
            side_box[c] = (
                (corners[c, 0] - poly[0, 0]) * n[0] + (corners[c, 1] - poly[0, 1]) * n[1]
                + (corners[c, 2] - poly[0, 2]) * n[2]
            )  # fmt: skip
            above &= side_box[c] > margin
            below &= side_box[c] < -margin
        if not (above or below):
            continue
        sign = 1.0 if side_box[0] > 0 else -1.0
        for k in range(4):  # inward edge normals of the (counter-clockwise about n) polygon
            e0 = poly[(k + 1) % 4, 0] - poly[k, 0]
            e1 = poly[(k + 1) % 4, 1] - poly[k, 1]
            e2 = poly[(k + 1) % 4, 2] - poly[k, 2]
            length2 = e0 * e0 + e1 * e1 + e2 * e2
            use[k] = length2 >= 1e-18  # a triangle's repeated vertex: no edge
            inward[k, 0] = n[1] * e2 - n[2] * e1
            inward[k, 1] = n[2] * e0 - n[0] * e2
            inward[k, 2] = n[0] * e1 - n[1] * e0
            edge_tol[k] = -1e-9 * np.sqrt(length2)
        floor = max(margin, tolerance_m)
        for i in range(n_pieces):
            if not open_[i]:
                continue
            s0 = sign * (
                (ends[i, 0, 0] - poly[0, 0]) * n[0]
                + (ends[i, 0, 1] - poly[0, 1]) * n[1]
                + (ends[i, 0, 2] - poly[0, 2]) * n[2]
            )
            s1 = sign * (
                (ends[i, 1, 0] - poly[0, 0]) * n[0]
                + (ends[i, 1, 1] - poly[0, 1]) * n[1]
                + (ends[i, 1, 2] - poly[0, 2]) * n[2]
            )
            if not (s0 < -floor and s1 < -floor):
                continue
            far = 0.0
            for j in range(2):
                d2 = 0.0
                for a in range(3):
                    r = max(abs(ends[i, j, a] - lo[a]), abs(ends[i, j, a] - hi[a]))
                    d2 += r * r
                far = max(far, np.sqrt(d2))
            behind = max(margin, tolerance_m + tolerance_fraction * far)
            if not (s0 < -behind and s1 < -behind):
                continue
            inside = True
            for j in range(2):
                se = s0 if j == 0 else s1
                for c in range(8):
                    if not inside:
                        break
                    sb = sign * side_box[c]
                    w = sb / (sb - se)
                    x0 = corners[c, 0] + w * (ends[i, j, 0] - corners[c, 0])
                    x1 = corners[c, 1] + w * (ends[i, j, 1] - corners[c, 1])
                    x2 = corners[c, 2] + w * (ends[i, j, 2] - corners[c, 2])
                    for k in range(4):
                        if use[k]:
                            dot = (
                                (x0 - poly[k, 0]) * inward[k, 0] + (x1 - poly[k, 1]) * inward[k, 1]
                                + (x2 - poly[k, 2]) * inward[k, 2]
                            )  # fmt: skip
                            if dot < edge_tol[k]:
                                inside = False
                                break
            if inside:
                open_[i] = False
    return open_
