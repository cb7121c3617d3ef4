"""Compiled kernels made ready before the first real query.

linereg's inner loops are compiled by numba on first use and cached on disk (next to the modules, or in
``NUMBA_CACHE_DIR``). A fresh install compiles them during its first localization, ~20-30 s on 2 cores;
a process whose cache is filled loads them in about a second. ``warm_up`` runs one small localization
and two tracked frames so that this happens before a caller waits for an answer: a service worker warms
up before it announces itself ready, and ``linereg demo`` warms up in a process of its own while it scans
and maps its scene. ``warm_up_map`` does the same for map building (``bench lines3d`` times a build after
it).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np


def warm_up(line_map: Any = None, config: Any = None) -> float:
    """Localizes a small generated building once (its edges as the map, its faces as the map's surfaces,
    the edges it shows projected at a street-level pose) and tracks it for two frames, so that every
    kernel a localization or a tracking session calls is compiled or loaded from the cache; with a
    ``line_map`` (a LineMap), also derives what every query of it needs once (``localization.prepare_map``
    under ``config``, a RegisterConfig or None: the defaults): a map of 10^5 segments took its first query
    seconds longer. Returns the seconds it took."""
    from .localization import localize_segments, prepare_map
    from .map.linemap import LineMap
    from .sim.building import BuildingConfig, make_building
    from .sim.views import camera_poses, project_building, street_camera
    from .tracking import Tracker

    start = time.perf_counter()
    rng = np.random.default_rng(0)
    building = make_building(rng, BuildingConfig(layout="street", blocks_per_side=1, floors=(2, 2)))
    camera = street_camera()
    pose = camera_poses(building, rng, 1, camera)[0]
    lines2d, _ = project_building(building, camera, pose)
    small = LineMap.from_segments(building.edges, name="warm-up", surfaces=building.mesh())
    localize_segments(lines2d, small, camera)
    tracker = Tracker(small, camera)
    tracker.start_at(pose)
    for timestamp in (0.0, 0.1):
        tracker.step(lines2d, timestamp=timestamp)
    if line_map is not None:
        prepare_map(line_map, config)
    return time.perf_counter() - start


def warm_up_map(config: Any) -> None:
    """Builds the map of a small generated room (a floor, two walls, a box on the floor, 1.5 cm apart,
    2 mm noise, a heap of clutter) with ``config`` (a ``MapBuildConfig``) and point edges on: imports every
    stage of map building and compiles or loads its kernels (``bench lines3d`` times a build after it)."""
    from dataclasses import replace

    from .map.linemap import LineMap

    rng = np.random.default_rng(0)
    g = np.arange(0.0, 1.2, 0.015)
    u, v = (a.ravel() for a in np.meshgrid(g, g))
    zero = np.zeros_like(u)
    box = np.arange(0.3, 0.6, 0.015)
    bu, bv = (a.ravel() for a in np.meshgrid(box, box))
    parts = [
        np.c_[u, v, zero], np.c_[zero, u, v], np.c_[u, zero, v],  # floor, walls
        np.c_[bu, bv, np.full_like(bu, 0.3)], np.c_[bu, np.full_like(bu, 0.3), bv - 0.3],  # box top, side
        rng.uniform([0.8, 0.8, 0.0], [0.9, 0.9, 0.1], (300, 3)),  # clutter beside the floor
    ]  # fmt: skip
    points = np.concatenate(parts) + rng.normal(0.0, 0.002, (sum(map(len, parts)), 3))
    LineMap.build(points, replace(config, point_edges=True))
