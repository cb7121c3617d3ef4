"""The embedded demo scene: a procedural building, its laser scan, photos with known poses.

Everything is generated from one seed, so ``linereg demo`` needs no data files and its answers are known.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import LineregError
from .building import Building, make_building
from .render import RenderConfig, rasterize, render_image, scaled_camera, visible_edge_lengths
from .scanner import ScanConfig, scan
from .views import aim, is_free, street_camera, street_view

log = logging.getLogger(__name__)

SCANNER_HEIGHT_M = 1.7  # the demo scanners' optical centre above the ground (a tripod)
# ~1 M points: 0.15 degree rays (~3.5 cm apart on a facade 13 m away; a coarser step loses 10-15 cm window
# recesses and 25 cm ledges) from 5 positions, thinned where densest (``scan.thin``); rays steeper than
# 30 degrees down would only add the ground right round each tripod
DEMO_SCAN = ScanConfig(angular_step_deg=0.15, min_elevation_deg=-30.0, target_points=1_000_000)


@dataclass(frozen=True)
class DemoScene:
    """A registration problem with its answer.

    cloud: (P, 3) float64 world points (the map); scanner_positions: (S, 3) float64;
    images: (K, H, W, 3) uint8 BGR photos taken by ``camera`` at ``cam_from_world`` (K, 4, 4) float64
    (the ground truth); ``building.edges`` are the true 3D lines.
    """

    building: Building
    cloud: np.ndarray
    scanner_positions: np.ndarray
    camera: Camera
    cam_from_world: np.ndarray
    images: np.ndarray


def make_demo_scene(
    seed: int = 0,
    num_images: int = 10,
    scan_config: ScanConfig = DEMO_SCAN,
    render_config: RenderConfig | None = None,
) -> DemoScene:
    """Returns the demo scene for a seed (deterministic): building, scan, ``num_images`` photos and poses."""
    rng_building, rng_scan, rng_poses, rng_render = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)
    )
    start = time.perf_counter()
    building = make_building(rng_building)
    positions = scanner_positions(building)
    cloud = scan(building, positions, rng_scan, scan_config)
    camera = street_camera()
    poses = np.array(demo_poses(building, rng_poses, num_images, camera)).reshape(-1, 4, 4)
    images = np.array(
        [render_image(building, pose, camera, rng_render, render_config) for pose in poses], dtype=np.uint8
    ).reshape(-1, camera.height, camera.width, 3)
    log.info(
        "demo scene (seed %d): %d points from %d scanners, %d images in %.1f s",
        seed,
        len(cloud),
        len(positions),
        len(images),
        time.perf_counter() - start,
    )
    return DemoScene(building, cloud, positions, camera, poses, images)


def scanner_positions(building: Building, clearance_m: float = 8.0) -> np.ndarray:
    """Returns (S, 3) float64 scanner positions (S <= 5): the middle of the site and its four outer corners.

    The middle is the courtyard (or the street) and sees the inner facades; each outer corner sees two
    outer sides, so every outer facade is scanned from both its ends (one corner alone sees the far
    half of a long facade at a grazing angle, too sparse for its windows). Positions inside a block are
    left out.
    """
    lo, hi = building.blocks[:, 0, :2].min(axis=0), building.blocks[:, 1, :2].max(axis=0)
    lo, hi = lo - clearance_m, hi + clearance_m
    candidates = np.array(
        [
            [*(0.5 * (building.blocks[:, 0, :2].min(axis=0) + building.blocks[:, 1, :2].max(axis=0)))],
            [hi[0], hi[1]],
            [lo[0], lo[1]],
            [hi[0], lo[1]],
            [lo[0], hi[1]],
        ]
    )
    above = candidates[:, None, :] > building.blocks[None, :, 0, :2] - 1.0
    below = candidates[:, None, :] < building.blocks[None, :, 1, :2] + 1.0
    inside = np.all(above & below, axis=2)
    free = candidates[~np.any(inside, axis=1)]
    return np.c_[free, np.full(len(free), SCANNER_HEIGHT_M)]


def demo_poses(
    building: Building,
    rng: np.random.Generator,
    n: int,
    camera: Camera,
    min_visible_edges: int = 60,
    max_tries: int = 100,
) -> list[np.ndarray]:
    """Returns n (4, 4) cam_from_world street views (``views.street_view``) a photographer would take.

    Each must show at least ``min_visible_edges`` edges of 20 px or more and some structure that fixes
    where along the building it stands (``_distinctive``), not just a patch of wall with a window grid,
    which is the same on every facade. Visibility comes from a half-resolution z-buffer (cheap per view).
    """
    small = scaled_camera(camera, 0.5)
    poses: list[np.ndarray] = []
    for _ in range(max_tries * max(n, 1)):
        if len(poses) == n:
            break
        centre, target = street_view(rng, building)
        if not is_free(building, centre):
            continue
        cam_from_world = aim(rng, centre, target)
        face_id, inv_depth = rasterize(building, cam_from_world, small)
        lengths = visible_edge_lengths(building, cam_from_world, camera, face_id, inv_depth)
        if (lengths >= 20.0).sum() >= min_visible_edges and _distinctive(building, face_id, lengths, camera):
            poses.append(cam_from_world)
    if len(poses) < n:
        raise LineregError(f"demo_poses: found {len(poses)} of {n} views in {max_tries * n} tries")
    return poses


def _distinctive(building: Building, face_id: np.ndarray, lengths: np.ndarray, camera: Camera) -> bool:
    """Returns whether a view shows two facade orientations (each on >= 8 % of the image: a corner) or a
    block's vertical corner or roof line over at least half the image (where the building ends)."""
    seen = face_id[face_id >= 0]
    normals = building.normals[seen]
    facade = np.abs(normals[:, 2]) < 0.5
    # the 4 horizontal Manhattan orientations: +x, +y, -x, -y
    orientation = np.round(np.arctan2(normals[facade, 1], normals[facade, 0]) / (0.5 * np.pi)).astype(int) % 4
    share = np.bincount(orientation, minlength=4) / face_id.size
    ends = np.isin(building.edge_kind, ("corner", "roof")) & (lengths >= camera.height / 2.0)
    return bool((share >= 0.08).sum() >= 2 or ends.any())
