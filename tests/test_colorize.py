"""Colorization (issue 12): a point takes its colour only from photos that see it; streamed files; batch runs."""

import json

import cv2
import numpy as np
import pytest

import linereg
from linereg.cli import main
from linereg.color.blend import Observation
from linereg.color.config import ColorizeConfig, GainConfig
from linereg.color.gains import estimate_gains
from linereg.geometry import make_cam_from_world

CAMERA = linereg.Camera(fx=300.0, fy=300.0, cx=79.5, cy=59.5, width=160, height=120)
RED, GREEN, BLUE = (0, 0, 255), (0, 255, 0), (255, 0, 0)  # BGR, as photos are read


def grid(x0, x1, y0, y1, z, step=0.05) -> np.ndarray:
    """Returns (P, 3) points of the rectangle [x0, x1] x [y0, y1] at depth z (a wall facing -z)."""
    x, y = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.c_[x.ravel(), y.ravel(), np.full(x.size, z)]


def look_from(centre) -> np.ndarray:
    """Returns the cam_from_world of a camera at ``centre`` looking along +z (no rotation)."""
    return make_cam_from_world(np.eye(3), -np.asarray(centre, dtype=np.float64))


def paint(camera, cam_from_world, regions) -> np.ndarray:
    """Returns a BGR photo: each (points, colour) region's points projected and dilated, in order."""
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for points, colour in regions:
        cam = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        u = np.rint(camera.fx * cam[:, 0] / cam[:, 2] + camera.cx).astype(int)
        v = np.rint(camera.fy * cam[:, 1] / cam[:, 2] + camera.cy).astype(int)
        ok = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        mask = np.zeros(image.shape[:2], np.uint8)
        mask[v[ok], u[ok]] = 1
        image[cv2.dilate(mask, np.ones((3, 3), np.uint8)) > 0] = colour
    return image


@pytest.fixture(scope="module")
def pillar_scene():
    """A wall at z = 10 m and a pillar 1 m wide at z = 5 m; photo 0 from the origin paints the pillar red
    and the wall green; photo 1, 2 m to the right, paints everything blue."""
    wall = grid(-4, 4, -2, 2, 10.0)
    pillar = grid(-0.5, 0.5, -2, 2, 5.0)
    points = np.r_[wall, pillar]
    poses = np.array([look_from([0, 0, 0]), look_from([2.0, 0, 0])])
    photos = [paint(CAMERA, poses[0], [(wall, GREEN), (pillar, RED)]),
              paint(CAMERA, poses[1], [(wall, BLUE), (pillar, BLUE)])]  # fmt: skip
    return points, len(wall), photos, poses


def test_colorize_returns_colours_and_counts_and_flags_unseen_points(pillar_scene):
    points, _, photos, poses = pillar_scene
    behind_camera = np.array([[0.0, 0.0, -5.0]])
    colors, seen = linereg.colorize(np.r_[points, behind_camera], photos, CAMERA, poses)
    assert colors.shape == (len(points) + 1, 3) and colors.dtype == np.uint8
    assert seen.shape == (len(points) + 1,) and seen[-1] == 0 and (colors[-1] == 0).all()
    assert seen.max() == 2 and (seen > 0).mean() > 0.5


def test_a_point_behind_the_pillar_never_takes_the_pillar_colour(pillar_scene):
    points, num_wall, photos, poses = pillar_scene
    colors, seen = linereg.colorize(points, photos, CAMERA, poses)
    wall, wall_colors = points[:num_wall], colors[:num_wall]
    shadow = (np.abs(wall[:, 0]) < 0.9) & (np.abs(wall[:, 1]) < 1.6)  # hidden from photo 0 by the pillar
    reddish = (wall_colors[:, 0] > 60) & (wall_colors[:, 0] > wall_colors[:, 2])  # RGB: red beats blue
    assert shadow.sum() > 500 and not reddish[shadow].any()
    assert (wall_colors[shadow & (seen[:num_wall] > 0), 2] > 150).all()  # photo 1 saw them: blue
    pillar_colors = colors[num_wall:][seen[num_wall:] > 0]  # photo 1 does not see the pillar
    assert len(pillar_colors) > 500 and (pillar_colors == [255, 0, 0]).all(axis=1).mean() > 0.95


def test_exposure_gains_are_recovered_from_shared_points():
    rng = np.random.default_rng(0)
    albedo = rng.uniform(40, 200, size=(20_000, 3))
    truth = np.array([[1.0, 1.0, 1.0], [0.7, 0.8, 0.9], [1.25, 1.1, 1.0]])
    observations = []
    for gain in truth:
        rows = np.flatnonzero(rng.random(len(albedo)) < 0.8)
        rgb = (albedo[rows] * gain + rng.normal(0, 2, (len(rows), 3))).astype(np.float32)
        observations.append(Observation(rows, rgb, np.ones(len(rows), np.float32)))
    gains = estimate_gains(observations, len(albedo), GainConfig())
    ratio = (gains / gains[0]) / truth
    assert np.abs(ratio - 1.0).max() < 0.03


def test_bad_inputs_are_named(pillar_scene):
    points, _, photos, poses = pillar_scene
    with pytest.raises(linereg.InvalidInputError, match="no points"):
        linereg.colorize(np.zeros((0, 3)), photos, CAMERA, poses)
    with pytest.raises(linereg.InvalidInputError, match=r"photos\[1\]: 80x60 px"):
        linereg.colorize(points, [photos[0], photos[1][::2, ::2]], CAMERA, poses)
    with pytest.raises(linereg.InvalidInputError, match="2 poses for 1 photos"):
        linereg.colorize(points, photos[:1], CAMERA, poses)


# --- files: chunked PLY / LAS, the CLI, the batch runners ---


@pytest.fixture(scope="module")
def files(pillar_scene, tmp_path_factory):
    """The pillar scene on disk: cloud.ply (float32), cloud.laz, camera.json, photos, poses.json."""
    laspy = pytest.importorskip("laspy")
    points, _, photos, poses = pillar_scene
    folder = tmp_path_factory.mktemp("colorize")
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    (folder / "cloud.ply").write_bytes(header.encode() + points.astype("<f4").tobytes())
    las_header = laspy.LasHeader(point_format=1, version="1.2")
    las_header.scales, las_header.offsets = [0.001] * 3, np.floor(points.min(axis=0))
    las = laspy.LasData(las_header)
    las.x, las.y, las.z = points.T
    las.intensity = np.arange(len(points)) % 1000
    las.write(folder / "cloud.laz")
    (folder / "camera.json").write_text(json.dumps(CAMERA.to_dict()))
    records = {}
    for k, (photo, pose) in enumerate(zip(photos, poses, strict=True)):
        cv2.imwrite(str(folder / f"photo{k}.png"), photo)
        records[f"photo{k}.png"] = {"success": True, "cam_from_world": pose.tolist()}
    records["lost.png"] = {"success": False, "reason": "not localized"}  # skipped: no pose
    (folder / "poses.json").write_text(json.dumps(records))
    return folder


def read_ply(path) -> np.ndarray:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
             ("photo_count", "<u2")]  # fmt: skip
    return np.frombuffer(data[end:], dtype=dtype)


def colorize_args(files, out, *extra):
    return ["colorize", files / "cloud.ply", "--poses", files / "poses.json", "--camera", files / "camera.json",
            "--images", files, "-o", out, *extra]  # fmt: skip


def test_cli_colours_a_ply_in_chunks_like_the_api(pillar_scene, files, tmp_path, capsys):
    points, _, photos, poses = pillar_scene
    (tmp_path / "small_chunks.json").write_text(json.dumps({"chunk_points": 2500}))
    argv = colorize_args(files, tmp_path / "out.ply", "--config", tmp_path / "small_chunks.json")
    assert main([str(a) for a in argv]) == 0
    rows = read_ply(tmp_path / "out.ply")
    config = ColorizeConfig(chunk_points=2500)
    colors, seen = linereg.colorize(
        points.astype(np.float32).astype(np.float64), photos, CAMERA, poses, config
    )
    assert len(rows) == len(points)
    np.testing.assert_array_equal(rows["photo_count"], seen)
    np.testing.assert_array_equal(np.c_[rows["red"], rows["green"], rows["blue"]], colors)
    assert "seen by no photo" in capsys.readouterr().err


def test_cli_keeps_las_dimensions_and_adds_rgb_and_count(files, tmp_path):
    laspy = pytest.importorskip("laspy")
    argv = colorize_args(files, tmp_path / "out.laz")
    argv[1] = files / "cloud.laz"
    assert main([str(a) for a in argv]) == 0
    source, out = laspy.read(files / "cloud.laz"), laspy.read(tmp_path / "out.laz")
    np.testing.assert_array_equal(out.X, source.X)
    np.testing.assert_array_equal(out.intensity, source.intensity)
    count = np.asarray(out["photo_count"])
    assert (count > 0).any() and (count == 0).any()
    assert (np.asarray(out.red)[count == 0] == 0).all() and (np.asarray(out.blue)[count > 0] > 0).any()


@pytest.mark.parametrize(
    ("case", "named"),
    [
        ("missing photo", "poses.json"),
        ("photo size", "photo1.png"),
        ("empty cloud", "empty.ply"),
        ("missing folder", "nowhere"),
    ],
)
def test_cli_bad_input_is_one_line_naming_the_file_and_writes_nothing(files, tmp_path, capsys, case, named):
    argv = colorize_args(files, tmp_path / "out.ply")
    if case == "missing photo":
        argv[argv.index("--images") + 1] = tmp_path  # the photos are not here
        (tmp_path / "poses.json").write_text((files / "poses.json").read_text())
        argv[argv.index("--poses") + 1] = tmp_path / "poses.json"
    elif case == "photo size":
        for name in ("photo0.png", "photo1.png"):
            image = cv2.imread(str(files / name))
            cv2.imwrite(str(tmp_path / name), image if name == "photo0.png" else image[::2, ::2])
        argv[argv.index("--images") + 1] = tmp_path
    elif case == "empty cloud":
        header = "ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
        (tmp_path / "empty.ply").write_text(header + "property float y\nproperty float z\nend_header\n")
        argv[1] = tmp_path / "empty.ply"
    else:
        argv[argv.index("-o") + 1] = tmp_path / "nowhere" / "out.ply"
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and named in err and "Traceback" not in err, err
    assert not (tmp_path / "out.ply").exists()
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_failing_run_leaves_no_half_written_file(files, tmp_path, monkeypatch):
    import linereg.color.engine as engine

    calls = []

    def dies(shared, item):
        if calls:
            raise KeyboardInterrupt  # killed in the middle of the colour pass
        calls.append(item)
        return real(shared, item)

    real = engine.colour_task
    monkeypatch.setattr(engine, "colour_task", dies)
    (tmp_path / "c.json").write_text(json.dumps({"chunk_points": 2000}))
    argv = colorize_args(files, tmp_path / "out.ply", "--config", tmp_path / "c.json")
    assert main([str(a) for a in argv]) == 130  # the CLI's answer to an interrupt
    assert list(tmp_path.iterdir()) == [tmp_path / "c.json"]


def test_colorize_on_a_dask_cluster_gives_the_local_answer(files, tmp_path):
    distributed = pytest.importorskip("distributed")
    from linereg import batch
    from linereg.colorization import colorize_file, read_localized_photos

    photos = read_localized_photos(files / "poses.json", files / "camera.json", files)
    config = ColorizeConfig(chunk_points=3000)
    local = colorize_file(files / "cloud.ply", tmp_path / "local.ply", photos, config)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        with batch.runner(scheduler=cluster.scheduler_address) as runner:
            assert runner.workers == 2
            remote = colorize_file(files / "cloud.ply", tmp_path / "dask.ply", photos, config, runner)
    np.testing.assert_array_equal(local, remote)
    assert (tmp_path / "local.ply").read_bytes() == (tmp_path / "dask.ply").read_bytes()


@pytest.mark.parametrize("cloud", ["cloud.ply", "cloud.laz"])
def test_process_pool_gives_the_inline_answer(files, tmp_path, cloud):
    # LAZ: workers fork from a parent that has read the file (lazrs' thread pool must not be inherited)
    from linereg import batch
    from linereg.colorization import colorize_file, read_localized_photos

    photos = read_localized_photos(files / "poses.json", files / "camera.json", files)
    config = ColorizeConfig(chunk_points=3000)
    colorize_file(files / cloud, tmp_path / "a.ply", photos, config)
    with batch.runner(workers=2, fork=False) as runner:
        colorize_file(files / cloud, tmp_path / "b.ply", photos, config, runner)
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def test_fill_gaps_closes_holes_in_an_occluder_but_keeps_its_edge():
    from linereg.color.config import VisibilityConfig
    from linereg.color.depth import fill_gaps

    depth = np.full((40, 40), 20.0, np.float32)  # a far wall
    depth[:, :20] = 5.0  # an occluder over the left half
    depth[10, 8] = depth[20:22, 5:15] = 20.0  # a hole and a 2 px stripe of scan-line gaps in it
    filled = fill_gaps(depth, VisibilityConfig())
    assert (filled[:, :20] == 5.0).all()
    assert (filled[:, 20:] == 20.0).all()  # the wall right beside the occluder's edge stays visible


def test_square_splats_lie_in_the_tangent_plane():
    from linereg.color.config import VisibilityConfig
    from linereg.color.depth import SplatLayout, crop, depth_slope, finish, splat

    layout = SplatLayout.for_camera(CAMERA, VisibilityConfig())
    normal = np.array([[np.sin(0.6), 0.0, -np.cos(0.6)]], np.float32)  # a plane turned 0.6 rad about y
    u, v, z = (np.array([x], np.float32) for x in (80.0, 60.0, 10.0))
    slope = depth_slope(normal, u, v, z, CAMERA, max_slope=1.5)
    buffer = layout.empty()
    splat(buffer, layout, u, v, z, np.array([3.0], np.float32), slope)
    row = crop(finish(buffer, layout))[60, 79:82]
    # the plane n . X = n . P met by the rays of pixels 79..81
    x = (np.arange(79, 82) - CAMERA.cx) / CAMERA.fx
    p = z[0] * np.array([(80.0 - CAMERA.cx) / CAMERA.fx, (60.0 - CAMERA.cy) / CAMERA.fy, 1.0])
    truth = normal[0] @ p / (normal[0, 0] * x + normal[0, 1] * (60.0 - CAMERA.cy) / CAMERA.fy + normal[0, 2])
    np.testing.assert_allclose(row, truth, atol=2e-3)


def test_behind_keeps_a_slanted_plane_level_and_sees_a_nearer_pixel_in_the_footprint():
    from linereg.color.depth import behind_m

    # a plane whose depth grows 0.2 m per column: each pixel centre holds the plane's depth there
    cols = np.arange(CAMERA.width, dtype=np.float32)
    depth = np.broadcast_to(10.0 + 0.2 * (cols - 80.0), (CAMERA.height, CAMERA.width)).copy()
    u = np.array([40.3, 80.7, 120.0], np.float32)
    v = np.array([30.2, 60.0, 90.4], np.float32)
    z = (10.0 + 0.2 * (u - 80.0)).astype(np.float32)
    slope = np.array([[0.2, 0.0]] * 3, np.float32)
    radius = np.array([1, 1, 2], np.int64)
    np.testing.assert_allclose(behind_m(depth, u, v, z, slope, radius), 0.0, atol=1e-4)
    depth[62, 82] -= 1.0  # a nearer surface 2 px from the second point, 1 px from nothing else
    behind = behind_m(depth, u, v, z, slope, np.array([1, 2, 2], np.int64))
    np.testing.assert_allclose(behind, [0.0, 1.0, 0.0], atol=1e-4)
    assert behind_m(depth, u[:0], v[:0], z[:0], slope[:0], radius[:0]).shape == (0,)


def sampled(x0, x1, y0, y1, z, spacing, rng) -> np.ndarray:
    """Returns (P, 3) points scattered at random over [x0, x1] x [y0, y1] at depth z (~1 per spacing^2),
    with 5 mm of range noise: the irregular sampling of a scan."""
    n = int((x1 - x0) * (y1 - y0) / spacing**2)
    return np.c_[rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), z + rng.normal(0.0, 0.005, n)]


def test_no_point_behind_an_occluder_is_coloured_at_range():
    # a far wall at 60 m seen head-on; before it a wall at 30 m crossing the image's left border and a
    # panel 0.15 m in front of the far wall; every surface sparse (splats ~1.5 px) and irregular
    rng = np.random.default_rng(3)
    far = sampled(-20, 20, -15, 15, 60.0, 0.3, rng)
    occluder = sampled(-10, -2, -3, 3, 30.0, 0.15, rng)
    panel = sampled(4, 8, -3, 3, 59.85, 0.3, rng)
    points = np.r_[far, occluder, panel]
    photo = np.full((CAMERA.height, CAMERA.width, 3), 128, np.uint8)
    _, seen = linereg.colorize(points, [photo], CAMERA, look_from([0, 0, 0])[None])
    seen_far = seen[: len(far)]
    u = CAMERA.fx * far[:, 0] / far[:, 2] + CAMERA.cx
    v = CAMERA.fy * far[:, 1] / far[:, 2] + CAMERA.cy

    def behind(x0, x1, y0, y1, z, inset_px):  # the far points inside a rectangle's silhouette, inset
        px = CAMERA.fx / z
        return (
            (u > x0 * px + CAMERA.cx + inset_px) & (u < x1 * px + CAMERA.cx - inset_px)
            & (v > y0 * px + CAMERA.cy + inset_px) & (v < y1 * px + CAMERA.cy - inset_px)
        )  # fmt: skip

    # a surface sampled every 1.5 px has its outline known to ~1.5 px: the hidden points are those 2 px
    # inside the silhouettes
    hidden = behind(-10, -2, -3, 3, 30.0, 2.0) | behind(4, 8, -3, 3, 59.85, 2.0)
    clear = ~behind(-10, -2, -3, 3, 30.0, -2.0) & ~behind(4, 8, -3, 3, 59.85, -2.0)
    inside = (u > 0) & (u < CAMERA.width - 1) & (v > 0) & (v < CAMERA.height - 1)
    assert hidden.sum() > 1000 and (hidden & (u < 1.5)).sum() > 20  # the occluder reaches the border
    assert (seen_far[hidden] == 0).all(), f"{(seen_far[hidden] > 0).sum()} points coloured through"
    assert (seen_far[clear & inside] > 0).mean() > 0.9
    front = points[len(far) :]
    in_image = np.abs(CAMERA.fx * front[:, 0] / front[:, 2]) < CAMERA.cx - 1.0
    assert (seen[len(far) :][in_image] > 0).mean() > 0.9  # the occluders themselves are seen


def test_a_script_without_a_main_guard_is_told_why_its_pool_broke(tmp_path):
    import subprocess
    import sys

    work = "with batch.runner(2, fork=False) as run:\n    print(sorted(run.unordered(operator.add, 1, [1, 2])))\n"
    guarded = "if __name__ == '__main__':\n" + "".join(f"    {line}\n" for line in work.splitlines())
    answers = {}
    for name, body in (("bare", work), ("guarded", guarded)):
        (tmp_path / f"{name}.py").write_text("import operator\n\nfrom linereg import batch\n\n" + body)
        answers[name] = subprocess.run(
            [sys.executable, str(tmp_path / f"{name}.py")], capture_output=True, text=True, timeout=120
        )
    assert answers["guarded"].returncode == 0 and "[(0, 2), (1, 3)]" in answers["guarded"].stdout
    assert answers["bare"].returncode != 0 and 'if __name__ == "__main__":' in answers["bare"].stderr


def test_a_point_behind_a_thin_pillar_is_never_coloured_by_the_photo_it_hides_from():
    # a pillar 0.4 m wide (8 px) at 15 m, 1 m before a wall; both sampled at random (~1.5 px apart on
    # the pillar), so the pillar's outline and its inside have holes between splats
    rng = np.random.default_rng(5)
    wall = sampled(-3, 3, -2.5, 2.5, 16.0, 0.06, rng)
    pillar = sampled(-0.2, 0.2, -2.5, 2.5, 15.0, 0.075, rng)
    photo = np.full((CAMERA.height, CAMERA.width, 3), 128, np.uint8)
    _, seen = linereg.colorize(np.r_[wall, pillar], [photo], CAMERA, look_from([0, 0, 0])[None])
    u = CAMERA.fx * wall[:, 0] / wall[:, 2] + CAMERA.cx
    half = 0.2 * CAMERA.fx / 15.0  # the pillar's half width, px
    hidden = np.abs(u - CAMERA.cx) < half - 1.0  # rays through the pillar a pixel inside its outline
    assert hidden.sum() > 300
    assert (seen[: len(wall)][hidden] == 0).all(), f"{(seen[: len(wall)][hidden] > 0).sum()} coloured through"
    assert (seen[: len(wall)][np.abs(u - CAMERA.cx) > half + 2.0] > 0).mean() > 0.9


def test_a_recess_seen_at_a_slant_is_not_coloured_through_the_wall_edge_before_it():
    # a facade at 30 m turned 50 degrees about y, the camera on its side, and beyond its edge the
    # recessed panel of a window 0.1 m deep: the edge hides a strip of the recess ~1 px wide, whose
    # points lie 0.16 m behind the facade along their rays (a flat test with a pixel of slope let them
    # through)
    rng = np.random.default_rng(7)
    angle = np.deg2rad(-50.0)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    # facade frame: x along the facade (its edge at 0), z into the wall (the recess at z = 0.1)
    local = np.r_[sampled(-4.0, 0.0, -2, 2, 0.0, 0.03, rng), sampled(0.0, 3.0, -2, 2, 0.1, 0.03, rng)]
    points = local @ R.T + [0.0, 0.0, 30.0]
    photo = np.full((CAMERA.height, CAMERA.width, 3), 128, np.uint8)
    _, seen = linereg.colorize(points, [photo], CAMERA, look_from([0, 0, 0])[None])
    eye = R.T @ [0.0, 0.0, -30.0]  # the camera in the facade frame
    crossing = eye[0] + (local[:, 0] - eye[0]) * eye[2] / (eye[2] - local[:, 2])  # ray meets z = 0
    pixel_m = 30.0 / CAMERA.fx / np.cos(angle)  # a pixel's width on the facade
    recess = local[:, 2] > 0.05
    hidden = recess & (crossing < -0.5 * pixel_m)  # behind the facade, half a pixel inside its edge
    assert hidden.sum() > 100
    assert (seen[hidden] == 0).all(), f"{(seen[hidden] > 0).sum()} of {hidden.sum()} coloured through"
    assert (seen[recess & (crossing > 3.0 * pixel_m)] > 0).mean() > 0.9  # the slanted recess sees itself


def test_a_point_half_a_spacing_beyond_an_occluders_last_splat_is_hidden():
    # a wall at 30 m and a wall behind it at 60 m, both sampled on grids 2.9 px apart; the near wall's
    # outline lies 0.99 of a spacing beyond its last column of samples, whose splats (3 px wide) stop
    # ~1.5 px short of it: far points in between are hidden, and the test reaches them
    s = 2.9 * 30.0 / CAMERA.fx  # 2.9 px at 30 m
    u_last = 100.45  # the near wall's last column, px
    x_last = (u_last - CAMERA.cx) * 30.0 / CAMERA.fx
    x_edge = x_last + 0.99 * s
    cols = x_last - s * np.arange(40)
    rows = np.arange(-3.0, 3.0, s)
    near = np.c_[np.repeat(cols, len(rows)), np.tile(rows, len(cols)), np.full(len(cols) * len(rows), 30.0)]
    far_cols = 2.0 * (x_last + s * np.arange(-30, 30) + 0.8 * s)  # one column 0.8 spacing beyond the last
    far_rows = np.arange(-9.0, 9.0, 2.0 * s)
    far = np.c_[
        np.repeat(far_cols, len(far_rows)),
        np.tile(far_rows, len(far_cols)),
        np.full(far_cols.size * far_rows.size, 60.0),
    ]
    photo = np.full((CAMERA.height, CAMERA.width, 3), 128, np.uint8)
    _, seen = linereg.colorize(np.r_[far, near], [photo], CAMERA, look_from([0, 0, 0])[None])
    crossing = far[:, :2] / 2.0  # where a far point's ray crosses z = 30
    inside_rows = np.abs(crossing[:, 1]) < 2.5
    hidden = inside_rows & (crossing[:, 0] < x_edge - 0.1 * s)
    assert (hidden & (crossing[:, 0] > x_last + 0.5 * s)).sum() >= 5
    assert (seen[: len(far)][hidden] == 0).all(), f"{(seen[: len(far)][hidden] > 0).sum()} coloured through"
    clear = crossing[:, 0] > x_edge + 3.0 * s / 2.9
    u = CAMERA.fx * far[:, 0] / 60.0 + CAMERA.cx
    assert (seen[: len(far)][clear & (u < CAMERA.width - 3)] > 0).mean() > 0.9


def test_the_compiled_view_pass_equals_the_numpy_functions_bit_for_bit():
    from linereg.color.config import VisibilityConfig
    from linereg.color.project import view_points

    rng = np.random.default_rng(11)
    points = rng.uniform([-30, -20, -5], [30, 20, 60], (20_000, 3)) + np.array([4.0e5, 5.0e6, 0.0])  # UTM
    normals = rng.normal(size=(len(points), 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[::7] = np.nan  # unknown normals
    spacing = rng.uniform(0.01, 0.3, len(points)).astype(np.float32)
    angle = 0.3
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    pose = make_cam_from_world(R, -R @ [4.0e5, 5.0e6, -10.0])
    rows = np.flatnonzero(rng.random(len(points)) < 0.8)
    for margin in (0.0, 8.5):
        args = (points, normals, spacing, CAMERA, pose, VisibilityConfig(), rows, margin)
        compiled, reference = view_points(*args), view_points(*args, compiled=False)
        assert len(compiled.index) > 1000
        for name in ("index", "u", "v", "z", "diameter", "slope", "distance", "cos"):
            assert np.array_equal(getattr(compiled, name), getattr(reference, name)), name


def test_voxel_statistics_by_hash_equal_those_by_sorting():
    from linereg.color.surface import _voxel_statistics

    rng = np.random.default_rng(12)
    points = np.r_[rng.uniform(0, 5, (5000, 3)), rng.uniform(0, 5, (50, 3)) * [1, 1, 0]] + [
        4.0e5,
        5.0e6,
        30.0,
    ]
    spacing, normals, count = _voxel_statistics(points, 0.7)
    # the same statistics by np.unique and np.bincount
    cell = np.floor(points / 0.7)
    local = points - cell * 0.7
    cell -= cell.min(axis=0)
    dims = cell.max(axis=0) + 1.0
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    mean = np.stack([np.bincount(inverse, weights=local[:, i]) for i in range(3)], 1) / counts[:, None]
    cov = np.empty((len(counts), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            s = np.bincount(inverse, weights=local[:, i] * local[:, j]) / counts
            cov[:, i, j] = cov[:, j, i] = s - mean[:, i] * mean[:, j]
    _, vectors = np.linalg.eigh(cov)
    expected = vectors[:, :, 0].astype(np.float32)[inverse]
    expected[counts[inverse] < 3] = np.nan
    assert np.array_equal(count, counts[inverse])
    assert np.array_equal(normals, expected, equal_nan=True)
    assert spacing.dtype == np.float32 and np.isfinite(spacing).all()


def test_a_point_is_seen_only_if_it_passes_with_the_shifted_grids_normal_too():
    # a wall at 10 m facing the camera; a second estimate of the normals (the voxel grid shifted by half a
    # voxel) that agrees leaves the observation as it is, one that calls every other point's surface seen
    # edge-on (a voxel holding two faces) takes exactly those points out
    from linereg.batch import InlineRunner
    from linereg.color.blend import Photo, observe
    from linereg.color.engine import ArraySource, View, chunk_geometry, depth_pass, make_plan

    rng = np.random.default_rng(13)
    points = sampled(-3, 3, -2, 2, 10.0, 0.05, rng)
    pose = look_from([0, 0, 0])
    config = ColorizeConfig()
    plan = make_plan(ArraySource(points), config)
    (depth,), _ = depth_pass(ArraySource(points), [View(CAMERA, pose)], plan, InlineRunner())
    spacing, normals = chunk_geometry(points, plan)
    photo = Photo(np.full((CAMERA.height, CAMERA.width, 3), 128, np.uint8), CAMERA, pose)
    alone = observe(photo, depth, points, spacing, normals, config)
    assert len(alone.index) > 0.8 * len(points)  # the wall reaches past the image's sides
    same = observe(photo, depth, points, spacing, normals, config, check_normals=normals)
    assert np.array_equal(same.index, alone.index) and np.array_equal(same.weight, alone.weight)
    edge_on = normals.copy()
    along = np.cross(points[::2], [0.0, 1.0, 0.0])  # at right angles to the ray: seen along the surface
    edge_on[::2] = along / np.linalg.norm(along, axis=1, keepdims=True)
    checked = observe(photo, depth, points, spacing, normals, config, check_normals=edge_on)
    odd = alone.index % 2 == 1
    assert np.array_equal(checked.index, alone.index[odd])
    assert np.array_equal(checked.weight, alone.weight[odd])  # weighted by the grid's own normals
