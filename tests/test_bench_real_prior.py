"""``bench real --prior``: the rough guesses stay within their bounds and are the same on every run."""

import numpy as np

from linereg.bench.real import rough_guess
from linereg.geometry import camera_center, pose_errors
from linereg.sim.synthetic import look_at


def test_rough_guesses_lie_within_their_bounds_and_repeat():
    truth = look_at(np.array([3.0, -2.0, 1.5]), np.array([0.0, 5.0, 1.0]))
    rotations, moves = [], []
    for k in range(200):
        guess = rough_guess(truth, 5.0, 0.5, f"scene/rgb_{k:06d}.png")
        R = guess[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
        rot, pos, _ = pose_errors(guess, truth)
        rotations.append(rot)
        moves.append(pos)
        assert np.array_equal(guess, rough_guess(truth, 5.0, 0.5, f"scene/rgb_{k:06d}.png"))
    assert max(rotations) <= 5.0 + 1e-9 and max(moves) <= 0.5 + 1e-9
    assert max(rotations) > 4.0 and max(moves) > 0.4  # the bounds are used, not just approached from afar
    other = rough_guess(truth, 5.0, 0.5, "other/rgb_000000.png")
    assert not np.allclose(
        camera_center(other), camera_center(rough_guess(truth, 5.0, 0.5, "scene/rgb_000000.png"))
    )


def test_each_image_is_localized_from_as_many_guesses_as_asked(tmp_path):
    """``--guesses N``: N records per image, the first from the guess the bench has always drawn."""
    import argparse
    from pathlib import Path

    import pytest

    from linereg.bench import real
    from linereg.errors import InvalidInputError

    item = real.RealImage(
        scene="s", image_path=Path("rgb_1.png"), cloud_path=Path("c.ply"), camera=None, cam_from_world=None
    )
    seeds = [real.guess_seed(item, k) for k in range(3)]
    assert seeds[0] == "s/rgb_1.png" and len(set(seeds)) == 3
    parser = argparse.ArgumentParser()
    real.configure(parser)
    for argv in (["--guesses", "2"], ["--guesses", "0", "--prior", "5", "0.5"]):
        with pytest.raises(InvalidInputError, match="--guesses"):
            real.run(parser.parse_args([*argv, "--data", str(tmp_path), "--out", str(tmp_path / "o")]))
    records = [
        {"scene": "s", "image": "a", "success": True, "reported": True},
        {"scene": "s", "image": "a", "success": False, "reported": True},  # claimed wrong from one guess
        {"scene": "s", "image": "b", "success": False, "reported": False},
    ]
    assert real._per_image(records) == (
        "per image: 1/2 right from at least one guess, 1/2 claimed wrong from at least one"
    )
