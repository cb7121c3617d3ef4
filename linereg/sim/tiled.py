"""A large map made of copies of a small one: the demo block repeated on a square grid (issue 9's
10⁶-segment map), for measuring how queries scale with the map and how a repeated map is answered."""

from __future__ import annotations

import uuid

import numpy as np

from ..directions import DirectionClusters
from ..map.linemap import LineMap
from ..map.surfaces import make_surfaces
from ..map.tiles import bounds, grid


def tiled_map(base: LineMap, n: int, gap_m: float = 30.0) -> tuple[LineMap, np.ndarray]:
    """Returns (the map of ``base`` copied on an ``n`` x ``n`` grid in its ground plane (x, y), (n², 3)
    offsets of the copies). The copies stand ``gap_m`` apart; the copy nearest the grid's middle has offset
    0, so a pose in ``base`` is the same pose in that copy. Segments, kinds, direction clusters (the copies'
    directions are the base's: its clusters are repeated, not computed again) and surfaces are copied."""
    if n < 1 or not gap_m >= 0:
        raise ValueError(f"tiled_map needs n >= 1 and gap_m >= 0, got n={n}, gap_m={gap_m}")
    box = bounds(base.segments)
    pitch = float(np.max(box[1, :2] - box[0, :2])) + gap_m
    i, j = np.divmod(np.arange(n * n), n)
    offsets = np.stack([(i - n // 2) * pitch, (j - n // 2) * pitch, np.zeros(n * n)], axis=1)
    segments = (base.segments[None] + np.tile(offsets, 2)[:, None]).reshape(-1, 6)
    c = base.clusters
    clusters = DirectionClusters(c.directions, np.tile(c.labels, n * n), c.support * (n * n))
    surfaces = None
    if base.surfaces is not None:
        v, t = base.surfaces.world_vertices(), base.surfaces.triangles.astype(np.int64)
        vertices = (v[None] + offsets[:, None]).reshape(-1, 3)
        triangles = (t[None] + (np.arange(n * n) * len(v))[:, None, None]).reshape(-1, 3)
        surfaces = make_surfaces(vertices, triangles)
    metadata = dict(base.metadata)
    metadata |= {
        "name": f"{metadata.get('name', 'map')} x {n * n}",
        "map_id": uuid.uuid4().hex,
        "num_segments": len(segments),
        "bounds": bounds(segments).tolist(),
        "grid": grid(segments, None),
    }
    kinds = np.tile(base.kinds, n * n)
    return LineMap(segments, clusters, metadata, kinds=kinds, surfaces=surfaces), offsets
