"""What each pipeline stage achieves at the ground-truth pose of a real image (``bench real --stages``).

A real image that fails says little by itself: the map may not hold the image's lines, the map may lack the
image's directions, the rotation candidates may miss the truth, the translation search may fail even at
the true rotation, or refinement may drift off the truth. Each stage is run here with the truth given to it
where the stage needs the previous one's answer, so the first stage that fails is the one to fix.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def stage_record(
    lines2d: np.ndarray, line_map: Any, camera: Any, cam_from_world: np.ndarray, config: Any = None
) -> dict[str, Any]:
    """Returns the per-stage figures at the true pose of (N, 4) undistorted 2D segments in a LineMap.

    gt_length_share: share of the 2D segments' length with an inlier map segment at the truth (the
    pipeline's test); vd_angles_deg: per vanishing direction, the angle to the nearest map cluster direction
    rotated by the true R (within a few degrees: the map has that direction); true_pairing: whether some
    rotation candidate lies within 5 deg of the truth, best_candidate_deg / best_candidate_rank: that
    candidate; t_at_true_R_*: translation search given the true R; refine_from_truth_*: refinement started
    at the truth with its inliers.
    """
    from ..config import RegisterConfig
    from ..geometry import make_cam_from_world, pose_errors, rotation_error_deg, segment_lengths
    from ..matching import match_segments
    from ..refine import refine_pose
    from ..rotation import refine_candidates, rotation_candidates
    from ..translation import estimate_translation
    from ..vanishing import vanishing_directions

    config = config or RegisterConfig()
    segments, clusters = line_map.segments, line_map.clusters
    R = cam_from_world[:3, :3]
    lengths = segment_lengths(lines2d)
    matches = match_segments(lines2d, segments, camera, cam_from_world, config.match)
    share = float(lengths[np.unique(matches[:, 0])].sum() / max(lengths.sum(), 1e-12))
    vds = vanishing_directions(lines2d, camera, config.vanishing)
    record: dict[str, Any] = {"gt_length_share": share, "num_vds": len(vds), "num_clusters": len(clusters)}
    record["vd_angles_deg"] = _vd_angles(vds.directions, clusters.directions @ R.T)
    candidates = rotation_candidates(vds, clusters, config.rotation)
    candidates = refine_candidates(candidates, vds, clusters, lines2d, camera)
    errors = [rotation_error_deg(c.R, R) for c in candidates]
    best = int(np.argmin(errors)) if errors else -1
    record |= {
        "num_candidates": len(candidates),
        "best_candidate_deg": errors[best] if errors else None,
        "best_candidate_rank": best if errors else None,
        "true_pairing": bool(errors and errors[best] <= 5.0),
    }
    hyp = estimate_translation(lines2d, segments, camera, R, clusters, config.translation, config.match)
    pos = pose_errors(make_cam_from_world(R, hyp.t), cam_from_world)[1] if hyp.num_inliers else None
    record |= {"t_at_true_R_inliers": hyp.num_inliers, "t_at_true_R_pos_m": pos}
    if len(matches) >= config.refine.min_matches:
        refined = refine_pose(lines2d, segments, camera, cam_from_world, matches, config.refine, config.match)
        rot, pos, _ = pose_errors(refined.cam_from_world, cam_from_world)
        record |= {"refine_from_truth_deg": rot, "refine_from_truth_m": pos}
    return record


def _vd_angles(vds: np.ndarray, directions: np.ndarray) -> list[float]:
    """Returns per (K, 3) VD the sign-free angle (deg) to the nearest of (C, 3) camera-frame directions."""
    if len(vds) == 0 or len(directions) == 0:
        return [float("nan")] * len(vds)
    cos = np.abs(vds @ directions.T).max(axis=1)
    return [round(float(a), 1) for a in np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))]


STAGE_COLUMNS = (
    ("scene", "scene", ""),
    ("image", "image", ""),
    ("gt_length_share", "GT len share", ".2f"),
    ("vd_angles_deg", "VD->map deg", ""),
    ("best_candidate_deg", "best cand deg", ".1f"),
    ("best_candidate_rank", "rank", "d"),
    ("num_candidates", "cands", "d"),
    ("t_at_true_R_inliers", "t@R inl", "d"),
    ("t_at_true_R_pos_m", "t@R pos m", ".2f"),
    ("refine_from_truth_deg", "ref deg", ".2f"),
    ("refine_from_truth_m", "ref m", ".2f"),
)
