"""Compatible 2D-3D pairs under a rotation, and the shared inlier test evaluated on them only.

With R fixed, a 2D segment i and a 3D segment j can correspond only if j's camera-frame direction lies on
i's interpretation plane (eq. "coplanar" for every point of the line). Directions come in groups: each 3D
parallel cluster is one group (its members share the cluster direction), each unclustered 3D segment is
a group of its own. A pair is a compatible (2D segment, group) "combo" times a member of the group.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .config import MatchConfig
from .directions import DirectionClusters
from .geometry import pixels_to_rays

_ANGLE_SAFETY = 1.5  # the bearing prefilter is widened by this (first-order tolerance, cluster spread)
_DIRECT_MAX_PAIRS = 20_000  # up to this many pairs, the inlier test's prefilter simply tries them all


@dataclass(frozen=True)
class Pairs:
    """Every 2D-3D pair whose 3D direction lies on the 2D interpretation plane under R (camera frame).

    i, j, group: (P,) int64 2D index, 3D index and direction group of each pair (group < num_clusters:
    that 3D cluster; otherwise an unclustered 3D segment). directions: (G, 3) camera-frame group directions.
    combo_i, combo_g: (C,) int64 the compatible (2D segment, group) combos the pairs expand;
    combo_normal: (C, 3) i's interpretation normal turned to contain the group direction;
    combo_bearing: (C, 3) the unit direction, orthogonal to the group direction, in which i's rays go;
    combo_turn: (C,) rad by which the bearing turns per pixel of sideways midpoint shift.
    members: (M,) int64 3D indices sorted by group, group g's at ``members[starts[g]:starts[g + 1]]``.
    Per segment: ends (M, 6) rotated 3D endpoints ``R P1, R P2``; point (M, 3) their midpoints;
    plane (N, 3) plain interpretation normals of the 2D segments. For few pairs, also per pair:
    plane_ij (P, 3) = plane[i] and plane_offset (P,) = plane[i] . point[j], else empty. frames: per
    3D cluster, what ``_near_pairs`` needs (``_cluster_frames``).
    """

    i: np.ndarray
    j: np.ndarray
    group: np.ndarray
    directions: np.ndarray
    num_clusters: int
    combo_i: np.ndarray
    combo_g: np.ndarray
    combo_normal: np.ndarray
    combo_bearing: np.ndarray
    combo_turn: np.ndarray
    members: np.ndarray
    starts: np.ndarray
    ends: np.ndarray
    point: np.ndarray
    plane: np.ndarray
    plane_ij: np.ndarray
    plane_offset: np.ndarray
    frames: tuple = ()

    def coplanarity(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((K, 3) normal n, (K,) offset n . R P_j) of pairs ``index``: eq. "coplanar" n . t = -offset."""
        combo = np.searchsorted(np.cumsum(self.counts()), index, side="right")
        normal = self.combo_normal[combo]
        return normal, np.einsum("pk,pk->p", normal, self.point[self.j[index]])

    def counts(self) -> np.ndarray:
        """Returns (C,) the number of pairs of each combo (its group's size)."""
        return self.starts[self.combo_g + 1] - self.starts[self.combo_g]


def compatible_pairs(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    clusters3d: DirectionClusters,
    tolerance_px: float,
) -> Pairs:
    """Returns the Pairs whose 3D direction (under R) lies on the 2D segment's interpretation plane.

    The test is in pixels so that short, noisy segments are judged fairly: the 2D segment's endpoints must
    lie within ``tolerance_px`` of the image line through its midpoint and the direction's vanishing point.
    Clustered 3D segments use their cluster's direction (less noisy than their own).
    """
    labels = np.asarray(clusters3d.labels, dtype=np.int64)
    if len(labels) != len(lines3d):
        labels = np.full(len(lines3d), -1, dtype=np.int64)
    K = len(clusters3d)
    loose = np.flatnonzero(labels < 0)
    own = lines3d[loose, 3:6] - lines3d[loose, 0:3]
    dirs = _unit(np.r_[np.asarray(clusters3d.directions, float).reshape(-1, 3), own] @ R.T)
    group_of_j = labels.copy()
    group_of_j[loose] = K + np.arange(len(loose))
    members = np.argsort(group_of_j, kind="stable")
    starts = np.searchsorted(group_of_j[members], np.arange(len(dirs) + 1))
    ci, cg = np.nonzero(_vanishing_compatible(lines2d, camera, dirs, tolerance_px))
    counts = starts[cg + 1] - starts[cg]
    # expand each compatible (i, group) into (i, j) for every member j of the group
    i, g = np.repeat(ci, counts), np.repeat(cg, counts)
    j = members[np.arange(len(i)) + np.repeat(starts[cg] - np.cumsum(counts) + counts, counts)]
    ends = (lines3d.reshape(-1, 3) @ R.T).reshape(-1, 6)
    mid = 0.5 * (lines2d[:, 0:2] + lines2d[:, 2:4])
    ray = pixels_to_rays(camera, mid)
    a = dirs[cg]
    normal = _unit(cross(ray[ci], a))
    bearing = cross(a, normal)  # = ray - (ray . a) a, normalised: towards i's rays
    # how far the bearing turns when the midpoint moves 1 px across the segment
    d = lines2d[ci, 2:4] - lines2d[ci, 0:2]
    across = np.c_[-d[:, 1], d[:, 0]] / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-300)[:, None]
    moved = pixels_to_rays(camera, mid[ci] + across)
    moved = _unit(moved - np.einsum("pk,pk->p", moved, a)[:, None] * a)
    turn = np.arccos(np.clip(np.einsum("pk,pk->p", moved, bearing), -1.0, 1.0))
    plane = _unit(cross(pixels_to_rays(camera, lines2d[:, 0:2]), pixels_to_rays(camera, lines2d[:, 2:4])))
    point = 0.5 * (ends[:, 0:3] + ends[:, 3:6])
    plane_ij, plane_offset = np.zeros((0, 3)), np.zeros(0)
    if len(i) <= _DIRECT_MAX_PAIRS:
        plane_ij = plane[i]
        plane_offset = np.einsum("pk,pk->p", plane_ij, point[j])
    frames = _cluster_frames(dirs, K, ci, cg, bearing, turn, members, starts)
    parts = (i, j, g, dirs, K, ci, cg, normal, bearing, turn, members, starts, ends, point, plane)
    return Pairs(*parts, plane_ij, plane_offset, frames)


def _cluster_frames(
    dirs: np.ndarray,
    num_clusters: int,
    ci: np.ndarray,
    cg: np.ndarray,
    bearing: np.ndarray,
    turn: np.ndarray,
    members: np.ndarray,
    starts: np.ndarray,
) -> tuple:
    """Returns per 3D cluster with compatible 2D segments ``(J, seen, psi, turn, e1, e2)``.

    J: its 3D members; seen: its 2D segments; psi: their bearing angles (rad) in the plane ``e1, e2``
    normal to the cluster direction, from the mean bearing ``e1`` (no wrap-around near 0); turn: their
    bearing turn per pixel.
    """
    frames = []
    for g in np.flatnonzero(np.bincount(cg, minlength=len(dirs))[:num_clusters]):
        sel = np.flatnonzero(cg == g)
        e1 = _unit(bearing[sel].sum(axis=0))
        e2 = cross(dirs[g][None, :], e1[None, :])[0]
        psi = np.arctan2(bearing[sel] @ e2, bearing[sel] @ e1)
        frames.append((members[starts[g] : starts[g + 1]], ci[sel], psi, turn[sel], e1, e2))
    return tuple(frames)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns (P, 3) row-wise cross products of (P, 3) arrays (np.cross is several times slower here)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _vanishing_compatible(
    lines2d: np.ndarray, camera: Camera, dirs: np.ndarray, tolerance_px: float
) -> np.ndarray:
    """Returns (N, G) bool: segment i points at the vanishing point of direction g within tolerance_px."""
    mid = 0.5 * (lines2d[:, 0:2] + lines2d[:, 2:4])
    vp = dirs @ camera.K.T  # (G, 3) homogeneous vanishing points (may be at infinity)
    # line through midpoint and vanishing point: l = mid x vp; endpoint distance |l . end| / |l_xy|
    lx = mid[:, 1:2] * vp[None, :, 2] - vp[None, :, 1]
    ly = vp[None, :, 0] - mid[:, 0:1] * vp[None, :, 2]
    lc = mid[:, 0:1] * vp[None, :, 1] - mid[:, 1:2] * vp[None, :, 0]
    num = np.abs(lx * lines2d[:, 0:1] + ly * lines2d[:, 1:2] + lc)
    den = np.hypot(lx, ly)
    return (num <= tolerance_px * den) & (den > 1e-9 * np.abs(lc).clip(1.0))


def pair_inliers(
    lines2d: np.ndarray, camera: Camera, pairs: Pairs, T: np.ndarray, match: MatchConfig
) -> np.ndarray:
    """Returns (H,) int64 inlier counts of translations T (H, 3): the shared test, on the pairs only.

    Counts 2D segments with at least one inlier pair (``pair_matches``): a fast lower bound of the
    number of ``match_segments`` rows.
    """
    h, i, _ = pair_matches(lines2d, camera, pairs, T, match)
    ok = np.zeros((len(T), len(lines2d)), dtype=bool)
    ok[h, i] = True
    return ok.sum(axis=1)


def pair_matches(
    lines2d: np.ndarray, camera: Camera, pairs: Pairs, T: np.ndarray, match: MatchConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (K,) int64 ``(h, i, j)``: the compatible pairs that pass the inlier test at translation T[h].

    Same test as ``matching.match_matrix`` (endpoint distance and overlap), evaluated on the few pairs
    that can pass: with few pairs, those whose 3D midpoint lies within ``distance_px * z / f`` of i's
    interpretation plane (both endpoints do, and the midpoint is their mean); with many, those whose line
    is seen near i's bearing (``_near_pairs``, sorted searches instead of all pairs).
    """
    if len(pairs.plane_offset) == len(pairs.i):
        res = pairs.plane_offset[None, :] + T @ pairs.plane_ij.T  # (H, P) midpoint off the plane (m)
        z = pairs.point[pairs.j, 2][None, :] + T[:, 2:3]
        h, p = np.nonzero(np.abs(res) <= (match.distance_px / max(camera.fx, camera.fy)) * z)
        i, j = pairs.i[p], pairs.j[p]
    else:
        h, i, j = _near_pairs(pairs, T, match.distance_px)
        x = pairs.point[j] + T[h]  # the same necessary plane test, on the near pairs only
        keep = (
            np.abs(np.einsum("pk,pk->p", pairs.plane[i], x))
            <= match.distance_px / max(camera.fx, camera.fy) * x[:, 2]
        )
        h, i, j = h[keep], i[keep], j[keep]
    t = T[h]
    seg = lines2d[i]
    d = seg[:, 2:4] - seg[:, 0:2]
    length = np.hypot(d[:, 0], d[:, 1])
    u = d / np.maximum(length, 1e-300)[:, None]
    close = np.ones(len(h), dtype=bool)
    along = []
    for x in (pairs.ends[j, 0:3] + t, pairs.ends[j, 3:6] + t):
        front = x[:, 2] >= match.min_depth_m
        zs = np.where(front, x[:, 2], 1.0)
        rel_x = camera.fx * x[:, 0] / zs + camera.cx - seg[:, 0]
        rel_y = camera.fy * x[:, 1] / zs + camera.cy - seg[:, 1]
        close &= front & (np.abs(u[:, 0] * rel_y - u[:, 1] * rel_x) <= match.distance_px)
        along.append(u[:, 0] * rel_x + u[:, 1] * rel_y)
    lo = np.maximum(np.minimum(along[0], along[1]), 0.0)
    hi = np.minimum(np.maximum(along[0], along[1]), length)
    keep = close & (hi - lo > match.min_overlap * length)
    return h[keep], i[keep], j[keep]


def _near_pairs(pairs: Pairs, T: np.ndarray, distance_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (K,) int64 ``(h, i, j)``: per translation, the pairs whose 3D line is near i's bearing.

    Seen along a group direction ``a``, a 3D line of the group is a point and 2D segment i a half-line
    from the camera with bearing ``combo_bearing``. An inlier's line lies within ``turn * distance_px``
    of that bearing (its image passes within distance_px of i's midpoint: the overlap covers it), so per
    group the line angles are sorted once per translation and each segment looks up its window.
    """
    out = [_near_loose(pairs, T, distance_px)]
    rows = 8.0 * np.arange(len(T))[:, None]  # angle rows apart by 8 > 2 pi: one sorted search for all T
    for J, seen, psi, turn, e1, e2 in pairs.frames:
        x = pairs.point[J][None, :, :] + T[:, None, :]  # (H, m, 3)
        phi = np.arctan2(x @ e2, x @ e1) + rows
        order = np.argsort(phi, axis=None)
        key = phi.ravel()[order]
        q = psi[None, :] + rows  # (H, n)
        tol = _ANGLE_SAFETY * distance_px * turn
        lo = np.searchsorted(key, (q - tol).ravel())
        hi = np.searchsorted(key, (q + tol).ravel())
        n = hi - lo
        flat = order[np.repeat(lo - np.cumsum(n) + n, n) + np.arange(n.sum())]
        out.append((flat // len(J), np.repeat(np.tile(seen, len(T)), n), J[flat % len(J)]))
    h, i, j = (np.concatenate(parts) for parts in zip(*out, strict=True))
    return h, i, j


def _near_loose(pairs: Pairs, T: np.ndarray, distance_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns ``_near_pairs`` for the unclustered 3D segments (one pair per combo), tested directly."""
    sel = np.flatnonzero(pairs.combo_g >= pairs.num_clusters)
    j = pairs.members[pairs.starts[pairs.combo_g[sel]]]
    bearing = pairs.combo_bearing[sel]
    side = cross(pairs.directions[pairs.combo_g[sel]], bearing)
    x = pairs.point[j][None, :, :] + T[:, None, :]  # (H, c, 3)
    phi = np.arctan2(np.einsum("hck,ck->hc", x, side), np.einsum("hck,ck->hc", x, bearing))
    h, c = np.nonzero(np.abs(phi) <= _ANGLE_SAFETY * distance_px * pairs.combo_turn[sel])
    return h, pairs.combo_i[sel][c], j[c]
