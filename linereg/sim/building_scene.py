"""Building scenes for the synthetic benchmark: a procedural block seen from the street, with its true pose.

The map holds every edge of the block (hidden back facades included) plus street clutter; the image holds
the visible parts of the edges, fragmented and noisy, plus clutter segments.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from .building import BuildingConfig, make_building
from .synthetic import (
    Scene,
    add_outliers_and_shuffle,
    fragment,
    num_outliers,
    random_image_segments,
    random_unit,
)
from .views import camera_poses, project_building, street_camera


def _distractors(rng: np.random.Generator, blocks: np.ndarray, bounds: np.ndarray, n: int) -> np.ndarray:
    """Returns (n, 6) street-level clutter segments (cars, poles, trees) outside the blocks, 0.5-3 m long."""
    out = np.zeros((0, 6))
    while len(out) < n:
        p = rng.uniform([*bounds[0, :2], 0.0], [*bounds[1, :2], 4.0], size=(2 * n, 3))
        inside = np.all(
            (p[:, None] > blocks[None, :, 0] - 0.5) & (p[:, None] < blocks[None, :, 1] + 0.5), axis=2
        )
        p = p[~inside.any(axis=1)]
        q = p + random_unit(rng, len(p)) * rng.uniform(0.5, 3.0, size=(len(p), 1))
        out = np.r_[out, np.c_[p, q]]
    return out[:n]


def building_scene(
    rng: np.random.Generator,
    num_distractors: int = 50,
    outlier2d_fraction: float = 0.2,
    noise_px: float = 1.0,
    camera: Camera | None = None,
    config: BuildingConfig | None = None,
) -> Scene:
    """Returns a street-level view of a procedural building with its true pose and correspondences.

    Choices:
    - Map (``lines3d``): every building edge (``make_building(rng, config)``, hidden back facades
      included) then ``num_distractors`` random street-level 3D segments (scanned clutter that the image
      does not show: cars gone, trees), at rows ``len(building.edges):``.
    - Camera: default ``views.street_camera()`` (640x480, f = 600), pose from ``camera_poses``.
    - 2D: visible parts of the edges (frustum, occlusion by every face, longest visible run), >= 20 px,
      then ``fragment`` (30 % shortened, 30 % of long ones split into 2-3 pieces), Gaussian endpoint noise
      ``noise_px``; every piece is a true match of its edge.
    - 2D outliers: clutter segments of 20-60 px, centres in the lower 60 % of the image (cars, trees),
      making ``outlier2d_fraction`` of all 2D segments. Shuffled; ``true_matches`` sorted by i2d.
    """
    camera = camera or street_camera()
    building = make_building(rng, config)
    cam_from_world = camera_poses(building, rng, 1, camera)[0]
    seg, edge = project_building(building, camera, cam_from_world)
    seg, source = fragment(rng, seg)
    seg = seg + rng.normal(scale=noise_px, size=seg.shape)
    lines3d = np.r_[building.edges, _distractors(rng, building.blocks, building.bounds, num_distractors)]
    n_clutter = num_outliers(len(seg), outlier2d_fraction)
    clutter = random_image_segments(rng, n_clutter, camera, np.linspace(20.0, 60.0, 41), top=0.4)
    lines2d, matches = add_outliers_and_shuffle(rng, seg, edge[source], clutter)
    return Scene(lines2d, lines3d, camera, cam_from_world, matches)
