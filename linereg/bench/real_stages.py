"""What each pipeline stage achieves at the ground-truth pose of a real image (``bench real --stages``).

A real image that fails says little by itself: the map may not hold the image's lines (the score at the
truth is low), the map may lack the image's directions, the rotation candidates may miss the truth, the
search may not find the truth's position even at the true rotation (a search problem), another pose may
score better than the truth (a scoring problem), or refinement may drift off the truth. Each stage is run
here with the truth given where it needs the previous one's answer, so the first that fails is the one to fix.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def stage_record(
    lines2d: np.ndarray, line_map: Any, camera: Any, cam_from_world: np.ndarray, config: Any = None
) -> dict[str, Any]:
    """Returns the per-stage figures at the true pose of (N, 4) undistorted 2D segments in a LineMap.

    truth_explained: share of the image's line length the map explains at the true pose (the score);
    vd_angles_deg: per vanishing direction, the angle to the nearest map cluster direction rotated by the
    true R; best_candidate_deg / best_candidate_rank: the rotation candidate nearest the truth;
    search_at_true_R_m / _score: the search given only the true rotation (its best pose's position error,
    and its score against the truth's: above 1 a scoring problem); refine_from_truth_*: refinement started
    at the truth.
    """
    from ..config import RegisterConfig
    from ..geometry import pose_errors, rotation_error_deg
    from ..localization import map_view
    from ..points import image_points
    from ..priors import search_region
    from ..refine import refine_pose
    from ..rotation import refine_candidates, rotation_candidates
    from ..score import image_lines, score_pose
    from ..search import search
    from ..vanishing import vanishing_directions

    config = config or RegisterConfig()
    view = map_view(line_map, None, config)
    R = cam_from_world[:3, :3]
    image = image_lines(lines2d, camera, config.score)
    truth = score_pose(image, view.segments, camera, cam_from_world, config.score, view.visible)
    vds = vanishing_directions(lines2d, camera, config.vanishing)
    record: dict[str, Any] = {
        "truth_explained": truth.explained_length / max(image.total_length, 1e-12),
        "truth_score": truth.value,
        "num_vds": len(vds),
        "num_clusters": len(view.clusters),
        "vd_angles_deg": _vd_angles(vds.directions, view.clusters.directions @ R.T),
    }
    candidates = rotation_candidates(vds, view.clusters, config.rotation)
    candidates = refine_candidates(candidates, vds, view.clusters, lines2d, camera)
    errors = [rotation_error_deg(c.R, R) for c in candidates]
    best = int(np.argmin(errors)) if errors else -1
    record |= {
        "num_candidates": len(candidates),
        "best_candidate_deg": errors[best] if errors else None,
        "best_candidate_rank": best if errors else None,
    }
    regions = [search_region(view.segments, None, margin) for margin in config.search.region_margins]
    found, _ = search(
        image, image_points(lines2d, config.points), view.segments, view.points, view.signatures, camera,
        [R], regions, config.search, config.score, view.visible,
    )  # fmt: skip
    if found:
        record |= {
            "search_at_true_R_m": pose_errors(found[0].cam_from_world, cam_from_world)[1],
            "search_at_true_R_score": found[0].score.value / truth.value if truth.value > 0 else None,
        }
    refined = refine_pose(
        image, view.segments, camera, cam_from_world, config.refine, config.score, view.visible
    )
    rot, pos, _ = pose_errors(refined.cam_from_world, cam_from_world)
    record |= {"refine_from_truth_deg": rot, "refine_from_truth_m": pos}
    return record


def _vd_angles(vds: np.ndarray, directions: np.ndarray) -> list[float]:
    """Returns per (K, 3) VD the sign-free angle (deg) to the nearest of (C, 3) camera-frame directions."""
    if len(vds) == 0 or len(directions) == 0:
        return [float("nan")] * len(vds)
    cos = np.abs(vds @ directions.T).max(axis=1)
    sin = np.sqrt(np.maximum(1.0 - cos**2, 0.0))
    return [round(float(a), 1) for a in np.degrees(np.arctan2(sin, cos))]


STAGE_COLUMNS = (
    ("scene", "scene", ""),
    ("image", "image", ""),
    ("truth_explained", "truth expl", ".2f"),
    ("vd_angles_deg", "VD->map deg", ""),
    ("best_candidate_deg", "best cand deg", ".1f"),
    ("best_candidate_rank", "rank", "d"),
    ("num_candidates", "cands", "d"),
    ("search_at_true_R_m", "search@R m", ".2f"),
    ("search_at_true_R_score", "score/truth", ".2f"),
    ("refine_from_truth_deg", "ref deg", ".2f"),
    ("refine_from_truth_m", "ref m", ".2f"),
)
