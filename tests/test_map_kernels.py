"""The compiled loops of map building against the rules they implement, written plainly with numpy."""

from __future__ import annotations

import numpy as np

from linereg.map import creases, edge_refine, lines3d, point_edges


def test_the_least_axis_is_the_eigenvector_of_the_smallest_eigenvalue():
    rng = np.random.default_rng(0)
    for _ in range(200):
        # a flat patch's spread (the common case), and any symmetric positive matrix
        spread = rng.normal(size=(20, 3)) * rng.choice([[1.0, 1.0, 0.01], [1.0, 0.3, 0.2]])
        turn = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        cov = (spread @ turn).T @ (spread @ turn)
        axis = np.array(point_edges._least_axis(*cov[0], *cov[1, 1:], cov[2, 2]))
        want = np.linalg.eigh(cov)[1][:, 0]
        assert abs(np.linalg.norm(axis) - 1.0) < 1e-12
        assert abs(abs(axis @ want) - 1.0) < 1e-9


def test_normals_and_shifts_match_a_plain_fit():
    rng = np.random.default_rng(1)
    points = np.c_[rng.uniform(0, 1, (400, 2)), 0.001 * rng.normal(size=400)]
    nb = np.array([np.argsort(np.linalg.norm(points - p, axis=1))[:12] for p in points])
    radius = np.linalg.norm(points[nb[:, -1]] - points, axis=1)
    normal, shift = np.zeros_like(points), np.zeros(len(points))
    point_edges._fit_normals(points, 0, nb, radius, normal, shift)
    q = points[nb]
    centroid = q.mean(axis=1)
    d = q - centroid[:, None]
    want = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))[1][:, :, 0]
    off = centroid - points
    off -= want * np.einsum("ni,ni->n", off, want)[:, None]
    assert np.allclose(np.abs(np.einsum("ni,ni->n", normal, want)), 1.0, atol=1e-9)
    assert np.allclose(shift, np.linalg.norm(off, axis=1) / radius, atol=1e-9)


def test_a_point_bends_where_enough_neighbours_normals_turn():
    normal = np.array([[0.0, 0.0, 1.0]] * 5 + [[1.0, 0.0, 0.0]] * 3)
    near = np.array([[1, 2, 3, 4], [5, 6, 7, 0], [5, 6, 0, 1], [5, 0, 1, 2], [0, 1, 2, 3]] * 2)[:8]
    out = np.zeros(8, dtype=bool)
    point_edges._bends(normal, near, 0, 8, np.cos(np.radians(30)), 2, out)
    turned = (np.abs(np.einsum("nki,ni->nk", normal[near], normal)) < np.cos(np.radians(30))).sum(axis=1)
    assert np.array_equal(out, turned >= 2)


def test_closing_fills_short_gaps_only():
    rng = np.random.default_rng(2)
    for half in (1, 2, 3):
        for _ in range(50):
            mask = rng.random(30) < 0.6
            got = creases._close_1d(mask, half)
            n = len(mask)
            dilated = np.array([mask[max(i - half, 0) : i + half + 1].any() for i in range(n)])
            padded = np.r_[np.ones(half, bool), dilated, np.ones(half, bool)]
            want = np.array([padded[i : i + 2 * half + 1].all() for i in range(n)])
            assert np.array_equal(got, want)


def test_beside_pairs_are_the_points_in_each_lines_band():
    rng = np.random.default_rng(3)
    beside = [rng.uniform(-1, 2, (50, 3)), np.zeros((0, 3)), rng.uniform(-1, 2, (30, 3))]
    a = rng.uniform(0, 1, (6, 2))
    angle = rng.uniform(0, np.pi, 6)
    d = np.c_[np.cos(angle), np.sin(angle)]
    out = np.c_[-d[:, 1], d[:, 0]] * rng.choice([-1.0, 1.0], (6, 1))
    length, band = rng.uniform(0.2, 1.0, 6), rng.uniform(0.05, 0.3, 6)
    regions = [(beside[0], 0, 2), (beside[1], 2, 4), (beside[2], 4, 6)]
    got = edge_refine._beside_pairs(regions, (a, d, out, length, band))
    want = []
    for points, lo, hi in regions:
        for k in range(lo, hi):
            rel = points[:, :2] - a[k]
            t, o = rel @ d[k], rel @ out[k]
            keep = (t >= 0) & (t <= length[k]) & (np.abs(o) <= band[k])
            want += [(k, tt, oo, z) for tt, oo, z in zip(t[keep], o[keep], points[keep, 2], strict=True)]
    want = np.array(want).reshape(-1, 4)
    # line by line, in any order within a line
    got, want = (x[np.lexsort((x[:, 1], x[:, 0]))] for x in (got, want))
    assert np.allclose(got, want, atol=1e-12)


def test_beside_rows_keep_the_points_near_each_plane_and_inside_its_box():
    rng = np.random.default_rng(4)
    data = rng.uniform(-1, 1, (300, 3))
    index = rng.integers(0, 300, 120)
    first = np.array([0, 50, 50, 120])
    origin = rng.uniform(-0.2, 0.2, (3, 3))
    normal = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    basis = np.stack([np.linalg.qr(np.c_[n, rng.normal(size=(3, 2))])[0][:, 1:].T for n in normal])
    lo, hi = np.full((3, 2), -0.5), np.full((3, 2), 0.4)
    rows, kept = lines3d._beside_rows(data, index, first, origin, normal, basis, lo, hi, 0.3)
    want = []
    for i in range(3):
        rel = data[index[first[i] : first[i + 1]]] - origin[i]
        depth, uv = rel @ normal[i], rel @ basis[i].T
        keep = (np.abs(depth) <= 0.3) & ((uv >= lo[i]) & (uv <= hi[i])).all(axis=1)
        want.append(np.c_[uv[keep], depth[keep]])
    assert np.array_equal(kept, [len(w) for w in want])
    assert np.allclose(rows, np.concatenate(want), atol=1e-12)


def test_group_minima_match_numpys_minimum_at():
    rng = np.random.default_rng(5)
    values = rng.normal(size=500)
    values[[7, 300]] = np.nan
    group = rng.integers(0, 40, 500)
    want = np.full(45, np.inf)
    with np.errstate(invalid="ignore"):
        np.minimum.at(want, group, values)
    assert np.array_equal(edge_refine._group_min(values, group, 45), want, equal_nan=True)


def test_small_regions_spacing_matches_a_kd_tree_bit_for_bit():
    from scipy.spatial import cKDTree

    from linereg.map import planes

    rng = np.random.default_rng(6)
    points = rng.uniform(0, 1, (3000, 3)) * [1.0, 1.0, 0.01]
    labels = rng.integers(0, 6, 3000)
    labels[:2] = 6  # a region of two points: one neighbour
    labels[2] = 7  # a region of one point: none
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(9)).astype(np.int64)
    got = planes._small_region_medians(points, order, bounds, np.arange(8), 8)
    for r in range(8):
        member = points[order[bounds[r] : bounds[r + 1]]]
        k = min(8, len(member) - 1)
        if k < 1:
            assert got[r] == 0.0
            continue
        dist, _ = cKDTree(member).query(member[:: max(1, len(member) // 500)], k=k + 1)
        assert got[r] == np.median(dist[:, -1])


def test_each_point_joins_the_nearest_pile_within_reach():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(7)
    spacing, lo = 0.01, np.array([-0.02, -0.03])
    uv = rng.uniform(0, 0.3, (2000, 2))
    ij = np.floor((uv - lo) / spacing).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 3)
    peaks = np.unique(rng.integers(0, min(shape), (60, 2)), axis=0)
    label = np.full(shape, -1, dtype=np.int64)
    label[peaks[:, 0], peaks[:, 1]] = np.arange(len(peaks))
    got = point_edges._nearest_pile(uv, ij, label, lo, spacing, 1.5 * spacing)
    dist, want = cKDTree(lo + (peaks + 0.5) * spacing).query(uv, distance_upper_bound=1.5 * spacing)
    assert np.array_equal(got, np.where(np.isfinite(dist), want, -1))


def test_section_moments_sum_the_offsets_of_each_slices_own_points():
    rng = np.random.default_rng(8)
    points = rng.uniform(-0.1, 1.1, (500, 3))
    p0, d = np.array([[0.0, 0.5, 0.5]]), np.array([[1.0, 0.0, 0.0]])
    seg, step = np.zeros(4, dtype=np.int64), np.full(4, 0.25)
    mid = (np.arange(4) + 0.5) * 0.25
    idx = np.arange(500)
    n, sums, second = point_edges._section_moments(
        points, np.r_[idx, idx, idx, idx], np.arange(5) * 500, seg, p0, d, mid, step, 0.2
    )
    rel = points - p0[0]
    perp = rel - np.outer(rel @ d[0], d[0])
    inside = (rel[:, 0] >= 0) & (rel[:, 0] <= 1) & (np.linalg.norm(perp, axis=1) <= 0.2)
    assert n[0] == inside.sum()
    assert np.allclose(sums[0], perp[inside].sum(axis=0))
    assert np.allclose(second[0], perp[inside].T @ perp[inside])


def test_the_median_by_selection_is_numpys():
    from linereg.map import planes

    rng = np.random.default_rng(9)
    for n in [1, 2, 3, 4, 5, 10, 11, 100, 501]:
        for _ in range(20):
            values = rng.normal(size=n)
            if n > 3:
                values[: n // 3] = values[n // 2]  # ties
            rng.shuffle(values)
            assert planes._median(values.copy()) == np.median(values)


def test_a_crease_lines_near_points_come_from_the_grid_as_from_a_plain_search():
    rng = np.random.default_rng(10)
    points = np.c_[rng.uniform(0, 2, (4000, 2)), 0.01 * rng.normal(size=4000)]  # a floor
    members = [np.arange(2000), np.arange(2000, 4000)]
    grid = creases._region_grids(points, members, np.array([0.06, 0.09]))
    origin, direction = np.array([0.3, 0.2, 0.0]), np.array([0.6, 0.8, 0.0])
    r, enter = 0.09, 0.1
    count = int(np.ceil((1.8 + r - enter) / r))
    for region in (0, 1):
        t_out, perp_out = np.empty(2000), np.empty((2000, 3))
        n = creases._near_side(points, grid, region, origin, direction, enter, r, count, t_out, perp_out)
        p = points[members[region]] - origin
        t = p @ direction
        perp = p - np.outer(t, direction)
        nearest = enter + np.clip(np.floor((t - enter) / r + 0.5), 0, count - 1) * r
        near = (np.linalg.norm(perp, axis=1) <= r) & (
            np.linalg.norm(points[members[region]] - (origin + np.outer(nearest, direction)), axis=1)
            <= 1.5 * r
        )
        assert n == near.sum() > 50
        assert np.allclose(np.sort(t_out[:n]), np.sort(t[near]), atol=1e-12)
