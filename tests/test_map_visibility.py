"""Occlusion-aware visibility of map segments: visible parts and potentially-visible sets against a
brute-force ray test on a synthetic scene (a box in front of a wall)."""

import numpy as np
import pytest
from conftest import look_at
from plain_visibility import clip_image, clip_near, in_pyramid, samples

from linereg.camera import Camera
from linereg.errors import InvalidInputError
from linereg.map.linemap import LineMap
from linereg.map.surfaces import make_surfaces, raster_mesh, raster_rectangles

CAMERA = Camera(fx=400.0, fy=400.0, cx=319.5, cy=239.5, width=640, height=480)


def quad_triangles(corners):
    """Returns ((4, 3) vertices, (2, 3) triangles) of a rectangle given by its 4 corners in order."""
    return np.asarray(corners, float), np.array([[0, 1, 2], [0, 2, 3]])


def box_faces(lo, hi):
    """Returns the 6 faces of an axis-aligned box as lists of 4 corners."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    return [
        [(x0, y0, z0), (x0, y1, z0), (x0, y1, z1), (x0, y0, z1)],
        [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)],
        [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],
        [(x0, y1, z0), (x1, y1, z0), (x1, y1, z1), (x0, y1, z1)],
        [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0)],
        [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)],
    ]


def scene():
    """Returns (segments (M, 6), faces list of 4 corners): a wall at x = 10 with its edges and a grid of
    lines on it, a box (x 6..7, y -1..1, z 0..1.5) in front with its edges."""
    wall = [(10, -5, 0), (10, 5, 0), (10, 5, 3), (10, -5, 3)]
    segs = [[*wall[k], *wall[(k + 1) % 4]] for k in range(4)]
    segs += [[10, y, 0.2, 10, y, 2.8] for y in np.linspace(-4, 4, 9)]  # vertical lines on the wall
    segs += [[10, -4.5, z, 10, 4.5, z] for z in (0.5, 1.0, 2.0)]
    lo, hi = np.array([6.0, -1, 0]), np.array([7.0, 1, 1.5])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    for i in range(8):
        for j in range(i + 1, 8):
            if np.sum(corners[i] != corners[j]) == 1:
                segs.append([*corners[i], *corners[j]])
    return np.array(segs, float), [wall, *box_faces(lo, hi)]


def mesh(faces):
    """Returns ((4 F, 3) vertices, (2 F, 3) triangles) of F rectangles."""
    vertices = np.concatenate([quad_triangles(f)[0] for f in faces])
    triangles = np.concatenate([quad_triangles(f)[1] + 4 * k for k, f in enumerate(faces)])
    return vertices, triangles


def hits_before(origin, points, faces, tol):
    """Returns (S,) bool: does the segment origin -> point cross one of the rectangles before
    ``tol`` short of the point (brute force, exact)?"""
    hidden = np.zeros(len(points), bool)
    d = points - origin
    dist = np.linalg.norm(d, axis=1)
    for f in faces:
        c = np.asarray(f, float)
        e1, e2 = c[1] - c[0], c[3] - c[0]
        n = np.cross(e1, e2)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((c[0] - origin) @ n) / denom
        x = origin + t[:, None] * d
        a = (x - c[0]) @ e1 / (e1 @ e1)
        b = (x - c[0]) @ e2 / (e2 @ e2)
        inside = (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1) & (t > 0)
        hidden |= inside & (t * dist < dist - tol)
    return hidden


@pytest.fixture(scope="module")
def line_map():
    segs, faces = scene()
    return LineMap.from_segments(segs, surfaces=mesh(faces)), faces


def brute_visible(segments, faces, cam_from_world, step=0.01):
    """Returns per segment (n,) bool samples and their (n, 3) positions: in front, in the image, not hidden."""
    centre = -cam_from_world[:3, :3].T @ cam_from_world[:3, 3]
    out = []
    for s in segments:
        n = max(2, int(np.linalg.norm(s[3:] - s[:3]) / step))
        p = s[:3] + np.linspace(0, 1, n)[:, None] * (s[3:] - s[:3])
        x = p @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = CAMERA.fx * x[:, 0] / x[:, 2] + CAMERA.cx, CAMERA.fy * x[:, 1] / x[:, 2] + CAMERA.cy
        ok = (
            (x[:, 2] > 0.05)
            & (u >= -0.5)
            & (u <= CAMERA.width - 0.5)
            & (v >= -0.5)
            & (v <= CAMERA.height - 0.5)
        )
        dist = np.linalg.norm(p - centre, axis=1)
        ok &= ~hits_before(centre, p, faces, 0.05 + 0.02 * dist)
        out.append((ok, p))
    return out


def covered(parts, rows, k, p, radius=0.03):
    """Returns (n,) bool: which points p of segment k lie within radius of one of its visible parts."""
    mine = parts[rows == k]
    if len(mine) == 0:
        return np.zeros(len(p), bool)
    a, d = mine[:, :3], mine[:, 3:] - mine[:, :3]
    w = p[:, None] - a[None]
    t = np.clip(np.einsum("pmk,mk->pm", w, d) / np.maximum(np.einsum("mk,mk->m", d, d), 1e-12), 0, 1)
    return (np.linalg.norm(w - t[..., None] * d[None], axis=2) <= radius).any(axis=1)


def test_visible_parts_match_brute_force(line_map, rng):
    lm, faces = line_map
    disagree, total, hidden_some = 0, 0, False
    for _ in range(8):
        centre = rng.uniform([0.0, -3, 0.3], [4.0, 3, 2.5])
        cam = look_at(centre, np.array([10.0, 0, 1.2]) + rng.normal(0, 0.5, 3))
        parts, rows = lm.visible_parts(CAMERA, cam)
        assert parts.shape[1] == 6 and parts.dtype == np.float64 and rows.dtype == np.int64
        for k, (ok, p) in enumerate(brute_visible(lm.segments, faces, cam)):
            got = covered(parts, rows, k, p)
            # samples near a visibility change may fall either way (samples every 3 px)
            boundary = np.convolve(np.diff(ok.astype(int)) != 0, np.ones(25), "same") > 0
            boundary = np.r_[boundary, False] | np.r_[False, boundary]
            disagree += int((got != ok)[~boundary].sum())
            total += len(ok)
            hidden_some |= bool((~ok).any() and ok.any())
    assert hidden_some  # the box does hide parts of the wall's lines
    assert disagree <= 0.005 * total


def test_segments_on_surfaces_are_not_self_occluded():
    segs, faces = scene()
    wall_only = LineMap.from_segments(segs, surfaces=mesh(faces[:1]))
    cam = look_at(np.array([2.0, 4.0, 2.5]), np.array([10.0, 3.0, 1.5]))
    parts, rows = wall_only.visible_parts(CAMERA, cam, index=np.arange(4))  # the wall's own outline
    lengths = np.bincount(rows, np.linalg.norm(parts[:, 3:] - parts[:, :3], axis=1), minlength=4)
    brute = brute_visible(segs[:4], [], cam)
    for k, (ok, _) in enumerate(brute):
        assert lengths[k] == pytest.approx(ok.mean() * np.linalg.norm(segs[k, 3:] - segs[k, :3]), abs=0.1)


def test_without_surfaces_it_is_the_frustum(line_map):
    lm, _ = line_map
    bare = LineMap.from_segments(lm.segments)
    assert bare.surfaces is None
    cam = look_at(np.array([2.0, 0.0, 1.0]), np.array([10.0, 0, 1.2]))
    parts, _ = bare.visible_parts(CAMERA, cam)
    hidden_parts, _ = lm.visible_parts(CAMERA, cam)
    length = np.linalg.norm(parts[:, 3:] - parts[:, :3], axis=1).sum()
    assert length > np.linalg.norm(hidden_parts[:, 3:] - hidden_parts[:, :3], axis=1).sum() + 1.0
    behind = look_at(np.array([12.0, 0, 1.0]), np.array([20.0, 0, 1.0]))
    assert len(bare.visible_parts(CAMERA, behind)[0]) == 0
    sub = bare.visible_parts(CAMERA, cam, index=np.array([0, 5]))[1]
    assert set(sub.tolist()) <= {0, 5}


def test_potentially_visible_never_misses(line_map, rng):
    lm, faces = line_map
    culled = 0
    for _ in range(12):
        lo = rng.uniform([2.0, -3, 0.2], [5.5, 2, 1.2])
        hi = lo + rng.uniform(0.2, 1.0, 3)
        pvs = lm.potentially_visible(lo, hi)
        assert np.all(np.diff(pvs) > 0)
        culled += len(lm) - len(pvs)
        for centre in rng.uniform(lo, hi, (6, 3)):
            for k, s in enumerate(lm.segments):
                p = s[:3] + np.linspace(0, 1, 200)[:, None] * (s[3:] - s[:3])
                seen = ~hits_before(centre, p, faces, 0.05 + 0.02 * np.linalg.norm(p - centre, axis=1))
                if seen.any():
                    assert k in pvs, (k, centre)
        again = lm.potentially_visible(lo, hi)  # a cached union: the same rows, not to be written to
        np.testing.assert_array_equal(again, pvs)
        assert not again.flags.writeable
    # from right behind the box, the wall's lines straight behind it are hidden from every point
    pvs = lm.potentially_visible([4.0, -0.3, 0.3], [5.0, 0.3, 0.6])
    assert len(pvs) < len(lm) and culled > 0


def test_potentially_visible_bad_box_and_no_surfaces(line_map):
    lm, _ = line_map
    with pytest.raises(InvalidInputError):
        lm.potentially_visible([1, 1, 1], [0, 0, 0])
    bare = LineMap.from_segments(lm.segments)
    np.testing.assert_array_equal(bare.potentially_visible([0, 0, 0], [1, 1, 1]), np.arange(len(lm)))


def test_rectangles_cover_the_raster_exactly(rng):
    image = rng.random((30, 40)) < 0.6
    rects = raster_rectangles(image)
    cover = np.zeros(image.shape, int)
    for c0, c1, r0, r1 in rects:
        cover[r0:r1, c0:c1] += 1
    np.testing.assert_array_equal(cover, image.astype(int))


def test_raster_mesh_is_a_plane_patch():
    image = np.zeros((10, 20), np.uint8)
    image[2:8, 3:15] = 255
    basis = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    surfaces = raster_mesh(image, np.array([0.0, 0.0]), 0.1, (np.array([0, 0, 5.0]), basis), 0.1)
    assert surfaces.area_m2() == pytest.approx(12 * 6 * 0.01)
    assert np.allclose(surfaces.world_vertices()[:, 2], 5.0)
    with pytest.raises(InvalidInputError):
        make_surfaces(np.zeros((3, 3)), np.array([[0, 1, 5]]))


def sampled_cloud(faces, spacing, offset):
    """Returns (P, 3) points on a grid of ``spacing`` over each rectangle of ``faces``, moved by ``offset``."""
    points = []
    for f in faces:
        c = np.asarray(f, float)
        e1, e2 = c[1] - c[0], c[3] - c[0]
        a = np.arange(0.0, 1.0 + 1e-9, spacing / np.linalg.norm(e1))
        b = np.arange(0.0, 1.0 + 1e-9, spacing / np.linalg.norm(e2))
        points.append((c[0] + a[:, None, None] * e1 + b[None, :, None] * e2).reshape(-1, 3))
    return np.concatenate(points) + offset


@pytest.fixture(scope="module")
def built_far_away():
    """A map built from a cloud of the scene far from the origin (georeferenced coordinates are)."""
    _, faces = scene()
    offset = np.array([651_000.0, 5_420_000.0, 312.0])
    cloud = sampled_cloud(faces, 0.05, offset)
    return LineMap.build(cloud), cloud, faces, offset


def test_built_surfaces_lie_on_the_cloud(built_far_away):
    """The mesh of a built map is in the map frame, on the cloud's planes, wherever the cloud lies."""
    from scipy.spatial import cKDTree

    line_map, cloud, _, _ = built_far_away
    assert line_map.surfaces is not None and len(line_map.surfaces) > 0
    v = line_map.surfaces.world_vertices()[line_map.surfaces.triangles].mean(axis=1)
    distance, _ = cKDTree(cloud).query(v)
    assert np.median(distance) < 0.1 and distance.max() < 0.5


def test_built_surfaces_hide_what_is_behind_them(built_far_away):
    """From in front of the box, the wall behind it is hidden; the wall beside it is not."""
    line_map, _, _, offset = built_far_away
    pose = look_at(offset + np.array([2.0, 0.0, 0.75]), offset + np.array([10.0, 0.0, 0.75]))
    behind = np.array([10.0, 0.0, 0.75]) + offset  # on the wall, straight behind the box
    beside = np.array([10.0, 3.5, 0.75]) + offset
    vis = line_map.visibility()
    seen = vis._unoccluded(np.stack([behind, beside]), -pose[:3, :3].T @ pose[:3, 3])
    assert not seen[0] and seen[1]


def test_version_2_maps_built_from_clouds_load_without_their_misplaced_surfaces(built_far_away, tmp_path):
    import json
    import zipfile
    from io import BytesIO

    line_map, *_ = built_far_away
    path, old = tmp_path / "map.npz", tmp_path / "v2.npz"
    line_map.save(path)
    with zipfile.ZipFile(path) as zin, zipfile.ZipFile(old, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "metadata.npy":
                meta = json.loads(str(np.load(BytesIO(data)))) | {"format_version": 2}
                buffer = BytesIO()
                np.save(buffer, np.array(json.dumps(meta)))
                data = buffer.getvalue()
            zout.writestr(item, data)
    assert LineMap.load(path).surfaces is not None
    loaded = LineMap.load(old)
    assert loaded.surfaces is None and len(loaded) == len(line_map)
    assert "misplaced" in loaded.info()["surfaces"]["note"]


def test_potentially_visible_keeps_what_the_ray_test_of_a_camera_in_the_box_shows():
    """A line 4 cm behind a wall's surface (a reveal, a mesh a cell off) is seen by the per-camera ray test
    (its tolerance grows with range); the set for a box holding that camera must not leave it out."""
    wall = [(10, -2, 0), (10, 2, 0), (10, 2, 3), (10, -2, 3)]
    segments = np.array([[10.04, 0.5, 0.5, 10.04, 0.5, 2.5], [9.0, -1.0, 0.5, 9.0, -1.0, 2.5]])
    line_map = LineMap.from_segments(segments, surfaces=quad_triangles(wall))
    centre = np.array([2.0, 0.0, 1.5])
    _, rows = line_map.visible_parts(CAMERA, look_at(centre, np.array([10.0, 0.0, 1.5])))
    assert 0 in rows  # the ray test shows it
    assert 0 in line_map.potentially_visible(centre - 0.25, centre + 0.25)
    far_behind = LineMap.from_segments(
        np.array([[10.5, 0.5, 0.5, 10.5, 0.5, 2.5]]), surfaces=quad_triangles(wall)
    )  # 0.5 m behind: hidden from everywhere in the box, by both tests
    assert len(far_behind.potentially_visible(centre - 0.25, centre + 0.25)) == 0


def test_the_surface_footprint_is_where_a_cells_ray_meets_a_surface(line_map):
    lm, faces = line_map
    cam = look_at(np.array([2.0, -2.0, 1.0]), np.array([10.0, 2.0, 1.8]))
    cell = 8.0
    got = lm.surface_footprint(CAMERA, cam, cell)
    assert got.shape == (60, 80) and got.dtype == bool
    # brute force: every cell's centre ray, 1000 m long, against the rectangles
    u = (np.arange(80) + 0.5) * cell - 0.5
    v = (np.arange(60) + 0.5) * cell - 0.5
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([(uu - CAMERA.cx) / CAMERA.fx, (vv - CAMERA.cy) / CAMERA.fy, np.ones_like(uu)], -1)
    centre = -cam[:3, :3].T @ cam[:3, 3]
    ends = (
        centre
        + 1000.0 * (rays.reshape(-1, 3) @ cam[:3, :3]) / np.linalg.norm(rays.reshape(-1, 3), axis=1)[:, None]
    )
    expected = hits_before(centre, ends, faces, 0.0).reshape(60, 80)
    assert expected.any() and not expected.all()  # the wall ends inside the view
    # rays grazing a rectangle's edge may fall either way (float32 in the ray caster)
    assert (got != expected).mean() < 0.01
    assert LineMap.from_segments(lm.segments).surface_footprint(CAMERA, cam, cell) is None


def test_the_pyramid_test_leaves_out_only_segments_the_exact_clipping_leaves_out(rng):
    """The pyramid test (the cheap first cut of ``visible_parts``' sampling) drops a segment only where the
    exact clipping to the near plane and the image finds no part of it in view, for random segments all
    round the camera (in front, behind, across the near plane), near and far."""
    near = 0.05
    for scale in (0.5, 5.0, 50.0):
        a, b = rng.normal(0.0, scale, (20000, 3)), rng.normal(0.0, scale, (20000, 3))
        kept = in_pyramid(a, b, CAMERA, near)
        t0, t1, ok = clip_near(a[:, 2], b[:, 2], near)
        _, _, ok = clip_image(a, b, t0, t1, ok, CAMERA)
        assert not (ok & ~kept).any()
        assert (~kept).sum() > 0.3 * len(a)  # it does cut: most random segments miss the view


def test_the_compiled_sampling_is_the_plain_rule_to_the_bit(rng):
    """``visibility._samples`` (the pyramid cut, the clipping, the samples of ``visible_parts`` in one
    compiled pass) returns what the plain numpy rule returns, array for array and bit for bit, for random
    segments all round the camera, across the near plane and the image border, short and long."""
    from linereg.map.visibility import _samples

    near = 0.05
    for scale in (0.5, 5.0, 50.0):
        world = rng.normal(0.0, scale, (5000, 6))
        cam = look_at(rng.normal(0.0, scale, 3), rng.normal(0.0, scale, 3))
        rows = np.sort(rng.choice(len(world), 4000, replace=False))
        R, t = cam[:3, :3], cam[:3, 3]
        a, b = world[rows, :3] @ R.T + t, world[rows, 3:] @ R.T + t
        got = _samples(
            world, rows, a, b, near, CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, 640.0, 480.0, 3.0, 4000
        )
        want = samples(world, rows, a, b, CAMERA, near, 3.0, 4000)
        assert len(want[0]) > 100  # some segments are in view
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)
