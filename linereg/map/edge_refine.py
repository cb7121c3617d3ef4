"""Boundary lines of a planar region moved from its raster (cell-quantised) to where its points end (part of
``lines3d.extract``).

All lines of all regions are refined at once: each line's points (its region's within its band) come
from one compiled loop over the regions' points, and the per-bin edge estimates and per-line fits are
grouped sums over flat arrays.
"""

from __future__ import annotations

import numba
import numpy as np

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
    fixed = np.zeros(len(lines), dtype=bool) if fixed is None else fixed
    beside = np.zeros((0, 3)) if beside is None else beside
    return refine_regions([uv], [lines], [band], config, [beside], [fixed])[0]


def refine_regions(
    uvs: list[np.ndarray],
    lines: list[np.ndarray],
    bands: list[float],
    config: Lines3DConfig,
    besides: list[np.ndarray],
    fixed: list[np.ndarray],
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Returns ``refine_edges`` of each region (its uv points, lines, band, beside points and fixed lines)
    computed at once: each line's points (those of its region within its band) in one compiled loop, the
    rest as grouped sums over every region's lines (a room holds a thousand small regions: a call each
    cost more than the sums). A line's sums add the same numbers in the same order as one region alone."""
    sizes = np.array([len(x) for x in lines], dtype=np.int64)
    first = np.r_[0, np.cumsum(sizes)]
    k = int(first[-1])
    if k == 0:
        return [(x, np.zeros(0, dtype=bool)) for x in lines]
    every = np.concatenate(lines)
    band = np.repeat(np.asarray(bands, dtype=np.float64), sizes)
    fix = np.concatenate(fixed).astype(bool)
    a, b = every[:, :2], every[:, 2:]
    length = np.linalg.norm(b - a, axis=1)
    d = (b - a) / length[:, None]
    m = np.stack([-d[:, 1], d[:, 0]], axis=1)
    base = np.r_[0, np.cumsum([len(u) for u in uvs])].astype(np.int64)
    uv = np.concatenate([np.zeros((0, 2)), *uvs])
    region = np.repeat(np.arange(len(lines)), sizes)
    has = np.flatnonzero(sizes > 0)
    # each line's points within its band across, half a band in from its ends
    near = _in_bands(uv, base, region, a, d, m, length, band, 0.5)
    line, t, s = near[:, 0].astype(np.int64), near[:, 1], near[:, 2]
    count = np.bincount(line, minlength=k)
    t_lo, t_hi = _group_min(t, line, k), -_group_min(-t, line, k)
    # no points along most of it: the raster's closing bridged a gap, no boundary of the surface
    ok = (count >= config.edge_min_line_points) & (t_hi - t_lo >= 0.5 * (length - band))
    outward = -np.sign(np.bincount(line, s, k))  # the points lie on the inner side
    geometry = (a, d, m * outward[:, None], length, band)
    pairs = _beside_pairs([(besides[r], first[r], first[r + 1]) for r in has], geometry)
    on_plane = np.abs(pairs[:, 3]) < config.edge_on_plane_m
    off = pairs[~on_plane]
    o = outward[line] * s
    # the free fit tells whether a straight edge lies behind the line (a ragged outline's chords snap
    # onto a family direction too); lines too short for it (one bin) may still take a known direction
    slope, intercept, on_line = _edge_lines(line, t, o, t_lo, band, np.zeros(k, dtype=bool), off, config)
    lo_hi = (-band[:, None], band[:, None])
    ends = np.clip(intercept[:, None] + slope[:, None] * np.stack([np.zeros(k), length], 1), *lo_hi)
    straight = (on_line >= 0.5 * (length - band) / band) & (
        np.abs(ends[:, 1] - ends[:, 0]) <= length * np.tan(np.radians(config.edge_max_tilt_deg))
    )
    _, intercept0, on_line0 = _edge_lines(line, t, o, t_lo, band, fix, off, config)
    short = fix & ~np.isfinite(slope) & (on_line0 >= 1)
    ok &= straight | short
    ends[fix] = np.clip(intercept0[fix, None], -band[fix, None], band[fix, None])
    # points of no region in the plane beyond the edge: the surface goes on, only its labels stop (region
    # growing leaves out the points round a crease, for one)
    on = pairs[on_plane]
    owner = on[:, 0].astype(np.int64)
    reach = ends[owner].max(axis=1)
    beyond = on[:, 2] > np.where(np.isnan(reach), band[owner], np.nan_to_num(reach))
    ok &= np.bincount(owner[beyond], minlength=k) < config.edge_max_going_on * count
    shift = (outward[:, None, None] * ends[..., None]) * m[:, None, :]
    moved = np.concatenate([a + shift[:, 0], b + shift[:, 1]], axis=1)
    return [(moved[first[r] : first[r + 1]], ok[first[r] : first[r + 1]]) for r in range(len(lines))]


def _beside_pairs(besides: list[tuple[np.ndarray, int, int]], geometry: tuple[np.ndarray, ...]) -> np.ndarray:
    """Returns (q, 4) line, t, outward offset, depth of each region's (b, 3) beside points (u, v, signed
    plane distance) within a band of each of its lines: 0 <= t <= length, |offset| <= band; ``besides``:
    per region its points and its lines (first, end); geometry: (k, 2) starts, directions, outward
    normals, (k,) lengths, bands of all lines. The pairs come line by line (their uses are minima and
    counts: the order does not matter)."""
    a, d, out, length, band = geometry
    besides = [x for x in besides if len(x[0])]
    if not besides:
        return np.zeros((0, 4))
    beside = np.concatenate([near for near, _, _ in besides])
    first = np.r_[0, np.cumsum([len(near) for near, _, _ in besides])].astype(np.int64)
    owner = np.full(len(a), -1, dtype=np.int64)  # the region of each line, among those with points
    for j, (_, lo, hi) in enumerate(besides):
        owner[lo:hi] = j
    return _in_bands(beside, first, owner, a, d, out, length, band, 0.0)


BRUTE_LINES = 16  # a region with at most this many lines tests all its points per line, no grid


@numba.njit(cache=True, nogil=True)
def _in_bands(
    points: np.ndarray,
    first: np.ndarray,
    owner: np.ndarray,
    a: np.ndarray,
    d: np.ndarray,
    across: np.ndarray,
    length: np.ndarray,
    band: np.ndarray,
    margin: float,
) -> np.ndarray:  # pragma: no cover - numba
    """Returns (q, 4) rows line k, t (along d[k] from a[k]), o (along across[k]), third column of the point
    (0 for (n, 2) points): for each line k of region owner[k] >= 0 (its points points[first[r]:first[r + 1]];
    a region's lines come one after another and share a band), every point with
    margin band[k] <= t <= length[k] - margin band[k], |o| <= band[k] and within hypot(band, band / 2) of
    the line's sample (every band from a[k]) nearest it along the line; line after line.

    A region of many lines (a facade holds 10^5 points and hundreds of window lines) has its points sorted
    into square cells a band wide: each sample of a line looks at the cells within two of its own and keeps
    the points whose nearest sample it is, so the work follows the lines' lengths. A region of at most
    BRUTE_LINES lines (most of a room's thousand) tests all its points per line.
    """
    rows = np.empty((0, 4))
    for fill in range(2):  # count, then fill (a loop over a tuple costs a second to compile)
        n = 0
        region, h = -1, -1.0
        brute = True
        lo0 = lo1 = 0.0
        nx = ny = 1
        order = np.zeros(0, dtype=np.int64)
        start = np.zeros(1, dtype=np.int64)
        for k in range(len(owner)):
            r = owner[k]
            if r < 0 or first[r + 1] == first[r]:
                continue
            if r != region or band[k] != h:
                region, h = r, band[k]
                lines = 0
                while k + lines < len(owner) and owner[k + lines] == r and band[k + lines] == h:
                    lines += 1
                brute = lines <= BRUTE_LINES
                if not brute:
                    lo0, lo1, nx, ny, order, start = _band_grid(points, first[r], first[r + 1], h)
            count = int(np.ceil((length[k] + band[k]) / band[k]))
            lo_t, hi_t = margin * band[k], length[k] - margin * band[k]
            # a region of few lines: one pass over all its points; else, per sample s, the points in the
            # cells round it whose nearest sample s is. The test is written once for both (a helper per
            # point, tuple- or int-returning, inlined or not, made these loops 10-15x slower)
            for s in range(1 if brute else count):
                i0, i1, j0, j1 = 0, 1, 0, 1
                if not brute:
                    ci = int(np.floor((a[k, 0] + s * band[k] * d[k, 0] - lo0) / h))
                    cj = int(np.floor((a[k, 1] + s * band[k] * d[k, 1] - lo1) / h))
                    i0, i1, j0, j1 = max(ci - 2, 0), min(ci + 3, nx), max(cj - 2, 0), min(cj + 3, ny)
                for i in range(i0, i1):
                    for j in range(j0, j1):
                        c = i * ny + j
                        m0, m1 = (first[r], first[r + 1]) if brute else (start[c], start[c + 1])
                        for m in range(m0, m1):
                            p = m if brute else order[m]
                            r0, r1 = points[p, 0] - a[k, 0], points[p, 1] - a[k, 1]
                            t = r0 * d[k, 0] + r1 * d[k, 1]
                            o = r0 * across[k, 0] + r1 * across[k, 1]
                            if not (t >= lo_t and t <= hi_t and abs(o) <= band[k] and np.isfinite(o)):
                                continue
                            own = min(max(np.floor(t / band[k] + 0.5), 0.0), count - 1.0)
                            if not brute and own != s:
                                continue  # another sample's point
                            e0 = points[p, 0] - (a[k, 0] + own * band[k] * d[k, 0])
                            e1 = points[p, 1] - (a[k, 1] + own * band[k] * d[k, 1])
                            if e0 * e0 + e1 * e1 > 1.25 * band[k] * band[k]:
                                continue
                            if fill:
                                rows[n, 0], rows[n, 1], rows[n, 2] = k, t, o
                                rows[n, 3] = points[p, 2] if points.shape[1] > 2 else 0.0
                            n += 1
        if not fill:
            rows = np.empty((n, 4))
    return rows


@numba.njit(cache=True, nogil=True)
def _band_grid(
    points: np.ndarray, lo: int, hi: int, h: float
) -> tuple[float, float, int, int, np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """Returns the grid of points[lo:hi] in square cells ``h`` wide from their lower corner: its corner,
    (nx, ny) cells, the points' indices cell after cell (in their order within a cell: a counting sort)
    and each cell's start among them (nx ny + 1)."""
    lo0, lo1 = np.inf, np.inf
    hi0, hi1 = -np.inf, -np.inf
    for p in range(lo, hi):
        lo0, lo1 = min(lo0, points[p, 0]), min(lo1, points[p, 1])
        hi0, hi1 = max(hi0, points[p, 0]), max(hi1, points[p, 1])
    nx, ny = int((hi0 - lo0) / h) + 1, int((hi1 - lo1) / h) + 1
    key = np.empty(hi - lo, dtype=np.int64)
    for p in range(lo, hi):
        key[p - lo] = int((points[p, 0] - lo0) / h) * ny + int((points[p, 1] - lo1) / h)
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(len(key)):
        start[key[i] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    placed = np.empty(nx * ny, dtype=np.int64)
    for c in range(nx * ny):
        placed[c] = start[c]
    order = np.empty(len(key), dtype=np.int64)
    for i in range(len(key)):
        order[placed[key[i]]] = lo + i
        placed[key[i]] += 1
    return lo0, lo1, nx, ny, order, start


def _group_min(values: np.ndarray, group: np.ndarray, num: int) -> np.ndarray:
    """Returns (num,) the minimum of values per group (inf for empty groups)."""
    out = np.full(num, np.inf)
    _min_into(out, group, values)
    return out


@numba.njit(cache=True, nogil=True)
def _min_into(out: np.ndarray, group: np.ndarray, values: np.ndarray) -> None:  # pragma: no cover - numba
    """out[group[i]] = minimum(out[group[i]], values[i]) for every i: ``np.minimum.at`` in one loop (a NaN
    wins, as there)."""
    for i in range(len(group)):
        if values[i] < out[group[i]] or np.isnan(values[i]):
            out[group[i]] = values[i]


def _edge_lines(
    line: np.ndarray,
    t: np.ndarray,
    o: np.ndarray,
    t_lo: np.ndarray,
    band: np.ndarray,
    fixed: np.ndarray,
    off: np.ndarray,
    config: Lines3DConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (k,) slope, intercept (NaN: no fit) and bins on it of the edge e(t) behind each line's
    points at (t, outward offset o); bins on it are the band-long stretches whose edge estimate lies
    within band / 2 of the line. Bins whose estimate is off by more than 2.5 median residuals (a bin
    reaching into a neighbouring structure) are left out of a second fit. ``fixed`` lines get slope 0;
    ``band``: (k,) of each line."""
    k = len(fixed)
    bins = np.floor((t - t_lo[line]) / band[line]).astype(np.int64)
    num_bins = bins.max(initial=0) + 1
    key, inverse = np.unique(line * num_bins + bins, return_inverse=True)
    inverse = inverse.ravel()
    owner = line[np.unique(inverse, return_index=True)[1]]
    count = np.bincount(inverse)
    top = -_group_min(-o, inverse, len(key))
    centre = np.bincount(inverse, t) / count
    edge = top + (top + band[owner]) / count
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
    on = np.abs(edge - (slope[owner] * centre + intercept[owner])) <= 0.5 * band[owner]
    slope[(n_all < 2) & ~fixed | (n_all < 1)] = np.nan
    return slope, intercept, np.bincount(owner[on], minlength=k)


def _first_beyond(
    off: np.ndarray, key: np.ndarray, top: np.ndarray, t_lo: np.ndarray, num_bins: int, band: np.ndarray
) -> np.ndarray:
    """Returns (B,) per bin (sorted ``key`` = line * num_bins + bin) the smallest outward offset of the
    (q, 4) ``off`` points beyond the bin's outermost region point ``top`` by at most its line's (k,) band
    (inf: none)."""
    first = np.full(len(key), np.inf)
    if len(off) == 0 or len(key) == 0:
        return first
    line = off[:, 0].astype(np.int64)
    bins = np.floor((off[:, 1] - t_lo[line]) / band[line])
    valid = np.isfinite(bins) & (bins >= 0) & (bins < num_bins)
    wanted = line[valid] * num_bins + bins[valid].astype(np.int64)
    idx = np.minimum(np.searchsorted(key, wanted), len(key) - 1)
    o = off[valid, 2]
    hit = (key[idx] == wanted) & (o > top[idx]) & (o <= top[idx] + band[line[valid]])
    _min_into(first, idx[hit], o[hit])
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
