"""``bench real --stages``: every stage at the true pose, on a synthetic scene whose answer is known."""

import argparse

import numpy as np
import pytest

from linereg.bench import real
from linereg.bench.real_stages import STAGE_COLUMNS, stage_record
from linereg.map.linemap import LineMap
from linereg.sim.synthetic import paper_scene


@pytest.fixture(scope="module")
def scene_and_map():
    scene = paper_scene(
        np.random.default_rng(3), num_lines=100, outlier3d_fraction=0.3, outlier2d_fraction=0.3
    )
    return scene, LineMap.from_segments(scene.lines3d)


def test_every_stage_passes_at_the_truth_of_a_clean_scene(scene_and_map):
    scene, line_map = scene_and_map
    record = stage_record(scene.lines2d, line_map, scene.camera, scene.cam_from_world)
    assert record["truth_explained"] > 0.5  # 30 % of the 2D segments are outliers
    assert record["num_vds"] >= 2 and record["num_clusters"] >= 2
    assert min(record["vd_angles_deg"][:2]) < 3.0  # the image's main VDs are map directions
    assert record["best_candidate_deg"] < 3.0
    assert record["search_at_true_R_m"] < 0.2 and record["search_at_true_R_score"] > 0.9  # unrefined
    assert record["refine_from_truth_deg"] < 1.0 and record["refine_from_truth_m"] < 0.1
    assert {key for key, _, _ in STAGE_COLUMNS} <= set(record) | {"scene", "image"}


def test_a_wrong_map_shows_where_it_fails(scene_and_map):
    scene, _ = scene_and_map
    # the map turned by 30 degrees: no 2D line has a map line at the (unturned) truth
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    turned = LineMap.from_segments((scene.lines3d.reshape(-1, 3) @ turn.T).reshape(-1, 6))
    record = stage_record(scene.lines2d, turned, scene.camera, scene.cam_from_world)
    assert record["truth_explained"] < 0.1
    assert record["best_candidate_deg"] > 10.0  # the candidates are the turned map's poses, 30 degrees away


def test_cli_options():
    parser = argparse.ArgumentParser()
    real.configure(parser)
    args = parser.parse_args(["--stages", "--plane-directions", "--data", "/nonexistent"])
    assert args.stages and args.plane_directions
    defaults = parser.parse_args([])
    assert not defaults.stages and not defaults.plane_directions


def test_map_config_values():
    from linereg.config import Lines3DConfig
    from linereg.errors import InvalidInputError

    points = np.random.default_rng(0).uniform(0, 1, (500, 3))
    assert real.lines3d_config(None, points) == Lines3DConfig()
    assert real.lines3d_config('{"min_length_m": 0.2}', points).min_length_m == 0.2
    assert isinstance(real.lines3d_config("auto", points), Lines3DConfig)
    for bad in ('{"no_such_field": 1}', "[1, 2]", "{"):
        with pytest.raises(InvalidInputError):
            real.lines3d_config(bad, points)
