"""What each map segment is: the kind of 3D edge it was extracted as (``LineMap.kinds``), so that a score
can weigh them (a crease is exact, a ring-curvature edge of a sparse sweep is rough).

The values are stored in map files: never renumber one, only add new ones.
"""

from __future__ import annotations

import numpy as np

UNKNOWN = 0  # given as bare segments (``LineMap.from_segments`` without kinds)
CREASE = 1  # where two planar regions meet: their intersection line
BOUNDARY = 2  # where a planar region ends (its contour in its plane)
OCCLUDING = 3  # a depth discontinuity seen from the known sensor origin (the near side's silhouette)
RING_EDGE = 4  # a sharp bend along a spinning LiDAR's scan ring (LOAM-style curvature), not on a plane edge
INTENSITY = 5  # an edge of the cloud's intensity or colour (opt-in: the paper's maps are untextured)
POINT_EDGE = 6  # where the surface bends or ends, found per point (``point_edges``: small structure)

NAMES = {
    UNKNOWN: "unknown",
    CREASE: "crease",
    BOUNDARY: "boundary",
    OCCLUDING: "occluding",
    RING_EDGE: "ring_edge",
    INTENSITY: "intensity",
    POINT_EDGE: "point_edge",
}


def kind_counts(kinds: np.ndarray) -> dict[str, int]:
    """Returns {kind name: number of segments} of (M,) int kinds (names of every kind, zero counts too)."""
    kinds = np.asarray(kinds, dtype=np.int64)
    return {name: int((kinds == k).sum()) for k, name in NAMES.items()}


def check_kinds(kinds: object, count: int) -> np.ndarray:
    """Returns (count,) int8 kinds, or raises InvalidInputError naming the problem."""
    from ..errors import InvalidInputError

    arr = np.asarray(kinds)
    if arr.shape != (count,):
        raise InvalidInputError(f"kinds must have shape ({count},), got {arr.shape}")
    if count and (not np.issubdtype(arr.dtype, np.integer) or arr.min() < 0 or arr.max() > max(NAMES)):
        raise InvalidInputError(f"kinds must be integers in 0..{max(NAMES)} (linereg.map.kinds)")
    return arr.astype(np.int8)
