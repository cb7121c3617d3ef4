"""The benchmarks' search check: why a photo failed (score, search or decision), from known answers."""

from types import SimpleNamespace

import numpy as np

import linereg
from linereg.bench import search_check
from linereg.sim.synthetic import paper_scene


def test_verdicts_on_a_paper_scene(rng):
    scene = paper_scene(rng, 100, 0.3, 0.3, 2.0)
    view = SimpleNamespace(segments=scene.lines3d, visible=None, parts=None, chunks=None)
    reg = linereg.register(scene.lines2d, scene.lines3d, scene.camera)
    assert reg.success
    check = search_check.check(scene.lines2d, view, scene.camera, scene.cam_from_world, reg, True)
    assert check["verdict"] == "right"
    assert abs(check["truth_score"] - reg.score) < 0.05 * reg.score  # the same pose, refined alike
    refused = linereg.Registration(
        False, reason="ambiguous", cam_from_world=reg.cam_from_world, score=reg.score
    )
    assert (
        search_check.check(scene.lines2d, view, scene.camera, scene.cam_from_world, refused, True)["verdict"]
        == "refused right"
    )
    wrong_pose = scene.cam_from_world.copy()
    wrong_pose[:3, 3] += 0.5
    missed = linereg.Registration(True, cam_from_world=wrong_pose, score=0.1 * reg.score)
    outscored = linereg.Registration(True, cam_from_world=wrong_pose, score=2.0 * reg.score)
    verdicts = [
        search_check.check(scene.lines2d, view, scene.camera, scene.cam_from_world, r, False)["verdict"]
        for r in (missed, outscored)
    ]
    assert verdicts == ["search", "score"]
    records = [{"search_check": {"verdict": v}} for v in ("right", "score", "score")] + [{}]
    assert search_check.tally(records) == {"right": 1, "refused right": 0, "score": 2, "search": 0}
    assert "2 the truth does not score best" in search_check.summary_line(search_check.tally(records))
    assert np.isfinite(check["found_score"])
