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
