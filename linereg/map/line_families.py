"""Dominant directions of boundary lines (part of ``lines3d.extract``): man-made boundaries come in a few
parallel families, whose long members fix the direction of the short ones.

Global families are found over the candidate lines of every region at once, so a small region (a window
pane) takes its directions from the facade around it; per-region families filter ragged boundaries.
"""

from __future__ import annotations

import numpy as np

from ..config import Lines3DConfig


def _undirected_angle(theta: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Returns |theta - ref| in [0, pi / 2] of undirected 2D line angles (radians), broadcast."""
    return np.abs((theta - ref + 0.5 * np.pi) % np.pi - 0.5 * np.pi)


def dominant_directions(segments: np.ndarray, config: Lines3DConfig) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((F, 3) unit directions, (F,) support: summed length) of the major families of (N, 6)
    segments.

    Greedy, longest first: a seed takes every free segment within snap_angle_deg; the family's direction is
    the principal axis of its members' directions weighted by length^2 (long lines are the exact ones).
    Families holding less than family_min_share of the best supported one are left out.
    """
    d = segments[:, 3:] - segments[:, :3]
    length = np.linalg.norm(d, axis=1)
    keep = length > 1e-9
    d, length = d[keep] / length[keep, None], length[keep]
    cos_thr = np.cos(np.radians(config.snap_angle_deg))
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
    # the rest are chance directions (raster diagonals, clutter): which of them exist is a matter of
    # rounding, and no line should take their direction
    major = np.array(support) >= config.family_min_share * max(support, default=0.0)
    return np.array(dirs).reshape(-1, 3)[major], np.array(support)[major]


def snap_to_families(
    lines: np.ndarray, basis: np.ndarray, families: tuple[np.ndarray, np.ndarray], config: Lines3DConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((k, 4) lines, (k,) bool snapped): (k, 4) 2D lines of a region with in-plane axes (2, 3)
    ``basis`` turned about their midpoints onto the best supported global family within snap_angle_deg
    (of those within family_in_plane_deg of the plane) that holds at least twice their length."""
    dirs, support = families
    max_angle_deg = config.snap_angle_deg
    if len(lines) == 0 or len(dirs) == 0 or max_angle_deg <= 0:
        return lines, np.zeros(len(lines), dtype=bool)
    flat = dirs @ basis.T  # (F, 2) in-plane components
    norm = np.linalg.norm(flat, axis=1)
    in_plane = norm >= np.cos(np.radians(config.family_in_plane_deg))
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


def has_parallel(lines: np.ndarray, size: float, config: Lines3DConfig) -> np.ndarray:
    """Returns (k,) bool: lines of one region that follow one of its dominant directions, i.e. whose
    direction (within snap_angle_deg) other lines share with at least their own length and with
    dominant_share of the region's whole line length, or that are long (lone_fraction of the region's
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
    diff = _undirected_angle(theta[:, None], theta[None, :])
    family = (diff <= np.radians(max(config.snap_angle_deg, 1.0))) @ length  # includes the line itself
    dominant = (family >= 2.0 * length) & (family >= config.dominant_share * length.sum())
    return dominant | (length >= config.lone_fraction * size)


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
        diff = _undirected_angle(theta, theta[seed])
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


def box_lines(
    outlines: list[np.ndarray],
    basis: np.ndarray,
    families: tuple[np.ndarray, np.ndarray],
    config: Lines3DConfig,
    min_fill: float | None = None,
) -> np.ndarray:
    """Returns (4 B, 4) 2D sides of the rectangles round each of B (n, 2) in-plane point sets (a region's
    contours, outer and hole) whose sides follow the region's best supported in-plane family (plane axes
    (2, 3) ``basis``) and the perpendicular to it.

    A small region (a window pane, a ledge strip) or hole (a window) spans a few raster cells only, too
    few for its contour's runs to give its sides; man-made outlines are often rectangles, and a side the
    points do not follow is dropped by the edge refinement. Closed outlines filling less than min_fill
    (default: rectangle_min_fill) of their rectangle are no rectangles (a circle, a ragged shadow) and
    give none; 0 takes every point set.
    """
    min_fill = config.rectangle_min_fill if min_fill is None else min_fill
    dirs, support = families
    flat = dirs @ basis.T
    in_plane = np.linalg.norm(flat, axis=1) >= np.cos(np.radians(config.family_in_plane_deg))
    if not outlines or not in_plane.any():
        return np.zeros((0, 4))
    best = np.flatnonzero(in_plane)[np.argmax(support[in_plane])]
    d1 = flat[best] / np.linalg.norm(flat[best])
    d2 = np.array([-d1[1], d1[0]])
    out = []
    for xy in outlines:
        s, t = xy @ d1, xy @ d2
        if min_fill > 0 and _area(xy) < min_fill * np.ptp(s) * np.ptp(t):
            continue
        corners = np.outer([s.min(), s.max(), s.max(), s.min()], d1)
        corners += np.outer([t.min(), t.min(), t.max(), t.max()], d2)
        out.append(np.concatenate([corners, np.roll(corners, -1, axis=0)], axis=1))
    return np.concatenate([np.zeros((0, 4)), *out])


def _area(xy: np.ndarray) -> float:
    """Returns the area enclosed by the (n, 2) closed polygon (shoelace formula)."""
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))
