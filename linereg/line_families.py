"""Dominant directions of boundary lines (part of ``lines3d.extract``): man-made boundaries come in a few
parallel families, whose long members fix the direction of the short ones.

Global families are found over the candidate lines of every region at once, so a small region (a window
pane) takes its directions from the facade around it; per-region families filter ragged boundaries.
"""

from __future__ import annotations

import numpy as np

_LONE_FRACTION = 0.25  # a line off its region's dominant directions is kept if this long (of its size)
_DOMINANT_SHARE = 0.15  # a dominant direction holds this share of a region's line length
_IN_PLANE_DEG = 3.0  # a global direction this close to a region's plane is one of its directions


def _undirected_angle(theta: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Returns |theta - ref| in [0, pi / 2] of undirected 2D line angles (radians), broadcast."""
    return np.abs((theta - ref + 0.5 * np.pi) % np.pi - 0.5 * np.pi)


def dominant_directions(segments: np.ndarray, max_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((F, 3) unit directions, (F,) support: summed length) of the families of (N, 6) segments.

    Greedy, longest first: a seed takes every free segment within max_angle_deg; the family's direction is
    the principal axis of its members' directions weighted by length^2 (long lines are the exact ones).
    """
    d = segments[:, 3:] - segments[:, :3]
    length = np.linalg.norm(d, axis=1)
    keep = length > 1e-9
    d, length = d[keep] / length[keep, None], length[keep]
    cos_thr = np.cos(np.radians(max_angle_deg))
    free = np.ones(len(d), dtype=bool)
    dirs, support = [], []
    for seed in np.argsort(-length, kind="stable"):
        if not free[seed]:
            continue
        members = np.flatnonzero(free & (np.abs(d @ d[seed]) >= cos_thr))
        free[members] = False
        w = length[members] ** 2
        scatter = (d[members] * w[:, None]).T @ d[members]
        dirs.append(np.linalg.eigh(scatter)[1][:, -1])
        support.append(length[members].sum())
    return np.array(dirs).reshape(-1, 3), np.array(support)


def snap_to_families(
    lines: np.ndarray, basis: np.ndarray, families: tuple[np.ndarray, np.ndarray], max_angle_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((k, 4) lines, (k,) bool snapped): (k, 4) 2D lines of a region with in-plane axes (2, 3)
    ``basis`` turned about their midpoints onto the best supported global family within max_angle_deg
    that holds at least twice their length."""
    dirs, support = families
    if len(lines) == 0 or len(dirs) == 0 or max_angle_deg <= 0:
        return lines, np.zeros(len(lines), dtype=bool)
    flat = dirs @ basis.T  # (F, 2) in-plane components
    norm = np.linalg.norm(flat, axis=1)
    in_plane = norm >= np.cos(np.radians(_IN_PLANE_DEG))
    phi = np.arctan2(flat[in_plane, 1], flat[in_plane, 0])
    d = lines[:, 2:] - lines[:, :2]
    length = np.linalg.norm(d, axis=1)
    theta = np.arctan2(d[:, 1], d[:, 0])
    near = _undirected_angle(theta[:, None], phi[None, :]) <= np.radians(max_angle_deg)
    near &= support[in_plane][None, :] >= 2.0 * length[:, None]
    score = np.where(near, support[in_plane][None, :], -1.0)
    best = np.argmax(score, axis=1) if len(phi) else np.zeros(len(lines), dtype=np.int64)
    snapped = near.any(axis=1)
    direction = np.stack([np.cos(phi[best]), np.sin(phi[best])], axis=1) if len(phi) else d
    return _turn(lines, direction, snapped), snapped


def _turn(lines: np.ndarray, direction: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Returns (k, 4) lines, those marked ``which`` turned about their midpoints onto (k, 2) directions."""
    out = lines.copy()
    d = lines[which, 2:] - lines[which, :2]
    u = direction[which] * np.sign(np.einsum("kj,kj->k", d, direction[which]))[:, None]
    half = 0.5 * np.linalg.norm(d, axis=1)[:, None] * u
    mid = 0.5 * (lines[which, :2] + lines[which, 2:])
    out[which] = np.concatenate([mid - half, mid + half], axis=1)
    return out


def has_parallel(lines: np.ndarray, size: float, snap_angle_deg: float) -> np.ndarray:
    """Returns (k,) bool: lines of one region that follow one of its dominant directions, i.e. whose
    direction (within snap_angle_deg) other lines share with at least their own length and with
    _DOMINANT_SHARE of the region's whole line length, or that are long (_LONE_FRACTION of the region's
    ``size``, its longer side).

    Man-made boundaries come in a few parallel families (both sides of a window, ledge, facade), while a
    ragged boundary (clutter, a scanner's occlusion shadow, the edge of its sampling pattern on the
    ground) is cut into chords in every direction, each family holding a small share.
    """
    if len(lines) == 0:
        return np.zeros(0, dtype=bool)
    d = lines[:, 2:] - lines[:, :2]
    length = np.linalg.norm(d, axis=1)
    theta = np.arctan2(d[:, 1], d[:, 0])
    diff = np.abs((theta[:, None] - theta[None, :] + 0.5 * np.pi) % np.pi - 0.5 * np.pi)
    family = (diff <= np.radians(max(snap_angle_deg, 1.0))) @ length  # includes the line itself
    dominant = (family >= 2.0 * length) & (family >= _DOMINANT_SHARE * length.sum())
    return dominant | (length >= _LONE_FRACTION * size)


def snap_directions(lines: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """Returns (k, 4) 2D lines of one region turned about their midpoints onto the region's dominant
    directions: lines within max_angle_deg of the longest free line share its direction, averaged with
    weights length^2 (a facade's long outline fixes the direction of its short window edges)."""
    if max_angle_deg <= 0 or len(lines) < 2:
        return lines
    d = lines[:, 2:] - lines[:, :2]
    length = np.linalg.norm(d, axis=1)
    theta = np.arctan2(d[:, 1], d[:, 0])
    free = np.ones(len(lines), dtype=bool)
    out = lines.copy()
    for seed in np.argsort(-length, kind="stable"):
        if not free[seed]:
            continue
        diff = np.abs((theta - theta[seed] + 0.5 * np.pi) % np.pi - 0.5 * np.pi)  # undirected angle
        members = np.flatnonzero(free & (diff <= np.radians(max_angle_deg)))
        free[members] = False
        # mean of undirected angles: average the doubled angles
        w = length[members] ** 2
        mean = 0.5 * np.arctan2(
            (w * np.sin(2 * theta[members])).sum(), (w * np.cos(2 * theta[members])).sum()
        )
        direction = np.array([np.cos(mean), np.sin(mean)])
        sign = np.sign(d[members] @ direction)[:, None]
        mid = 0.5 * (lines[members, :2] + lines[members, 2:])
        half = 0.5 * length[members, None] * sign * direction
        out[members] = np.concatenate([mid - half, mid + half], axis=1)
    return out


def box_lines(uv: np.ndarray, basis: np.ndarray, families: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Returns (4, 4) or (0, 4) 2D sides of the rectangle round a region's (n, 2) points whose sides follow
    its best supported in-plane family (plane axes (2, 3) ``basis``) and the perpendicular to it.

    A small region (a window pane) spans a few raster cells only, too few for its contour's runs to give
    its sides; man-made regions are often rectangles, and a side the points do not follow is dropped by
    the edge refinement.
    """
    dirs, support = families
    flat = dirs @ basis.T
    in_plane = np.linalg.norm(flat, axis=1) >= np.cos(np.radians(_IN_PLANE_DEG))
    if len(uv) < 3 or not in_plane.any():
        return np.zeros((0, 4))
    best = np.flatnonzero(in_plane)[np.argmax(support[in_plane])]
    d1 = flat[best] / np.linalg.norm(flat[best])
    d2 = np.array([-d1[1], d1[0]])
    s, t = uv @ d1, uv @ d2
    (s0, s1), (t0, t1) = np.percentile(s, [0.2, 99.8]), np.percentile(t, [0.2, 99.8])
    corners = np.outer([s0, s1, s1, s0], d1) + np.outer([t0, t0, t1, t1], d2)
    return np.concatenate([corners, np.roll(corners, -1, axis=0)], axis=1)
