"""``linereg map``: build a line map from a point cloud (``build``), or summarise one (``info``).

Examples:
  linereg map build scan.e57 -o site.linemap --name site   # clouds: .ply .pcd .xyz .txt .las .laz .e57
  linereg map build sweep.pcd -o street.linemap --intensity-edges   # + road markings of a LiDAR sweep
  (a sweep's per-point ring field, PLY / PCD / LAS ``ring``, gives its rings and, in any frame, its sensor)
  linereg map info site.linemap
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from . import check_output_file, description
from .progress import Progress

STAGES = ("read", "profile", "normals", "regions", "lines", "point edges", "clusters", "write")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "map",
        help="build or inspect a line map",
        description=description(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    maps = p.add_subparsers(dest="map_command", required=True, metavar="ACTION")
    build = maps.add_parser("build", help="extract 3D line segments of a cloud into a map file")
    build.add_argument("cloud", type=Path, help="point cloud: .ply .pcd .xyz .txt .las .laz .e57")
    build.add_argument(
        "-o", "--output", type=Path, required=True, help="map file to write (e.g. site.linemap)"
    )
    build.add_argument(
        "--voxel", type=float, default=0.0, metavar="M", help="downsample to this voxel (m) first"
    )
    build.add_argument(
        "--plane-voxel", type=float, default=None, metavar="M", help="voxel of local plane fits (m)"
    )
    build.add_argument(
        "--sensor-origin",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="where the scanner stood, in the cloud's frame (default: a PCD's VIEWPOINT or a one-scan E57's "
        "pose, else found from a single sweep's rings)",
    )
    build.add_argument(
        "--intensity-edges",
        action="store_true",
        help="also extract the steps of the cloud's intensity along a single sweep's rings (road markings, "
        "paint; the cloud must carry an intensity per point)",
    )
    build.add_argument("--name", default=None, help="map name (default: the cloud's file name)")
    build.set_defaults(func=run_build)
    info = maps.add_parser("info", help="print a summary of a map file")
    info.add_argument("map", type=Path, help="map file (from `linereg map build`)")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    info.set_defaults(func=run_info)


def run_build(args: argparse.Namespace) -> int:
    from ..config import Lines3DConfig, MapBuildConfig
    from ..errors import InvalidInputError
    from ..io import read_cloud_fields, read_sensor_origin
    from ..map.linemap import LineMap

    if args.voxel < 0 or (args.plane_voxel is not None and args.plane_voxel <= 0):
        raise InvalidInputError("--voxel must be >= 0 and --plane-voxel > 0")
    config = replace(Lines3DConfig(), downsample_m=args.voxel)
    if args.plane_voxel is not None:
        config = replace(config, voxel_m=args.plane_voxel)
    check_output_file("--output", args.output)  # before minutes of extraction
    with Progress(len(STAGES), "map build", log_steps=True) as progress:
        progress.update(0, "read")
        start = time.perf_counter()
        # the intensity only when asked (reading it reads a PLY or PCD a second time); a ring field always
        points, intensity, rings = read_cloud_fields(args.cloud, intensity=args.intensity_edges)
        origin = args.sensor_origin if args.sensor_origin is not None else read_sensor_origin(args.cloud)
        line_map = LineMap.build(
            points,
            MapBuildConfig(lines3d=config, intensity_edges=args.intensity_edges),
            name=args.name or args.cloud.stem,
            progress=lambda stage: progress.update(1, stage),
            sensor_origin=None if origin is None else np.asarray(origin, dtype=np.float64),
            intensity=intensity,
            rings=rings,
            source=str(args.cloud),
        )
        progress.update(1, "write")
        line_map.save(args.output)
        progress.update(1, "done")
    seconds = time.perf_counter() - start
    repeated = line_map.metadata.get("repeated_points", 0)
    print(
        f"{args.output}: {len(line_map)} segments, {len(line_map.clusters)} clusters "
        f"from {len(points):,} points in {seconds:.1f} s"
        + (f" ({repeated:,} of them exact repeats, dropped)" if repeated else "")
    )
    return 0


def run_info(args: argparse.Namespace) -> int:
    from ..io import jsonable
    from ..map.linemap import LineMap

    summary = LineMap.load(args.map).info()
    if args.json:
        print(json.dumps(jsonable(summary), indent=2, allow_nan=False))
        return 0
    print(f"map {summary.get('name')!r} ({args.map}), format version {summary.get('format_version')}")
    print(f"  segments: {summary['num_segments']} (total {summary['total_length_m']:.1f} m)")
    print(f"  clusters: {len(summary['clusters'])} (+{summary['unclustered']} segments in none)")
    for k, c in enumerate(summary["clusters"]):
        d = ", ".join(f"{v:+.3f}" for v in c["direction"])
        print(f"    {k}: direction ({d})  {c['size']} segments  {c['support_m']:.1f} m")
    lo, hi = summary["bounds"]
    print(f"  bounds: min ({', '.join(f'{v:.3f}' for v in lo)})  max ({', '.join(f'{v:.3f}' for v in hi)})")
    print(f"  tiles: {summary['num_tiles']} of {summary['tile_m']:.1f} m")
    if isinstance(summary.get("profile"), dict):
        print("  cloud: " + _profile_line(summary["profile"]))
    skip = {"name", "format_version", "num_segments", "total_length_m", "clusters", "unclustered", "bounds"}
    skip |= {"num_tiles", "tile_m", "extraction", "profile"}
    for key, value in summary.items():
        if key not in skip:
            print(f"  {key}: {value}")
    if summary.get("extraction"):
        print("  extraction: " + ", ".join(f"{k}={v}" for k, v in summary["extraction"].items()))
    return 0


def _profile_line(profile: dict[str, Any]) -> str:
    """Returns a map's cloud profile (``map.profile.CloudProfile.as_dict``) in words; keys a map file of an
    older version lacks are left out."""
    words = [f"{profile.get('kind', '?')}, {profile.get('num_points', 0):,} points"]
    if profile.get("spacing_m"):
        spacing = f"spacing {100 * profile['spacing_m']:.1f} cm"
        if "spacing_p10_m" in profile and "spacing_p90_m" in profile:
            spacing += (
                f" (10-90 %: {100 * profile['spacing_p10_m']:.1f}-{100 * profile['spacing_p90_m']:.1f} cm)"
            )
        words.append(spacing)
    if "density_spread" in profile:
        words.append(f"density spread {profile['density_spread']:.1f}")
    if "noise_m" in profile:
        words.append(f"noise {1000 * profile['noise_m']:.1f} mm")
    if profile.get("rings"):
        words.append(f"{profile['rings']} rings {profile.get('ring_gap_deg', 0.0):.2f} deg apart")
        if profile.get("ring_source") == "field":
            words[-1] += " (the file's ring field)"
    if profile.get("sensor_origin") is not None:
        words.append("sensor at (" + ", ".join(f"{v:.2f}" for v in profile["sensor_origin"]) + ")")
    return ", ".join(words)
