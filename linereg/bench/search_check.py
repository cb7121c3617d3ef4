"""Why a photo failed: a scoring problem, a search problem or the decision (issue 9's search check).

A registration can fail in three separate ways, and each needs a different fix:

- **score**: some pose that is not the truth scores at least as well as the truth (refined from the true
  pose, so ground-truth noise does not count against it). No search can help; the score or the map must.
- **search**: the truth scores better than everything the search returned, yet it was not returned.
- **decision**: the returned pose is right but was refused (ambiguous, too little explained), or one that
  is wrong was claimed.

``verdict`` compares the pipeline's best score with the refined truth's, both by ``score.score_pose`` (the
one scoring function) on the same map view.
"""

from __future__ import annotations

from typing import Any

import numpy as np

VERDICTS = ("right", "refused right", "score", "search")


def check(
    lines2d: np.ndarray,
    view: Any,
    camera: Any,
    truth: np.ndarray,
    result: Any,
    pose_is_right: bool,
    config: Any = None,
) -> dict[str, Any]:
    """Returns {"truth_score", "found_score", "verdict"} of a Registration ``result`` of (N, 4) undistorted
    ``lines2d`` against a ``localization.map_view``, given the true (4, 4) cam_from_world.

    ``pose_is_right``: the returned pose meets the benchmark's criterion. Verdict "right" (claimed and
    right), "refused right" (right pose, success=False), "score" (the truth does not score best),
    "search" (it does, and the search did not return it).
    """
    from ..config import RegisterConfig
    from ..pipeline import view_score
    from ..refine import refine_pose
    from ..score import image_lines

    config = config or RegisterConfig()
    image = image_lines(lines2d, camera, config.score)
    refined = refine_pose(image, view.segments, camera, truth, config.refine, config.score, view.visible)
    # scored as the decision scores the poses it compares (occlusion by the map's surfaces included)
    truth_score = float(view_score(view, image, camera, refined.cam_from_world, config.score)[0].value)
    found_score = float(result.score) if result.cam_from_world is not None else -np.inf
    if pose_is_right:
        verdict = "right" if result.success else "refused right"
    else:
        verdict = "search" if truth_score > found_score else "score"
    return {"truth_score": truth_score, "found_score": found_score, "verdict": verdict}


def tally(records: list[dict[str, Any]]) -> dict[str, int]:
    """Returns how many records have each verdict (records without one are left out)."""
    verdicts = [r["search_check"]["verdict"] for r in records if "search_check" in r]
    return {v: verdicts.count(v) for v in VERDICTS}


def summary_line(counts: dict[str, int]) -> str:
    """Returns the one-line summary the benchmarks print."""
    return (
        f"search check: {counts['right']} right, {counts['refused right']} right but refused, "
        f"{counts['score']} the truth does not score best (score problem), "
        f"{counts['search']} the truth scores best but was not found (search problem)"
    )
