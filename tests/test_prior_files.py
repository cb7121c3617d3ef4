"""Priors from files (``linereg.prior_files``, ``linereg localize --prior``): every format finds each
image's prior, what a file leaves out is filled by --prior-sigma or named as missing, and a library prior
crosses the wire to the service unchanged."""

import json

import numpy as np
import pytest

from linereg import Prior
from linereg.errors import FileFormatError, InvalidInputError, LineregError
from linereg.geometry import camera_center, invert, make_cam_from_world
from linereg.io import write_tum
from linereg.prior_files import MAX_DT_S, read_priors


def some_pose(k: int) -> np.ndarray:
    """Returns a (4, 4) cam_from_world with a rotation about a tilted axis and a centre depending on k."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.1 * k, 0.4, -0.2]).as_matrix()
    return make_cam_from_world(R, -R @ np.array([k, 2.0 * k, 1.5]))


def write(path, obj) -> str:
    path.write_text(json.dumps(obj))
    return path


def test_one_json_prior_serves_every_image(tmp_path):
    table = read_priors(write(tmp_path / "site.json", {"position": [10, 20, 1.5], "radius_m": 30}))
    for image in ("a.png", "photos/b.jpg"):
        prior = table.for_image(image)
        assert prior.cam_from_world is None and prior.radius_m == 30
        np.testing.assert_array_equal(prior.position, [10, 20, 1.5])


@pytest.mark.parametrize("layout", ["dict", "list", "images"])
def test_json_priors_per_image_by_path_name_or_stem(tmp_path, layout):
    T0, T1 = some_pose(0), some_pose(1)
    records = {
        "img0.png": {"cam_from_world": T0.tolist(), "sigma_rot_deg": 3, "radius_m": 0.5},
        "img1": {"world_from_cam": invert(T1).tolist(), "sigma_rot_deg": 2, "sigma_pos_m": 0.1},
    }
    if layout == "dict":
        obj: object = records
    else:
        items = [{"image": name, **fields} for name, fields in records.items()]
        obj = items if layout == "list" else {"images": items}
    table = read_priors(write(tmp_path / "priors.json", obj))
    first, second = table.for_image("photos/img0.png"), table.for_image("other/img1.png")
    np.testing.assert_allclose(first.cam_from_world, T0, atol=1e-12)
    assert (first.sigma_rot_deg, first.radius_m) == (3, 0.5)
    np.testing.assert_allclose(second.cam_from_world, T1, atol=1e-12)  # world_from_cam inverted
    assert second.sigma_rot_deg == 2 and second.radius_m == pytest.approx(0.3)  # 3 sigma
    np.testing.assert_allclose(second.position, camera_center(T1), atol=1e-12)
    with pytest.raises(InvalidInputError, match=r"no prior for image img2\.png"):
        table.for_image("img2.png")


def test_prior_sigma_fills_what_a_json_prior_leaves_out(tmp_path):
    path = write(tmp_path / "p.json", {"a.png": {"cam_from_world": some_pose(2).tolist()}, "b.png": {
        "position": [1, 2, 3]}, "c.png": {"cam_from_world": some_pose(3).tolist(), "sigma_rot_deg": 1,
        "radius_m": 2}})  # fmt: skip
    with pytest.raises(FileFormatError, match=r"a\.png.*radius_m"):
        read_priors(path)  # a pose without a radius: named, with the key it lacks
    table = read_priors(path, (4.0, 0.7))
    a, b, c = (table.for_image(name) for name in ("a.png", "b.png", "c.png"))
    assert (a.sigma_rot_deg, a.radius_m) == (4.0, 0.7) and b.radius_m == 0.7
    assert (c.sigma_rot_deg, c.radius_m) == (1, 2)  # given values are kept


@pytest.mark.parametrize(
    ("obj", "problem"),
    [
        ({"position": [1, 2, 3], "radius": 5}, "unknown prior key"),
        ({"position": [1, 2], "radius_m": 5}, "3 finite numbers"),
        ({"position": [1, 2, 3], "radius_m": -1}, "positive"),
        ({"position": [1, 2, 3], "radius_m": "5"}, "must be a number"),
        (
            {"cam_from_world": np.eye(4).tolist(), "world_from_cam": np.eye(4).tolist(), "radius_m": 1},
            "not both",
        ),
        ({"cam_from_world": (2 * np.eye(4)).tolist(), "radius_m": 1}, "not rigid"),
        ({"a.png": {"position": [1, 2, float("nan")], "radius_m": 1}}, "finite"),
        ({"a.png": [1, 2, 3]}, "JSON object"),
        ([{"position": [1, 2, 3], "radius_m": 1}], "missing key 'image'"),
        ([], "no prior found"),
    ],
)
def test_bad_json_priors_are_named(tmp_path, obj, problem):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(obj))  # NaN written as JSON's NaN token, which Python reads back
    with pytest.raises(LineregError, match=problem) as info:
        read_priors(path)
    assert "bad.json" in str(info.value)


def test_unreadable_prior_files(tmp_path):
    with pytest.raises(FileFormatError, match="no such file"):
        read_priors(tmp_path / "missing.json")
    (tmp_path / "broken.json").write_text('{"position": [1, 2')
    with pytest.raises(FileFormatError, match="invalid JSON"):
        read_priors(tmp_path / "broken.json")


def test_a_tum_trajectory_gives_the_pose_at_each_image_time(tmp_path):
    poses = [some_pose(k) for k in range(4)]
    stamps = [100.0, 100.1, 100.2, 100.3]
    write_tum(tmp_path / "slam.tum", stamps, poses)
    with pytest.raises(InvalidInputError, match="--prior-sigma"):
        read_priors(tmp_path / "slam.tum")  # how rough the poses are must be said
    table = read_priors(tmp_path / "slam.tum", (5.0, 0.5))
    for k in (3, 0, 2):  # any order; a stamp a little off still finds its row
        prior = table.for_image(f"{stamps[k]:.6f}.png", stamps[k] + 0.5 * MAX_DT_S * (-1) ** k)
        np.testing.assert_allclose(prior.cam_from_world, poses[k], atol=1e-8)
        assert (prior.sigma_rot_deg, prior.radius_m) == (5.0, 0.5)
    with pytest.raises(InvalidInputError, match="no pose within"):
        table.for_image("100.150000.png", 100.15)
    with pytest.raises(InvalidInputError, match="positive"):
        read_priors(tmp_path / "slam.tum", (0.0, 0.5))


def test_prior_dict_round_trip():
    for prior in (
        Prior(position=np.array([1.0, 2.0, 3.0]), radius_m=4.0, gravity=np.array([0.0, 1.0, 0.1])),
        Prior(
            cam_from_world=some_pose(5), sigma_rot_deg=2.5, radius_m=0.6, world_down=np.array([0, -1.0, 0])
        ),
    ):
        back = Prior.from_dict(json.loads(json.dumps(prior.to_dict())))
        for name in ("position", "radius_m", "cam_from_world", "sigma_rot_deg", "gravity", "world_down"):
            a, b = getattr(prior, name), getattr(back, name)
            assert (a is None) == (b is None), name
            if a is not None:
                np.testing.assert_allclose(b, a, atol=1e-12, err_msg=name)
        assert back.gravity_sigma_deg == prior.gravity_sigma_deg


def test_library_priors_cross_the_wire_unchanged():
    """What a client sends is what the service's handler searches within: a pose's radius (not only its
    sigma_pos_m), gravity with either kind of prior or alone."""
    from protocols.codec import decode_prior, encode_prior
    from service.client import wire_prior
    from service.handlers import to_library_prior

    gravity = np.array([0.0, 0.98, 0.2])
    for prior in (
        Prior(cam_from_world=some_pose(1), sigma_rot_deg=4.0, radius_m=1.5, gravity=gravity),
        Prior(cam_from_world=some_pose(2), sigma_pos_m=0.2),
        Prior(position=np.array([5.0, 6.0, 7.0]), radius_m=20.0, gravity=gravity, gravity_sigma_deg=2.0),
        Prior(gravity=gravity),
    ):
        back = to_library_prior(decode_prior(encode_prior(wire_prior(prior))))
        assert back.radius_m == pytest.approx(prior.radius_m) if prior.radius_m else back.radius_m is None
        assert back.sigma_rot_deg == prior.sigma_rot_deg
        for name in ("position", "cam_from_world", "gravity"):
            a, b = getattr(prior, name), getattr(back, name)
            assert (a is None) == (b is None), name
            if a is not None:
                np.testing.assert_allclose(b, a, atol=1e-12, err_msg=name)
        assert back.gravity_sigma_deg == prior.gravity_sigma_deg
    with pytest.raises(InvalidInputError, match="world_down"):
        wire_prior(Prior(gravity=gravity, world_down=np.array([0.0, -1.0, 0.0])))


@pytest.mark.parametrize("scale", [1e-300, 1e200])
def test_a_gravity_of_any_magnitude_is_a_direction(scale):
    """A direction given as huge or tiny numbers: its norm would overflow to inf (the vector then divided to
    zero) or underflow to 0 (refused); scaled by its largest component first, it is the direction it says."""
    from protocols import ProtocolError
    from protocols.codec import decode_prior

    want = np.array([0.0, 0.6, 0.8])
    np.testing.assert_allclose(Prior(gravity=want * scale).gravity, want, atol=1e-15)
    np.testing.assert_allclose(
        decode_prior({"gravity": (want * scale).tolist(), "gravity_sigma_deg": 3.0}).gravity, want, atol=1e-15
    )
    with pytest.raises(InvalidInputError, match="not all zero"):
        Prior(gravity=np.zeros(3))
    with pytest.raises(ProtocolError, match="must not be zero"):
        decode_prior({"gravity": [0.0, 0.0, 0.0]})
