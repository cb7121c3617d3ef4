"""The shared inlier test (``matching``) evaluated on the compatible pairs only, for many translations.

Paper section III-C: a 3D segment is an inlier of a 2D segment when both projected endpoints lie within
``distance_px`` of the 2D segment's line and the projection overlaps more than half of it. Here the test
runs only on compatible pairs (``translation_pairs``) that can pass, found by a necessary prefilter.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .config import MatchConfig
from .translation_pairs import Pairs, take_rows

_ANGLE_SAFETY = 1.5  # the bearing prefilter is widened by this (first-order tolerance, cluster spread)


def pair_inliers(
    lines2d: np.ndarray, camera: Camera, pairs: Pairs, T: np.ndarray, match: MatchConfig
) -> np.ndarray:
    """Returns (H,) int64 inlier counts of translations T (H, 3): the shared test, on the pairs only.

    Counts 2D segments with at least one inlier pair (``pair_matches``): a fast lower bound of the
    number of ``match_segments`` rows.
    """
    h, i, _ = pair_matches(lines2d, camera, pairs, T, match)
    return count_inliers(h, i, len(T), len(lines2d))


def count_inliers(h: np.ndarray, i: np.ndarray, num_t: int, num_2d: int) -> np.ndarray:
    """Returns (num_t,) int64 how many distinct 2D segments i each translation h matched."""
    ok = np.zeros((num_t, num_2d), dtype=bool)
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
    slack = match.distance_px / max(camera.fx, camera.fy)
    if pairs.direct:
        plane_ij, offset, depth = pairs.direct_plane
        res = offset[None, :] + T @ plane_ij.T  # (H, P) midpoint off the plane (m)
        h, p = np.nonzero(np.abs(res) <= slack * (depth[None, :] + T[:, 2:3]))
        i, j = pairs.i[p], pairs.j[p]
    else:
        h, i, j = _near_pairs(pairs, T, match.distance_px)
        x = take_rows(pairs.point, j) + take_rows(
            T, h
        )  # the same necessary plane test, on the near pairs only
        keep = np.abs(np.einsum("pk,pk->p", take_rows(pairs.plane, i), x)) <= slack * x[:, 2]
        k = np.flatnonzero(keep)
        h, i, j = h.take(k), i.take(k), j.take(k)
    keep = _passes(lines2d, camera, take_rows(pairs.ends, j) + np.tile(take_rows(T, h), 2), i, match)
    k = np.flatnonzero(keep)
    return h.take(k), i.take(k), j.take(k)


def _passes(
    lines2d: np.ndarray, camera: Camera, ends: np.ndarray, i: np.ndarray, match: MatchConfig
) -> np.ndarray:
    """Returns (K,) bool: camera-frame 3D segments ends (K, 6) pass the inlier test of 2D segments i (K,)."""
    d = lines2d[:, 2:4] - lines2d[:, 0:2]
    length = np.hypot(d[:, 0], d[:, 1])
    u = d / np.maximum(length, 1e-300)[:, None]
    ux, uy, length = u[:, 0].take(i), u[:, 1].take(i), length.take(i)
    x0, y0 = lines2d[:, 0].take(i), lines2d[:, 1].take(i)
    close = np.ones(len(i), dtype=bool)
    along = []
    for x in (ends[:, 0:3], ends[:, 3:6]):
        front = x[:, 2] >= match.min_depth_m
        zs = np.where(front, x[:, 2], 1.0)
        rel_x = camera.fx * x[:, 0] / zs + camera.cx - x0
        rel_y = camera.fy * x[:, 1] / zs + camera.cy - y0
        close &= front & (np.abs(ux * rel_y - uy * rel_x) <= match.distance_px)
        along.append(ux * rel_x + uy * rel_y)
    lo = np.maximum(np.minimum(along[0], along[1]), 0.0)
    hi = np.minimum(np.maximum(along[0], along[1]), length)
    return close & (hi - lo > match.min_overlap * length)


def _near_pairs(pairs: Pairs, T: np.ndarray, distance_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (K,) int64 ``(h, i, j)``: per translation, the pairs whose 3D line is near i's bearing.

    Seen along a group direction ``a``, a 3D line of the group is a point and 2D segment i a half-line
    from the camera with bearing ``combo_bearing``. An inlier's line lies within ``turn * distance_px``
    of that bearing (its image passes within distance_px of i's midpoint: the overlap covers it), so per
    group the line angles are sorted once per translation and each segment looks up its window.
    """
    out = [_near_loose(pairs, T, distance_px)]
    rows = 8.0 * np.arange(len(T))[:, None]  # angle rows apart by 8 > 2 pi: one sorted search for all T
    for J, seen, psi, turn, e1, e2, x1, x2 in pairs.frames:
        phi = np.arctan2(x2[None, :] + (T @ e2)[:, None], x1[None, :] + (T @ e1)[:, None]) + rows  # (H, m)
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
    """Returns ``_near_pairs`` for the unclustered 3D segments (one pair per combo), tested directly.

    The line's angle from the bearing, ``atan2(x . side, x . bearing)``, is within tol exactly when it lies
    in front (``x . bearing > 0``) and ``|x . side| <= tan(tol) x . bearing`` (tol < pi / 2).
    """
    i, j, turn, axes, offsets = pairs.loose
    tol = _ANGLE_SAFETY * distance_px * turn
    sb = T.astype(np.float32) @ axes  # (H, 2c), in place from here: the largest arrays of the search
    sb += offsets[None, :]
    s, b = sb[:, : len(i)], sb[:, len(i) :]
    np.abs(s, out=s)
    wide = np.flatnonzero(tol >= 1.5)  # a huge tolerance (a tiny focal length): the angle itself
    wide_ok = np.arctan2(s[:, wide], b[:, wide]) <= tol[wide]
    ok = b > 0
    b *= np.tan(np.minimum(tol, 1.5)).astype(np.float32)[None, :]
    ok &= s <= b
    ok[:, wide] = wide_ok
    h, c = np.nonzero(ok)
    return h, i[c], j[c]
