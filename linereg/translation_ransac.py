"""The paper's translation RANSAC (section III-C, Algorithm 2): three random pairs fix t, count inliers.

Each compatible pair (2D segment i, 3D segment j) gives one linear equation ``n_i . t = -n_i . R P_j``
(eq. "coplanar"); three pairs with independent normals give t. Hypotheses are drawn in small batches and
scored together with the shared inlier test; the loop stops when a hypothesis explains
``stop_inlier_fraction`` (paper: 70 %) of the 2D segments or after ``ransac_iterations``.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .config import MatchConfig, TranslationConfig
from .translation_inliers import pair_inliers
from .translation_pairs import Pairs

_BATCH = 64  # hypotheses scored per vectorised batch


def ransac_candidates(
    lines2d: np.ndarray,
    lines3d: np.ndarray,
    camera: Camera,
    R: np.ndarray,
    pairs: Pairs,
    config: TranslationConfig,
    match: MatchConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((H, 3) translations, (H,) inlier counts) of every RANSAC hypothesis drawn."""
    rng = np.random.default_rng(config.seed)
    stop = config.stop_inlier_fraction * len(lines2d)
    found_T, found_n = [np.zeros((0, 3))], [np.zeros(0, dtype=np.int64)]
    drawn = 0
    while drawn < config.ransac_iterations:
        size = min(_BATCH, config.ransac_iterations - drawn)
        drawn += size
        pick = rng.integers(0, pairs.size, size=(size, 3))
        normal, offset = pairs.coplanarity(pick.ravel())
        A, b = normal.reshape(size, 3, 3), -offset.reshape(size, 3, 1)  # one equation per row
        ok = np.abs(np.linalg.det(A)) > 1e-3  # skip (near-)parallel planes: t undetermined
        if not ok.any():
            continue
        T = np.linalg.solve(A[ok], b[ok])[..., 0]
        counts = pair_inliers(lines2d, camera, pairs, T, match)
        found_T.append(T)
        found_n.append(counts)
        if counts.max() >= stop:
            break
    return np.concatenate(found_T), np.concatenate(found_n)
