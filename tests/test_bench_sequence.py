"""``linereg bench sequence --seeds``: one walk per seed and every row's wrong claims summed over them."""

import argparse

import pytest

from linereg.bench import sequence
from linereg.errors import InvalidInputError


def _walk(wrong: dict[str, int], within: dict[str, float], ate: tuple[float, float]) -> dict:
    rows = {name: {"wrong": wrong[name], "within": within[name]} for name in wrong}
    rows["global"] |= {"frames": list(range(0, 320, 20))}  # every 20th frame only
    rows["per-frame"]["ate_m"], rows["smoothed"]["ate_m_same_frames"] = ate
    return {"rows": rows, "frames": 320}


def test_the_seeds_table_sums_each_rows_wrong_claims_and_frames_within(capsys):
    walks = [
        _walk(
            {"per-frame": 0, "smoothed": 0, "tracking": 0, "tracking-reach": 1, "global": 0},
            {"per-frame": 0.5, "smoothed": 0.75, "tracking": 0.5, "tracking-reach": 0.25, "global": 0.0625},
            (0.08, 0.04),
        ),
        _walk(
            {"per-frame": 0, "smoothed": 0, "tracking": 2, "tracking-reach": 110, "global": 1},
            {"per-frame": 0.5, "smoothed": 0.75, "tracking": 1.0, "tracking-reach": 0.125, "global": 0.125},
            (0.1, 0.06),
        ),
    ]
    sequence._print_seeds([0, 2], walks)
    header, _, _, tracking, reach, global_, ratios = capsys.readouterr().out.strip().splitlines()
    assert "seeds 0 2" in header
    assert tracking.endswith("all:    2 /  480 of 640")
    assert reach.endswith("all:  111 /  120 of 640")
    assert global_.endswith("all:    1 /    3 of 32")  # 1 + 2 of the 16 + 16 global frames
    assert ratios.endswith("0.50  0.60")  # smoothed / per-frame ATE on the per-frame frames


def test_the_same_seed_twice_is_refused(tmp_path):
    parser = argparse.ArgumentParser()
    sequence.configure(parser)
    args = parser.parse_args(["--scene", "synthetic", "--seeds", "3", "3", "--out", str(tmp_path / "out")])
    with pytest.raises(InvalidInputError, match="--seeds"):
        sequence.run(args)
