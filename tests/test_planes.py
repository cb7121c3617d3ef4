"""planes / voxels: voxel neighbours, plane fits, candidate regions and segmentation of known planes."""

import itertools

import numpy as np
import pytest

import linereg.map.voxels as voxels_module
from linereg.config import Lines3DConfig
from linereg.map.planes import segment_planes
from linereg.map.regions import _candidates, _nearest
from linereg.map.voxels import (
    AROUND,
    FORWARD,
    build_voxels,
    combine_moments,
    fit_planes,
    moments,
    neighbors,
    voxel_downsample,
)


def _brute_neighbors(vox, index, offsets):
    where = {tuple(k): i for i, k in enumerate(vox.keys)}
    return np.array([[where.get(tuple(vox.keys[i] + o), -1) for o in offsets] for i in index], dtype=np.int64)


@pytest.fixture(params=["table", "search"])
def lookup(request, monkeypatch):
    if request.param == "search":
        monkeypatch.setattr(voxels_module, "MAX_TABLE_CELLS", 0)
    return request.param


def test_neighbors_match_brute_force(lookup):
    rng = np.random.default_rng(0)
    points = rng.uniform(-1.0, 1.0, size=(400, 3)) * [1.0, 0.5, 0.3]
    vox = build_voxels(points, 0.2)
    assert (vox.lookup is None) == (lookup == "search")
    index = np.arange(len(vox.flat))
    np.testing.assert_array_equal(neighbors(vox, index, AROUND), _brute_neighbors(vox, index, AROUND))
    np.testing.assert_array_equal(
        neighbors(vox, index[::3], FORWARD), _brute_neighbors(vox, index[::3], FORWARD)
    )


@pytest.mark.parametrize("bound", [1, 7, 2**40])
def test_unique_matches_numpy(bound):
    values = np.random.default_rng(bound).integers(0, bound, size=5000)
    for ours, theirs in zip(
        voxels_module._unique(values, bound),
        np.unique(values, return_inverse=True, return_counts=True),
        strict=True,
    ):
        np.testing.assert_array_equal(ours, theirs)


def test_build_voxels_groups_points():
    points = np.array([[0.05, 0.05, 0.05], [0.06, 0.01, 0.09], [0.15, 0.0, 0.0], [1.0, 2.0, 3.0]])
    vox = build_voxels(points, 0.1)
    assert vox.of_point[0] == vox.of_point[1] != vox.of_point[2]
    np.testing.assert_array_equal(vox.counts[vox.of_point], [2, 2, 1, 1])
    np.testing.assert_array_equal(
        vox.keys[vox.of_point], np.floor(points / 0.1) - np.floor(points / 0.1).min(0)
    )


def test_voxel_downsample_gives_centroids():
    points = np.array([[0.01, 0.0, 0.0], [0.03, 0.02, 0.0], [0.5, 0.5, 0.5]])
    out = voxel_downsample(points, 0.1)
    np.testing.assert_allclose(out, [[0.02, 0.01, 0.0], [0.5, 0.5, 0.5]])
    assert voxel_downsample(np.zeros((0, 3)), 0.1).shape == (0, 3)


def _covariance_groups(rng):
    """Returns (P, 3) points and (P,) groups: noisy planes, a line, a blob, duplicated points, a pair."""
    groups = []
    for _ in range(200):
        frame = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        scale = [1.0, rng.uniform(0.1, 1.0), rng.uniform(1e-4, 0.05)]
        groups.append(rng.normal(size=(rng.integers(3, 30), 3)) * scale @ frame.T + rng.uniform(-50, 50, 3))
    groups.append(np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 3.0]))  # collinear: repeated eigenvalue 0
    groups.append(np.tile([[5.0, 5.0, 5.0]], (6, 1)))  # identical points: zero covariance
    groups.append(rng.normal(size=(50, 3)))  # isotropic blob
    groups.append(np.zeros((2, 3)))  # too few to fit
    labels = np.concatenate([np.full(len(g), i) for i, g in enumerate(groups)])
    return np.concatenate(groups), labels


def test_closed_form_fit_matches_eigh():
    points, group = _covariance_groups(np.random.default_rng(1))
    num = int(group.max()) + 1
    counts, cen, nrm, curv = fit_planes(points, group, num)
    counts2, cen2, nrm2, curv2 = fit_planes(points, group, num, closed_form=True)
    np.testing.assert_array_equal(counts, counts2)
    np.testing.assert_array_equal(cen, cen2)
    np.testing.assert_allclose(curv2, curv, atol=1e-12)
    assert np.isinf(curv[-1]) and (nrm[-1] == 0).all()
    well_posed = np.arange(200)  # the planes; the line, the blob and the duplicates have no unique normal
    cos = np.abs(np.einsum("ij,ij->i", nrm[well_posed], nrm2[well_posed]))
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(nrm2[:-1], axis=1), 1.0, atol=1e-12)


def test_fit_planes_known_plane_and_ignored_points():
    rng = np.random.default_rng(2)
    uv = rng.uniform(-1, 1, size=(500, 2))
    normal = np.array([1.0, 2.0, 2.0]) / 3.0
    basis = np.linalg.svd(normal[None])[2][1:]
    plane = uv @ basis + [10.0, 0.0, -3.0]
    noise = rng.uniform(-5, 5, size=(100, 3))
    group = np.r_[np.zeros(500, np.int64), np.full(100, -1)]
    counts, cen, nrm, curv = fit_planes(np.r_[plane, noise], group, 1, min_points=5)
    assert counts[0] == 500 and curv[0] < 1e-12
    np.testing.assert_allclose(abs(nrm[0] @ normal), 1.0, atol=1e-12)
    np.testing.assert_allclose(cen[0], plane.mean(axis=0), atol=1e-12)


def test_combined_moments_are_the_moments_of_the_union():
    points, group = _covariance_groups(np.random.default_rng(6))
    parts = moments(points, group, int(group.max()) + 1)
    into = np.random.default_rng(7).integers(-1, 20, size=len(parts.counts))
    joined = combine_moments(parts, into, 20)
    # the union of the fitted parts (the last group, 2 points, has no covariance and joins nothing)
    direct = moments(points, np.where(parts.fitted[group], into[group], -1), 20)
    np.testing.assert_array_equal(joined.counts, direct.counts)
    np.testing.assert_allclose(joined.centroids, direct.centroids, rtol=0, atol=1e-9)
    np.testing.assert_allclose(joined.covariance, direct.covariance, rtol=0, atol=1e-7)


def test_candidates_are_the_regions_around_each_voxel():
    rng = np.random.default_rng(3)
    vox = build_voxels(rng.integers(0, 6, size=(300, 3)) * 0.1 + 0.05, 0.1)
    labels = rng.integers(-1, 4, size=len(vox.flat))
    table, count = _candidates(vox, labels)
    table = table.T
    np.testing.assert_array_equal(count, (table >= 0).sum(axis=1))
    around = _brute_neighbors(vox, np.arange(len(vox.flat)), AROUND)
    for v in range(len(vox.flat)):
        expected = {int(labels[u]) for u in around[v] if u >= 0 and labels[u] >= 0}
        row = table[v]
        assert (row[: len(expected)] >= 0).all() and (row[len(expected) :] < 0).all()
        assert set(row[row >= 0].tolist()) == expected


def test_nearest_takes_smallest_key_then_smallest_value():
    group = np.array([0, 0, 0, 2, 2, 3])
    value = np.array([7, 3, 5, 1, 9, 4])
    key = np.array([0.2, 0.1, 0.1, np.inf, 0.3, np.inf])
    np.testing.assert_array_equal(_nearest(group, value, key, 5), [3, -1, 9, -1, -1])


def _box(rng, density=300.0, noise_m=0.002):
    """Returns (P, 3) points of the ground, two walls meeting at a right angle and a roof of a 6 x 4 x 3 m
    box, and (P,) int64 the part of each point."""
    parts = []
    for origin, a, b in [
        ((-2, -2, 0), (10, 0, 0), (0, 8, 0)),  # ground
        ((0, 0, 0), (6, 0, 0), (0, 0, 3)),  # wall y = 0
        ((0, 0, 0), (0, 4, 0), (0, 0, 3)),  # wall x = 0
        ((0, 0, 3), (6, 0, 0), (0, 4, 0)),  # roof
    ]:
        origin, a, b = (np.asarray(v, dtype=np.float64) for v in (origin, a, b))
        uv = rng.uniform(size=(int(density * np.linalg.norm(a) * np.linalg.norm(b)), 2))
        parts.append(origin + uv[:, :1] * a + uv[:, 1:] * b)
    points = np.concatenate(parts)
    points += rng.normal(0.0, noise_m, points.shape)
    return points + 2.0, np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)])


def test_segment_planes_finds_the_box_faces():
    points, part = _box(np.random.default_rng(4))
    planes = segment_planes(points)
    assert planes.labels.shape == (len(points),) and planes.labels.dtype == np.int64
    big = np.flatnonzero(planes.counts > 2000)
    assert len(big) == 4
    truth = np.eye(3)[[2, 1, 0, 2]]
    for label in big:
        members = part[planes.labels == label]
        dominant = np.bincount(members).argmax()
        assert (members == dominant).mean() > 0.99  # one face per region
        assert abs(planes.normals[label] @ truth[dominant]) > 0.999
    # the faces meet: ground-walls, walls-walls, walls-roof touch
    touching = {
        tuple(sorted(np.bincount(part[planes.labels == r]).argmax() for r in p)) for p in planes.pairs
    }
    assert {(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)} <= touching
    assert (planes.labels >= 0).mean() > 0.95
    np.testing.assert_allclose(planes.spacing_m[big], 1 / np.sqrt(300.0), rtol=0.3)


def test_segment_planes_without_planes():
    rng = np.random.default_rng(5)
    empty = segment_planes(np.zeros((0, 3)))
    assert empty.labels.shape == (0,) and empty.normals.shape == (0, 3)
    blob = segment_planes(rng.normal(size=(2000, 3)), Lines3DConfig())
    assert (blob.labels < 0).all() and len(blob.counts) == 0 and blob.pairs.shape == (0, 2)


def test_offsets_are_the_neighbourhood():
    assert len({tuple(o) for o in AROUND}) == 27 and len(FORWARD) == 13
    both = {tuple(o) for o in FORWARD} | {tuple(-o) for o in FORWARD}
    assert both == {o for o in itertools.product((-1, 0, 1), repeat=3)} - {(0, 0, 0)}
