"""``register``: the paper's section III from segments to a refined pose — a composer, no math here."""

from __future__ import annotations

import logging

import numpy as np

from .camera import Camera
from .config import RegisterConfig
from .directions import DirectionClusters
from .errors import InvalidInputError
from .geometry import make_cam_from_world, rotation_error_deg
from .parallel import parallel_clusters
from .refine import refine_pose
from .registration import Registration, check_segments
from .rotation import rotation_candidates
from .timing import StageTimer
from .translation import estimate_translation
from .vanishing import vanishing_directions

log = logging.getLogger(__name__)


def register(
    lines2d: np.ndarray, lines3d: np.ndarray, camera: Camera, config: RegisterConfig | None = None
) -> Registration:
    """Returns the Registration of an image's 2D segments against a map's 3D segments.

    lines2d: (N, 4) float64 pixels as measured in the image (distorted if ``camera.dist`` is set).
    lines3d: (M, 6) float64 world metres. No pose found -> ``success=False`` with a reason; malformed
    input -> ``InvalidInputError`` naming the argument.
    """
    config = config or RegisterConfig()
    if not isinstance(camera, Camera):
        raise InvalidInputError(f"camera must be a linereg.Camera, got {type(camera).__name__}")
    lines2d = check_segments(lines2d, "lines2d", 4, config.min_lines2d)
    lines3d = check_segments(lines3d, "lines3d", 6, config.min_lines3d)
    if camera.has_distortion:  # the pipeline works on undistorted pixels of the same K
        lines2d = camera.undistort_points(lines2d.reshape(-1, 2)).reshape(-1, 4)
        camera = camera.undistorted()
    if config.method == "ransac6":
        from .baseline import register_ransac6

        return register_ransac6(lines2d, lines3d, camera, config)
    timer = StageTimer()
    with timer("parallel_3d"):
        clusters = parallel_clusters(lines3d, config.parallel)
    return register_undistorted(lines2d, lines3d, clusters, camera, config, timer)


def register_undistorted(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    clusters3d: DirectionClusters,
    camera: Camera,
    config: RegisterConfig,
    timer: StageTimer | None = None,
) -> Registration:
    """Returns the Registration of validated, undistorted segments with precomputed 3D parallel clusters."""
    timer = timer or StageTimer()
    # III-B: vanishing directions of the image (Rother 2002, multiple RANSAC on interpretation planes)
    with timer("vanishing"):
        vds = vanishing_directions(lines2d, camera, config.vanishing)
    # III-B, eq. (2): rotation candidates from VD <-> parallel-cluster pairings and signs (Algorithm 1)
    with timer("rotation"):
        candidates = rotation_candidates(vds, clusters3d, config.rotation)
    if not candidates:
        reason = f"no rotation candidate ({len(vds)} vanishing directions, {len(clusters3d)} 3D clusters)"
        return Registration(success=False, reason=reason, timings=timer.finish())
    # III-C, eq. (coplanar): translation and correspondences per candidate; most inliers wins (Algorithm 2)
    with timer("translation"):
        hypotheses = [
            estimate_translation(lines2d, lines3d, camera, c.R, clusters3d, config.translation, config.match)
            for c in candidates
        ]
    order = np.argsort([-h.num_inliers for h in hypotheses], kind="stable")
    best, winner = hypotheses[order[0]], candidates[order[0]]
    runner_up = max(
        [best.runner_up_inliers]
        + [hypotheses[i].num_inliers for i in order[1:] if _differs(candidates[i].R, winner.R)]
    )
    if best.num_inliers < config.min_inliers:
        reason = f"best hypothesis has {best.num_inliers} inliers, fewer than {config.min_inliers}"
        return Registration(success=False, reason=reason, timings=timer.finish())
    # III-D, eq. (costs): GTSAM refinement of endpoint-to-line distances, reject outliers, re-associate
    with timer("refine"):
        refined = refine_pose(
            lines2d,
            lines3d,
            camera,
            make_cam_from_world(winner.R, best.t),
            best.matches,
            config.refine,
            config.match,
        )
    num_inliers = len(refined.matches)
    if num_inliers < config.min_inliers:
        reason = f"refinement kept {num_inliers} inliers, fewer than {config.min_inliers}"
        return Registration(success=False, reason=reason, timings=timer.finish())
    return Registration(
        success=True,
        cam_from_world=refined.cam_from_world,
        matches=refined.matches,
        num_inliers=num_inliers,
        covariance=refined.covariance,
        runner_up_inliers=int(runner_up),
        rms_px=refined.rms_px,
        timings=timer.finish(),
    )


def _differs(R_a: np.ndarray, R_b: np.ndarray, angle_deg: float = 2.0) -> bool:
    """Returns True if two rotation candidates are distinct hypotheses (not the same up to noise)."""
    return rotation_error_deg(R_a, R_b) > angle_deg
