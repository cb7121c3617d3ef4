"""Laser-scanner simulation: points on the surfaces within noise, occlusion, range, subsampling."""

import numpy as np
import pytest

from linereg.errors import InvalidInputError
from linereg.sim.building import make_building
from linereg.sim.demo_scene import scanner_positions
from linereg.sim.scanner import ScanConfig, scan, thin
from linereg.sim.views import occluded

COARSE = ScanConfig(angular_step_deg=0.6)


@pytest.fixture(scope="module")
def building():
    return make_building(np.random.default_rng(0))


def face_distances(
    points: np.ndarray, faces: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P,) distance to the nearest face, (P,) its index): plane distance, inside its rectangle."""
    best, arg = np.full(len(points), np.inf), np.zeros(len(points), dtype=np.int64)
    e1, e2 = faces[:, 1] - faces[:, 0], faces[:, 3] - faces[:, 0]
    for chunk in np.array_split(np.arange(len(points)), max(1, len(points) // 500)):
        rel = points[chunk, None, :] - faces[None, :, 0]  # (p, F, 3)
        a = np.einsum("pfk,fk->pf", rel, e1) / np.einsum("fk,fk->f", e1, e1)
        b = np.einsum("pfk,fk->pf", rel, e2) / np.einsum("fk,fk->f", e2, e2)
        dist = np.abs(np.einsum("pfk,fk->pf", rel, normals))
        dist[(a < -1e-3) | (a > 1 + 1e-3) | (b < -1e-3) | (b > 1 + 1e-3)] = np.inf
        best[chunk], arg[chunk] = dist.min(axis=1), dist.argmin(axis=1)
    return best, arg


def test_points_lie_on_faces_within_noise(building):
    position = scanner_positions(building)[:1]
    cloud = scan(building, position, np.random.default_rng(0), COARSE)
    assert cloud.dtype == np.float64 and cloud.shape[1] == 3 and len(cloud) > 20_000
    sample = cloud[np.random.default_rng(1).choice(len(cloud), 3000, replace=False)]
    dist, _ = face_distances(sample, building.faces, building.normals)
    assert np.quantile(dist, 0.99) < 0.04  # 4 sigma of 1 cm range noise (ranges meet faces obliquely)
    assert 0.002 < np.median(dist) < 0.0075  # median |N(0, 1 cm)| = 6.7 mm, less on oblique faces
    ranges = np.linalg.norm(cloud - position, axis=1)
    assert ranges.max() <= COARSE.max_range_m + 0.05 and ranges.min() >= COARSE.min_range_m - 0.05


def test_occluded_faces_receive_no_points(building):
    position = scanner_positions(building)[1]  # an outer corner: most facades are hidden or turned away
    cloud = scan(building, position[None], np.random.default_rng(0), ScanConfig(angular_step_deg=0.8,
                 range_noise_m=0.0))  # fmt: skip
    big = np.flatnonzero(np.linalg.norm(building.faces[:, 2] - building.faces[:, 0], axis=1) > 3.0)
    corners = building.faces[big].reshape(-1, 3)
    # shrink the corners a little towards the face centre so that they do not sit on other faces' borders
    centres = building.faces[big].mean(axis=1, keepdims=True)
    probes = (0.9 * building.faces[big] + 0.1 * centres).reshape(-1, 3)
    hidden = occluded(building, position, probes).reshape(-1, 4).all(axis=1)
    facing = np.einsum("fk,fk->f", position - building.faces[big, 0], building.normals[big]) > 0
    dist, arg = face_distances(cloud, building.faces[big], building.normals[big])
    counts = np.bincount(arg[dist < 1e-6], minlength=len(big))
    assert (facing & hidden).sum() > 20 and (facing & ~hidden).sum() > 20 and len(corners) == 4 * len(big)
    assert counts[hidden | ~facing].sum() == 0
    assert (counts[facing & ~hidden] > 0).mean() > 0.8


def test_subsampling_determinism_and_density(building):
    positions = scanner_positions(building)[:2]
    cfg = ScanConfig(angular_step_deg=1.0, target_points=5000)
    a = scan(building, positions, np.random.default_rng(4), cfg)
    b = scan(building, positions, np.random.default_rng(4), cfg)
    assert a.shape == (5000, 3) and np.array_equal(a, b)
    full = scan(building, positions[:1], np.random.default_rng(4), ScanConfig(angular_step_deg=1.0))
    finer = scan(building, positions[:1], np.random.default_rng(4), ScanConfig(angular_step_deg=0.5))
    assert 3.0 < len(finer) / len(full) < 5.0  # half the step, four times the rays


@pytest.mark.parametrize("bad", [np.zeros(3), np.zeros((2, 2)), np.full((1, 3), np.nan)])
def test_bad_positions(building, bad):
    with pytest.raises(InvalidInputError, match="scanner_positions"):
        scan(building, bad, np.random.default_rng(0))


def test_thin_caps_the_densest_cells_first():
    rng = np.random.default_rng(3)
    dense = rng.uniform(0.0, 0.1, size=(5000, 3))  # one 10 cm cell
    sparse = np.c_[np.arange(200) * 0.5 + 1.0, np.zeros((200, 2))]  # one point per cell
    cloud = np.r_[dense, sparse]
    thinned = thin(cloud, 1000, np.random.default_rng(0), 0.1)
    assert len(thinned) == 1000
    assert (np.isin(sparse[:, 0], thinned[:, 0])).all()  # the sparse cells keep every point
    rows = np.flatnonzero((cloud[:, None] == thinned[None]).all(axis=2).any(axis=1))
    assert (np.diff(rows) > 0).all()  # a subset in the input order
    uniform = thin(cloud, 1000, np.random.default_rng(0), 0.0)
    assert len(uniform) == 1000 and (uniform[:, 0] >= 1.0).sum() < 100  # the old uniform subsample
    assert len(thin(cloud, 10_000, np.random.default_rng(0), 0.1)) == len(cloud)
