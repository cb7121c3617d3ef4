"""The accuracy reference of the benchmarks: PnL with the TRUE correspondences, solved by PoseLib.

No method that must find its own correspondences can beat this on the same segments; the gap between a
method's pose error and the oracle's is what correspondence search costs.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..errors import InvalidInputError
from ..geometry import make_cam_from_world
from ..registration import check_segments


def pnl_known_correspondences(
    scene_lines2d: np.ndarray,
    lines3d: np.ndarray,
    true_matches: np.ndarray,
    camera: Camera,
    threshold_px: float = 6.0,
) -> np.ndarray:
    """Returns the (4, 4) ``cam_from_world`` PoseLib estimates from the known 2D <-> 3D line matches.

    scene_lines2d: (N, 4) float64 undistorted pixels; lines3d: (M, 6) float64 world;
    true_matches: (K, 2) int64 ``(i2d, j3d)``, K >= 3 (PoseLib's minimal line solver needs 3 lines).
    threshold_px: line inlier threshold of PoseLib's LO-RANSAC (endpoint-to-line distance in pixels).
    """
    import poselib  # imported here: only the benchmarks need it

    lines2d = check_segments(scene_lines2d, "scene_lines2d", 4)
    lines3d = check_segments(lines3d, "lines3d", 6)
    matches = np.asarray(true_matches, dtype=np.int64).reshape(-1, 2)
    if len(matches) < 3:
        raise InvalidInputError(f"true_matches has {len(matches)} rows; PnL needs at least 3")
    if (matches < 0).any() or (matches[:, 0] >= len(lines2d)).any() or (matches[:, 1] >= len(lines3d)).any():
        raise InvalidInputError("true_matches indexes outside scene_lines2d / lines3d")
    l2, l3 = lines2d[matches[:, 0]], lines3d[matches[:, 1]]
    cam = {
        "model": "PINHOLE",
        "width": camera.width,
        "height": camera.height,
        "params": [camera.fx, camera.fy, camera.cx, camera.cy],
    }
    pose, _ = poselib.estimate_absolute_pose_pnpl(
        np.zeros((0, 2)),  # no points: lines only
        np.zeros((0, 3)),
        l2[:, 0:2],
        l2[:, 2:4],
        l3[:, 0:3],
        l3[:, 3:6],
        cam,
        {"max_epipolar_error": float(threshold_px)},  # PoseLib's line threshold, pixels
        {},
    )
    # PoseLib's CameraPose maps world to camera, x_cam = R x_world + t: our cam_from_world as is
    return make_cam_from_world(np.asarray(pose.R), np.asarray(pose.t))
