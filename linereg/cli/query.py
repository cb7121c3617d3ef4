"""``linereg query --connect ENDPOINT --map NAME --camera CAMERA IMAGE...``: localize images via a service.

Prints one JSON object per image (the Registration, or the service's error) on stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..camera import Camera
from ..errors import InvalidInputError


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "query", help="localize images through a running service", description=__doc__
    )
    parser.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="PNG or JPEG files")
    parser.add_argument(
        "--connect", action="append", help="router endpoint (repeatable; default tcp/127.0.0.1:7447)"
    )
    parser.add_argument("--map", help="map name (default: the only map being served)")
    parser.add_argument(
        "--camera", required=True, type=Path, help="camera JSON {fx, fy, cx, cy, width, height[, dist]}"
    )
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds per image (default 10)")
    parser.add_argument("--zenoh-config", help="zenoh json5 config file (TLS, credentials)")
    parser.add_argument("--matches", action="store_true", help="also return the 2D-3D matches")
    parser.set_defaults(func=run)


def read_camera(path: Path) -> Camera:
    """Returns the camera in a JSON file (the library reader when present, else ``Camera.from_dict``)."""
    try:
        from .. import io  # type: ignore[attr-defined]

        cameras = io.read_cameras(path)
        if isinstance(cameras, Camera):
            return cameras
    except ImportError:
        pass
    try:
        return Camera.from_dict(json.loads(path.read_text()), source=str(path))
    except (OSError, json.JSONDecodeError) as e:
        raise InvalidInputError(f"{path}: cannot read a camera: {e}") from None


def run(args: argparse.Namespace) -> int:
    from service.client import Client, ServiceError

    camera = read_camera(args.camera)
    failures = 0
    with Client(args.connect, map_name=args.map, config_file=args.zenoh_config) as client:
        for path in args.images:
            try:
                reg = client.localize(path, camera, timeout=args.timeout, return_matches=args.matches)
                record = {"image": str(path), **reg.to_dict()}
            except (ServiceError, OSError) as e:
                failures += 1
                record = {"image": str(path), "error": getattr(e, "code", "io"), "message": str(e)}
            print(json.dumps(record), flush=True)
    print(f"{len(args.images) - failures}/{len(args.images)} images answered", file=sys.stderr)
    return 1 if failures else 0
