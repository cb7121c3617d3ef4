import numpy as np
import pytest

from linereg.geometry import camera_center, line_coefficients
from linereg.score import project_segments
from linereg.sim.building import EDGE_KINDS, FACE_KINDS, BuildingConfig, make_building, rect_minus
from linereg.sim.building_scene import building_scene
from linereg.sim.views import camera_poses, occluded, project_building, street_camera

SMALL = BuildingConfig(layout="street", blocks_per_side=1, floors=(3, 4))


@pytest.fixture(scope="module")
def building():
    return make_building(np.random.default_rng(5))


@pytest.fixture(scope="module")
def small():
    return make_building(np.random.default_rng(6), SMALL)


def areas(faces):
    return np.linalg.norm(np.cross(faces[:, 1] - faces[:, 0], faces[:, 3] - faces[:, 0]), axis=1)


def test_faces_are_planar_rectangles(building):
    q = building.faces
    assert q.ndim == 3 and q.shape[1:] == (4, 3) and q.dtype == np.float64
    sides = np.roll(q, -1, axis=1) - q
    np.testing.assert_allclose(sides[:, 0] + sides[:, 2], 0.0, atol=1e-9)  # parallelogram
    np.testing.assert_allclose(np.einsum("fk,fk->f", sides[:, 0], sides[:, 1]), 0.0, atol=1e-9)  # right angle
    n = building.normals
    np.testing.assert_allclose(np.einsum("fck,fk->fc", q - q[:, :1], n), 0.0, atol=1e-9)  # planar
    assert np.all(areas(q) > 1e-4)
    assert np.allclose(np.abs(n).max(axis=1), 1.0)  # Manhattan faces


def test_faces_are_oriented_outwards_and_closed(building):
    n, a = building.normals, areas(building.faces)
    assert np.all(n[building.face_kind == "roof", 2] > 0.99)
    assert np.all(n[building.face_kind == "ground", 2] > 0.99)
    for b, (lo, hi) in enumerate(building.blocks):
        # divergence theorem: a closed solid standing on the ground has a flux of +footprint through z only
        flux = (a[:, None] * n)[building.face_block == b].sum(axis=0)
        np.testing.assert_allclose(flux, [0.0, 0.0, np.prod(hi[:2] - lo[:2])], atol=1e-6)


def test_kinds_sizes_and_scale(building):
    assert set(np.unique(building.face_kind)) == set(FACE_KINDS)
    assert set(np.unique(building.edge_kind)) == set(EDGE_KINDS)
    assert len(building.faces) < 5000 and building.edges.shape[1] == 6
    assert len(building.face_kind) == len(building.faces) == len(building.face_block)
    size = building.blocks[:, 1] - building.blocks[:, 0]
    assert np.all(np.maximum(size[:, 0], size[:, 1]) >= 10.0) and np.all(size[:, 2] >= 9.0)
    assert np.all(size[:, 2] <= 6 * 3.6 + 1e-9)
    np.testing.assert_allclose(building.bounds[:, 2], [0.0, size[:, 2].max()], atol=0.5)


def test_edges_lie_on_face_boundaries(small):
    sides = np.stack([small.faces, np.roll(small.faces, -1, axis=1)], axis=2).reshape(-1, 2, 3)
    a, d = sides[:, 0], sides[:, 1] - sides[:, 0]
    t = np.linspace(0.0, 1.0, 5)
    pts = (
        small.edges[:, None, :3] + t[None, :, None] * (small.edges[:, None, 3:] - small.edges[:, None, :3])
    ).reshape(-1, 3)
    for chunk in np.array_split(pts, 20):
        s = np.clip(np.einsum("pk,sk->ps", chunk, d) - np.einsum("sk,sk->s", a, d), 0, None) / np.einsum(
            "sk,sk->s", d, d
        )
        s = np.minimum(s, 1.0)
        closest = a[None] + s[..., None] * d[None]
        assert np.linalg.norm(closest - chunk[:, None], axis=2).min(axis=1).max() < 1e-9


def test_manhattan_directions_dominate(building):
    e = building.edges[:, 3:] - building.edges[:, :3]
    length = np.linalg.norm(e, axis=1)
    assert np.all(length > 0.05)
    axis_aligned = np.abs(e / length[:, None]).max(axis=1) > 1 - 1e-9
    assert axis_aligned.all()
    share = np.array([length[np.argmax(np.abs(e), axis=1) == k].sum() for k in range(3)]) / length.sum()
    assert np.all(share > 0.15), share


def test_rect_minus_covers_exactly():
    holes = np.array([[1.0, 1.0, 2.0, 3.0], [4.0, 0.0, 5.0, 1.0], [0.0, 4.0, 6.0, 4.5]])
    rects = rect_minus(6.0, 5.0, holes)
    area = np.prod(rects[:, 2:] - rects[:, :2], axis=1)
    assert area.sum() == pytest.approx(30.0 - 2.0 - 1.0 - 3.0)
    assert np.all(area > 0)
    grid = np.stack(np.meshgrid(np.linspace(0.05, 5.95, 60), np.linspace(0.05, 4.95, 50)), -1).reshape(-1, 2)

    def cover(r):
        x, y = grid[:, None, 0], grid[:, None, 1]
        return (x > r[:, 0]) & (x < r[:, 2]) & (y > r[:, 1]) & (y < r[:, 3])

    assert np.all(cover(rects).sum(1) + cover(holes).sum(1) == 1)  # every point in exactly one


def test_occlusion_behind_a_block(small):
    lo, hi = small.blocks[0]
    mid = 0.5 * (lo + hi)
    front = np.array([mid[0], lo[1] - 20.0, 1.7])  # in front of the y-min facade
    near = np.array(
        [[lo[0] + 0.3, lo[1], 0.5], [lo[0] + 0.3, lo[1], hi[2]]]
    )  # on the facade (maybe a window)
    far = np.array([[mid[0], hi[1], 1.0], [mid[0], hi[1] + 5.0, 1.0]])  # back facade, behind the block
    assert not occluded(small, front, near).any()
    assert occluded(small, front, far).all()
    assert not occluded(small, front, front[None] + [[0.0, 5.0, 0.0]]).any()


def test_camera_poses_are_street_level(small):
    cam = street_camera()
    poses = camera_poses(small, np.random.default_rng(0), 3, cam)
    again = camera_poses(small, np.random.default_rng(0), 3, cam)
    for T, T2 in zip(poses, again, strict=True):
        np.testing.assert_array_equal(T, T2)
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        c = camera_center(T)
        assert 1.5 <= c[2] <= 2.0
        assert not np.any(np.all((c > small.blocks[:, 0] - 1) & (c < small.blocks[:, 1] + 1), axis=1))
        assert abs(np.degrees(np.arcsin(T[2, 2]))) < 20.0  # slight pitch: optical axis near horizontal
        assert len(project_building(small, cam, T)[0]) >= 60


def test_building_scene_true_matches_project(small):
    noise = 1.0
    scene = building_scene(np.random.default_rng(2), num_distractors=30, noise_px=noise, config=SMALL)
    i, j = scene.true_matches.T
    n_edges = len(scene.lines3d) - 30
    assert j.max() < n_edges  # distractors are map-only
    proj, visible = project_segments(scene.lines3d[j], scene.camera, scene.cam_from_world, 0.1)
    assert visible.all()
    H = line_coefficients(proj)
    ends = scene.lines2d[i].reshape(-1, 2, 2)
    dist = np.abs(np.einsum("kpc,kc->kp", ends, H[:, :2]) + H[:, 2:3])
    assert dist.max() < 5 * noise
    n = len(scene.lines2d)
    assert abs((n - len(i)) / n - 0.2) <= 1.0 / n
    assert len(np.unique(j)) < len(j)  # some edges are fragmented into several pieces
    # every true piece lies along its projected edge (partial, not extended)
    d = proj[:, 2:] - proj[:, :2]
    length = np.linalg.norm(d, axis=1)[:, None]
    s = np.einsum("kpc,kc->kp", ends - proj[:, None, :2], d) / length  # pixels along the projected edge
    assert np.all((s > -5 * noise) & (s < length + 5 * noise))


def test_building_scene_is_deterministic():
    a = building_scene(np.random.default_rng(9), config=SMALL)
    b = building_scene(np.random.default_rng(9), config=SMALL)
    np.testing.assert_array_equal(a.lines2d, b.lines2d)
    np.testing.assert_array_equal(a.true_matches, b.true_matches)
