"""A camera on a LiDAR: the frames a camera-LiDAR calibration works on, made from a scene with known poses.

A rig moves through a scene; at each stop its LiDAR maps the scene in its own frame and its camera takes a
photo from the same place relative to the LiDAR, ``cam_from_lidar`` (the extrinsic). Given photos taken
from ``cam_from_world[k]`` and one world map, stop k's LiDAR stood at ``lidar_from_world[k] =
cam_from_lidar^-1 cam_from_world[k]``, and its map is the world map moved there (``moved_map``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..directions import DirectionClusters
from ..geometry import invert
from ..map.linemap import LineMap
from ..map.surfaces import make_surfaces


def moved_map(line_map: LineMap, new_from_old: np.ndarray) -> LineMap:
    """Returns the map with its segments, direction clusters and surfaces in the frame ``new_from_old``
    (4, 4, rigid) takes its frame to; kinds and metadata are kept."""
    R, t = new_from_old[:3, :3], new_from_old[:3, 3]
    segments = (line_map.segments.reshape(-1, 3) @ R.T + t).reshape(-1, 6)
    c = line_map.clusters
    clusters = DirectionClusters(c.directions @ R.T, c.labels, c.support)
    surfaces = None
    if line_map.surfaces is not None and len(line_map.surfaces):
        vertices = line_map.surfaces.world_vertices() @ R.T + t
        surfaces = make_surfaces(vertices, line_map.surfaces.triangles)
    return LineMap(segments, clusters, dict(line_map.metadata), kinds=line_map.kinds, surfaces=surfaces)


def rig_maps(
    line_map: LineMap, cam_from_world: Sequence[np.ndarray], cam_from_lidar: np.ndarray
) -> list[LineMap]:
    """Returns per photo pose the world map in the frame of the LiDAR that stood at ``cam_from_lidar``
    behind the camera: what each stop of the rig maps."""
    lidar_from_cam = invert(cam_from_lidar)
    return [moved_map(line_map, lidar_from_cam @ T) for T in cam_from_world]
