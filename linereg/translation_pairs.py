"""Compatible 2D-3D pairs under a rotation (paper section III-C, eq. "coplanar").

With R fixed, a 2D segment i and a 3D segment j can correspond only if j's camera-frame direction lies on
i's interpretation plane (eq. "coplanar" for every point of the line). Directions come in groups: each 3D
parallel cluster is one group (its members share the cluster direction), each unclustered 3D segment is
a group of its own. A pair is a compatible (2D segment, group) "combo" times a member of the group; the
pairs are expanded only where they are needed (a large map has ~10^5 of them, a search reads a budget).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .camera import Camera
from .directions import DirectionClusters
from .geometry import pixels_to_rays

_DIRECT_MAX_PAIRS = 20_000  # up to this many pairs, the inlier test's prefilter simply tries them all


@dataclass(frozen=True)
class Pairs:
    """Every 2D-3D pair whose 3D direction lies on the 2D interpretation plane under R (camera frame).

    directions: (G, 3) camera-frame group directions (group < num_clusters: that 3D cluster; otherwise an
    unclustered 3D segment). combo_i, combo_g: (C,) int64 the compatible (2D segment, group) combos the
    pairs expand; combo_normal: (C, 3) i's interpretation normal turned to contain the group direction;
    combo_bearing: (C, 3) the unit direction, orthogonal to the group direction, in which i's rays go;
    combo_turn: (C,) rad by which the bearing turns per pixel of sideways midpoint shift.
    members: (M,) int64 3D indices sorted by group, group g's at ``members[starts[g]:starts[g + 1]]``.
    Per segment: ends (M, 6) rotated 3D endpoints ``R P1, R P2``; point (M, 3) their midpoints;
    plane (N, 3) plain interpretation normals of the 2D segments. frames: per 3D cluster, what
    ``translation_inliers`` needs (``_cluster_frames``). direct: few pairs, the inlier test tries them all.
    The pairs themselves (``i``, ``j``, ``group``: (P,) int64) are expanded on first use, combo by combo.
    """

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
    frames: tuple = ()
    direct: bool = True

    def counts(self) -> np.ndarray:
        """Returns (C,) the number of pairs of each combo (its group's size)."""
        return self.starts[self.combo_g + 1] - self.starts[self.combo_g]

    @cached_property
    def size(self) -> int:
        """Returns the number of pairs P."""
        return int(self.counts().sum())

    def expand(self, combos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((K,) combo, (K,) j) int64: every pair of the given combos (ascending), in pair order."""
        g = self.combo_g[combos]
        n = self.starts[g + 1] - self.starts[g]
        first = np.repeat(self.starts[g] - np.cumsum(n) + n, n)
        return np.repeat(combos, n), self.members[first + np.arange(len(first))]

    @cached_property
    def _pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        combo, j = self.expand(np.arange(len(self.combo_i)))
        return self.combo_i[combo], j, self.combo_g[combo]

    @property
    def i(self) -> np.ndarray:
        return self._pairs[0]

    @property
    def j(self) -> np.ndarray:
        return self._pairs[1]

    @property
    def group(self) -> np.ndarray:
        return self._pairs[2]

    @cached_property
    def direct_plane(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Returns per pair (P, 3) plane[i], (P,) plane[i] . point[j] and (P,) point[j] depth (m)."""
        plane_ij, point = take_rows(self.plane, self.i), take_rows(self.point, self.j)
        return plane_ij, np.einsum("pk,pk->p", plane_ij, point), point[:, 2]

    @cached_property
    def loose(self) -> tuple[np.ndarray, ...]:
        """Returns per combo with an unclustered 3D segment ``(i, j, turn, axes, offsets)``.

        axes: (3, 2c) float32 the turned normals (up to sign, direction x bearing), then the bearings;
        offsets: (2c,) float32 the segment midpoint's coordinates along them (a translation T adds T @ axes).
        Single precision: they only serve a prefilter whose tolerance is ~10^4 times its rounding.
        """
        sel = np.flatnonzero(self.combo_g >= self.num_clusters)
        j = self.members[self.starts[self.combo_g[sel]]]
        # (3, c) coordinate rows (the combo frames are stored so: contiguous takes)
        side, bearing = np.take(self.combo_normal.T, sel, axis=1), np.take(self.combo_bearing.T, sel, axis=1)
        p = np.take(self.point.T, j, axis=1)
        axes = np.concatenate([side, bearing], axis=1).astype(np.float32)
        offsets = np.r_[dot(p.T, side.T), dot(p.T, bearing.T)].astype(np.float32)
        return self.combo_i[sel], j, self.combo_turn[sel], axes, offsets

    def coplanarity(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((K, 3) normal n, (K,) offset n . R P_j) of pairs ``index``: eq. "coplanar" n . t = -offset."""
        combo = np.searchsorted(np.cumsum(self.counts()), index, side="right")
        normal = self.combo_normal[combo]
        return normal, np.einsum("pk,pk->p", normal, self.point[self.j[index]])


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
    ends = (lines3d.reshape(-1, 3) @ R.T).reshape(-1, 6)
    normal, bearing, turn = _combo_frames(lines2d, camera, dirs, ci, cg)
    plane = _unit(cross(pixels_to_rays(camera, lines2d[:, 0:2]), pixels_to_rays(camera, lines2d[:, 2:4])))
    point = 0.5 * (ends[:, 0:3] + ends[:, 3:6])
    frames = _cluster_frames(dirs, K, ci, cg, bearing, turn, members, starts, point)
    parts = (dirs, K, ci, cg, normal, bearing, turn, members, starts, ends, point, plane, frames)
    direct = int((starts[cg + 1] - starts[cg]).sum()) <= _DIRECT_MAX_PAIRS
    return Pairs(*parts, direct=direct)


def _combo_frames(
    lines2d: np.ndarray, camera: Camera, dirs: np.ndarray, ci: np.ndarray, cg: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns per combo (C, 3) turned normal, (C, 3) bearing and (C,) bearing turn per pixel (see Pairs)."""
    mid = 0.5 * (lines2d[:, 0:2] + lines2d[:, 2:4])
    ray = pixels_to_rays(camera, mid)
    d = lines2d[:, 2:4] - lines2d[:, 0:2]
    across = np.c_[-d[:, 1], d[:, 0]] / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-300)[:, None]
    shifted = pixels_to_rays(camera, mid + across)  # the midpoint's ray, 1 px across the segment
    # (3, C) coordinate rows: every operation below runs on contiguous rows
    a = np.take(dirs.T, cg, axis=1)
    normal = _unit(cross(np.take(ray.T, ci, axis=1).T, a.T)).T
    bearing = cross(a.T, normal.T).T  # = ray - (ray . a) a, normalised: towards i's rays
    moved = np.take(shifted.T, ci, axis=1)
    moved = moved - (moved[0] * a[0] + moved[1] * a[1] + moved[2] * a[2]) * a
    moved = moved / np.maximum(
        np.sqrt(moved[0] * moved[0] + moved[1] * moved[1] + moved[2] * moved[2]), 1e-300
    )
    turn = np.arccos(
        np.clip(moved[0] * bearing[0] + moved[1] * bearing[1] + moved[2] * bearing[2], -1.0, 1.0)
    )
    return normal.T, bearing.T, turn


def _cluster_frames(
    dirs: np.ndarray,
    num_clusters: int,
    ci: np.ndarray,
    cg: np.ndarray,
    bearing: np.ndarray,
    turn: np.ndarray,
    members: np.ndarray,
    starts: np.ndarray,
    point: np.ndarray,
) -> tuple:
    """Returns per 3D cluster with compatible 2D segments ``(J, seen, psi, turn, e1, e2, x1, x2)``.

    J: its 3D members; seen: its 2D segments; psi: their bearing angles (rad) in the plane ``e1, e2``
    normal to the cluster direction, from the mean bearing ``e1`` (no wrap-around near 0); turn: their
    bearing turn per pixel; x1, x2: the members' midpoints along e1 and e2.
    """
    frames = []
    for g in np.flatnonzero(np.bincount(cg, minlength=len(dirs))[:num_clusters]):
        sel = np.flatnonzero(cg == g)
        e1 = _unit(bearing[sel].sum(axis=0))
        e2 = cross(dirs[g][None, :], e1[None, :])[0]
        psi = np.arctan2(bearing[sel] @ e2, bearing[sel] @ e1)
        J = members[starts[g] : starts[g + 1]]
        frames.append((J, ci[sel], psi, turn[sel], e1, e2, point[J] @ e1, point[J] @ e2))
    return tuple(frames)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns (P, 3) row-wise cross products of (P, 3) arrays (np.cross is several times slower here).

    The result has a's memory layout: transposed views of (3, P) arrays give a transposed (3, P) array.
    """
    shape = np.broadcast_shapes(a.shape, b.shape)
    out = (
        np.empty(shape[::-1]).T
        if a.ndim == 2 and a.flags.f_contiguous and not a.flags.c_contiguous
        else np.empty(shape)
    )
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns (P,) row-wise dot products of (P, 3) arrays."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def take_rows(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Returns a[index] for a 2D array a (np.take: several times faster than fancy indexing of rows)."""
    return np.take(a, index, axis=0)


def _unit(v: np.ndarray) -> np.ndarray:
    if v.ndim == 1:
        return _unit(v[None, :])[0]
    return v / np.maximum(np.sqrt(dot(v, v)), 1e-300)[:, None]  # keeps v's memory layout


def _vanishing_compatible(
    lines2d: np.ndarray, camera: Camera, dirs: np.ndarray, tolerance_px: float
) -> np.ndarray:
    """Returns (N, G) bool: segment i points at the vanishing point of direction g within tolerance_px."""
    mx, my = 0.5 * (lines2d[:, 0] + lines2d[:, 2]), 0.5 * (lines2d[:, 1] + lines2d[:, 3])
    vp = (dirs @ camera.K.T).T  # (3, G) homogeneous vanishing points (may be at infinity)
    # line through midpoint and vanishing point: l = mid x vp, linear in vp; endpoint distance |l . end| / |l_xy|
    zero, one = np.zeros_like(mx), np.ones_like(mx)
    lx = np.c_[zero, -one, my] @ vp
    ly = np.c_[one, zero, -mx] @ vp
    lc = np.c_[-my, mx, zero] @ vp
    x1, y1 = lines2d[:, 0:1], lines2d[:, 1:2]
    num = lx * x1
    num += ly * y1
    num += lc
    np.abs(num, out=num)
    den = np.hypot(lx, ly)
    np.abs(lc, out=lc)
    lc.clip(1.0, out=lc)
    lc *= 1e-9
    ok = num <= tolerance_px * den
    ok &= den > lc
    return ok
