"""Boundary lines of a planar region moved from its raster (cell-quantised) to where its points end (part of
``lines3d.extract``).

All lines of a region are refined at once: their point neighbourhoods come from one batched KD-tree
query, and the per-bin edge estimates and per-line fits are grouped sums over flat arrays.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from ..config import Lines3DConfig


def refine_edges(
    uv: np.ndarray,
    lines: np.ndarray,
    band: float,
    config: Lines3DConfig,
    beside: np.ndarray | None = None,
    fixed: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((k, 4) boundary lines moved from the raster (cell-quantised) to where the points end,
    (k,) bool which of them are kept).

    Along the line, bins of ``band`` length: the outermost of n points spread uniformly over
    [-band, e] lies on average (e + band) / (n + 1) inside the edge e, so e = o_max + (o_max + band) / n
    per bin, but not beyond the first point off the region there; a weighted least-squares line through
    the bins' e gives offset and angle. Lines this would tilt by more than edge_max_tilt_deg, or with most
    bins off the fitted edge, are dropped (the ``edge_*`` fields of ``config``).
    uv: (n, 2) region points in plane coordinates; lines: (k, 4); beside: (q, 3) u, v, signed distance
    from the plane of points of no region near it, or None; fixed: (k,) bool lines whose direction is
    known (a dominant direction): only their offset is fitted.
    """
    if len(lines) == 0:
        return lines, np.zeros(0, dtype=bool)
    a, b = lines[:, :2], lines[:, 2:]
    length = np.linalg.norm(b - a, axis=1)
    d = (b - a) / length[:, None]
    m = np.stack([-d[:, 1], d[:, 0]], axis=1)
    line, point = _near_pairs(cKDTree(uv), a, d, length, band)
    rel = uv[point] - a[line]
    t, s = np.einsum("pk,pk->p", rel, d[line]), np.einsum("pk,pk->p", rel, m[line])
    keep = (np.abs(s) <= band) & (t >= 0.5 * band) & (t <= length[line] - 0.5 * band)
    line, t, s = line[keep], t[keep], s[keep]
    k = len(lines)
    count = np.bincount(line, minlength=k)
    t_lo, t_hi = _group_min(t, line, k), -_group_min(-t, line, k)
    # no points along most of it: the raster's closing bridged a gap, no boundary of the surface
    ok = (count >= config.edge_min_line_points) & (t_hi - t_lo >= 0.5 * (length - band))
    outward = -np.sign(np.bincount(line, s, k))  # the points lie on the inner side
    fixed = np.zeros(k, dtype=bool) if fixed is None else fixed
    geometry = (a, d, m * outward[:, None], length)
    pairs = _beside_pairs(beside, geometry, band)
    on_plane = np.abs(pairs[:, 3]) < config.edge_on_plane_m
    off = pairs[~on_plane]
    o = outward[line] * s
    # the free fit tells whether a straight edge lies behind the line (a ragged outline's chords snap
    # onto a family direction too); lines too short for it (one bin) may still take a known direction
    slope, intercept, on_line = _edge_lines(line, t, o, t_lo, band, np.zeros(k, dtype=bool), off, config)
    ends = np.clip(intercept[:, None] + slope[:, None] * np.stack([np.zeros(k), length], 1), -band, band)
    straight = (on_line >= 0.5 * (length - band) / band) & (
        np.abs(ends[:, 1] - ends[:, 0]) <= length * np.tan(np.radians(config.edge_max_tilt_deg))
    )
    _, intercept0, on_line0 = _edge_lines(line, t, o, t_lo, band, fixed, off, config)
    short = fixed & ~np.isfinite(slope) & (on_line0 >= 1)
    ok &= straight | short
    ends[fixed] = np.clip(intercept0[fixed, None], -band, band)
    # points of no region in the plane beyond the edge: the surface goes on, only its labels stop (region
    # growing leaves out the points round a crease, for one)
    on = pairs[on_plane]
    beyond = on[:, 2] > np.nan_to_num(ends[on[:, 0].astype(np.int64)].max(axis=1), nan=band)
    ok &= np.bincount(on[beyond, 0].astype(np.int64), minlength=k) < config.edge_max_going_on * count
    shift = (outward[:, None, None] * ends[..., None]) * m[:, None, :]
    return np.concatenate([a + shift[:, 0], b + shift[:, 1]], axis=1), ok


def _beside_pairs(beside: np.ndarray | None, geometry: tuple[np.ndarray, ...], band: float) -> np.ndarray:
    """Returns (q, 4) line, t, outward offset, depth of the (b, 3) ``beside`` points (u, v, signed plane
    distance) within a band of each line; geometry: (k, 2) starts, directions, outward normals, (k,)
    lengths."""
    a, d, out, length = geometry
    if beside is None or len(beside) == 0:
        return np.zeros((0, 4))
    line, point = _near_pairs(cKDTree(beside[:, :2]), a, d, length, band)
    rel = beside[point, :2] - a[line]
    t, o = np.einsum("pk,pk->p", rel, d[line]), np.einsum("pk,pk->p", rel, out[line])
    keep = (t >= 0) & (t <= length[line]) & (np.abs(o) <= band) & np.isfinite(o)
    return np.stack([line, t, o, beside[point, 2]], axis=1)[keep]


def _near_pairs(
    tree: cKDTree, a: np.ndarray, d: np.ndarray, length: np.ndarray, band: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((q,) line, (q,) point) distinct pairs of tree points near each line: all within band of it
    along its length, and a few more (within hypot(band, band / 2) of samples taken every band)."""
    count = np.ceil((length + band) / band).astype(np.int64)
    line = np.repeat(np.arange(len(a)), count)
    step = np.arange(len(line)) - np.repeat(np.cumsum(count) - count, count)
    radius = float(np.hypot(band, 0.5 * band))
    found = tree.query_ball_point(a[line] + (step * band)[:, None] * d[line], radius, return_sorted=False)
    sizes = np.fromiter(map(len, found), np.int64, len(found))
    point = np.fromiter(itertools.chain.from_iterable(found), np.int64, int(sizes.sum()))
    line, step = np.repeat(line, sizes), np.repeat(step, sizes)
    # a point is found by neighbouring samples too: it belongs to the one whose stretch holds it
    t = np.einsum("pk,pk->p", tree.data[point] - a[line], d[line])
    mine = np.clip(np.floor(t / band + 0.5), 0, count[line] - 1) == step
    return line[mine], point[mine]


def _group_min(values: np.ndarray, group: np.ndarray, num: int) -> np.ndarray:
    """Returns (num,) the minimum of values per group (inf for empty groups)."""
    out = np.full(num, np.inf)
    np.minimum.at(out, group, values)
    return out


def _edge_lines(
    line: np.ndarray,
    t: np.ndarray,
    o: np.ndarray,
    t_lo: np.ndarray,
    band: float,
    fixed: np.ndarray,
    off: np.ndarray,
    config: Lines3DConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (k,) slope, intercept (NaN: no fit) and bins on it of the edge e(t) behind each line's
    points at (t, outward offset o); bins on it are the band-long stretches whose edge estimate lies
    within band / 2 of the line. Bins whose estimate is off by more than 2.5 median residuals (a bin
    reaching into a neighbouring structure) are left out of a second fit. ``fixed`` lines get slope 0."""
    k = len(fixed)
    bins = np.floor((t - t_lo[line]) / band).astype(np.int64)
    num_bins = bins.max(initial=0) + 1
    key, inverse = np.unique(line * num_bins + bins, return_inverse=True)
    inverse = inverse.ravel()
    owner = line[np.unique(inverse, return_index=True)[1]]
    count = np.bincount(inverse)
    top = -_group_min(-o, inverse, len(key))
    centre = np.bincount(inverse, t) / count
    edge = top + (top + band) / count
    # a scanner samples in rows and columns: the last one lies on average half their spacing inside the
    # edge, the spacing being the gap down to the next line of points (typical over the line's bins)
    lower = o < top[inverse] - config.edge_row_step_m
    second = -_group_min(-o[lower], inverse[lower], len(key))
    has = np.isfinite(second)
    gap = _group_median((top - second)[has], owner[has], k)
    edge = np.fmax(edge, top + 0.5 * gap[owner])
    # a point off the region beyond its last one bounds the edge: the surface ends before the point (the
    # other surface is behind it, seen through the gap, or meets it there)
    first = _first_beyond(off, key, top, t_lo, num_bins, band)
    edge = np.minimum(edge, first)
    good = count >= config.edge_min_bin_points
    owner, centre, edge, weight = owner[good], centre[good], edge[good], count[good].astype(np.float64)
    slope, intercept = _weighted_fit(owner, centre, edge, weight, fixed)
    residual = np.abs(edge - (slope[owner] * centre + intercept[owner]))
    inlier = residual <= np.maximum(2.5 * _group_median(residual, owner, k)[owner], 1e-9)
    n_in, n_all = np.bincount(owner[inlier], minlength=k), np.bincount(owner, minlength=k)
    refit = (n_in >= 2) & (n_in < n_all)
    s2, i2 = _weighted_fit(owner[inlier], centre[inlier], edge[inlier], weight[inlier], fixed)
    slope, intercept = np.where(refit, s2, slope), np.where(refit, i2, intercept)
    on = np.abs(edge - (slope[owner] * centre + intercept[owner])) <= 0.5 * band
    slope[(n_all < 2) & ~fixed | (n_all < 1)] = np.nan
    return slope, intercept, np.bincount(owner[on], minlength=k)


def _first_beyond(
    off: np.ndarray, key: np.ndarray, top: np.ndarray, t_lo: np.ndarray, num_bins: int, band: float
) -> np.ndarray:
    """Returns (B,) per bin (sorted ``key`` = line * num_bins + bin) the smallest outward offset of the
    (q, 4) ``off`` points beyond the bin's outermost region point ``top`` by at most band (inf: none)."""
    first = np.full(len(key), np.inf)
    if len(off) == 0 or len(key) == 0:
        return first
    line = off[:, 0].astype(np.int64)
    bins = np.floor((off[:, 1] - t_lo[line]) / band)
    valid = np.isfinite(bins) & (bins >= 0) & (bins < num_bins)
    wanted = line[valid] * num_bins + bins[valid].astype(np.int64)
    idx = np.minimum(np.searchsorted(key, wanted), len(key) - 1)
    o = off[valid, 2]
    hit = (key[idx] == wanted) & (o > top[idx]) & (o <= top[idx] + band)
    np.minimum.at(first, idx[hit], o[hit])
    return first


def _weighted_fit(group: np.ndarray, x: np.ndarray, y: np.ndarray, w: np.ndarray, fixed: np.ndarray):
    """Returns (k,) slope, intercept of the weighted least-squares line y = slope x + intercept per group
    (weights w are those of the squared residuals; slope 0 for the (k,) ``fixed`` groups); NaN where a
    free group has fewer than 2 distinct x."""
    k = len(fixed)
    sw, sx, sy = (np.bincount(group, v, k) for v in (w, w * x, w * y))
    sxx, sxy = np.bincount(group, w * x * x, k), np.bincount(group, w * x * y, k)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my = sx / sw, sy / sw
        var = sxx / sw - mx * mx
        slope = (sxy / sw - mx * my) / var
        slope = np.where(var > 1e-12 * np.maximum(mx * mx, 1.0), slope, np.nan)
        slope[fixed] = 0.0
        return slope, my - slope * mx


def _group_median(values: np.ndarray, group: np.ndarray, k: int) -> np.ndarray:
    """Returns (k,) the median of values per group (NaN for empty groups)."""
    order = np.lexsort((values, group))
    v, g = values[order], group[order]
    count = np.bincount(g, minlength=k)
    start = np.cumsum(count) - count
    out = np.full(k, np.nan)
    has = count > 0
    lo = start[has] + (count[has] - 1) // 2
    hi = start[has] + count[has] // 2
    out[has] = 0.5 * (v[lo] + v[hi])
    return out
