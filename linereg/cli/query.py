"""``linereg query``: localize images through a running service (``linereg serve``), one JSON line each.

Example:
  linereg query --connect tcp/127.0.0.1:7447 --map site --camera cameras.json photos/*.png > poses.jsonl

Prints one JSON object per image on stdout: {"image": path, ...the Registration...}, or {"image": path,
"error": code, "message": ...} when no pose came back. The camera file is read as by ``linereg localize``:
one shared camera, one per image (by path, file name or stem), or a COLMAP cameras.txt.

``--prior FILE`` (``--prior-sigma DEG M``) sends what is known of each pose, read as by ``linereg
localize``: a JSON prior for every image or per image, or a TUM file of rough poses.

An image that cannot be used (unreadable, corrupt, another size than its camera, refused by the service
as bad input) is named on stderr and the others are still sent; the exit code is then 2. When the service
did not answer some images (busy, timeout, internal error) the exit code is 1.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import InvalidInputError, LineregError
from . import description
from .localize import add_prior_arguments, read_prior_arguments, tum_timestamps

INPUT_ERRORS = ("bad_request", "too_large")  # service error codes about the image itself


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "query",
        help="localize images through a running service",
        description=description(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="image files (PNG, JPEG, ...)")
    parser.add_argument(
        "--connect", action="append", help="router endpoint (repeatable; default tcp/127.0.0.1:7447)"
    )
    parser.add_argument("--map", help="map name (default: the only map being served)")
    parser.add_argument(
        "--camera",
        required=True,
        type=Path,
        help="camera JSON (shared or per image) or COLMAP cameras.txt, as for `linereg localize`",
    )
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds per image (default 10)")
    parser.add_argument("--zenoh-config", help="zenoh json5 config file (TLS, credentials)")
    parser.add_argument("--matches", action="store_true", help="also return the 2D-3D matches")
    add_prior_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .. import io

    if not args.timeout > 0:
        raise InvalidInputError(f"--timeout must be > 0 seconds, got {args.timeout}")
    _check_map_name(args.map)
    missing = [str(p) for p in args.images if not p.is_file()]
    if missing:  # as in `linereg localize`: a typo is said before anything is sent
        raise InvalidInputError(f"image file(s) not found: {', '.join(missing[:5])}")
    cameras = io.read_cameras(args.camera)
    priors = read_prior_arguments(args, args.images, tum_timestamps(args.images))
    jobs = [
        (path, io.camera_for_image(cameras, path, args.camera), prior)
        for path, prior in zip(args.images, priors, strict=True)
    ]
    bad, failed = [], 0
    with _connect(args) as client:
        _check_served(client)
        for path, camera, prior in jobs:
            record = _query_one(client, path, camera, prior, args)
            print(json.dumps(io.jsonable(record), allow_nan=False), flush=True)
            if record.get("input_error"):
                bad.append(record["message"])
            elif "error" in record:
                failed += 1
    answered = len(jobs) - len(bad) - failed
    print(f"{answered}/{len(jobs)} images answered", file=sys.stderr)
    for message in bad:
        print(f"linereg query: error: {message}", file=sys.stderr)
    return 2 if bad else 1 if failed else 0


def _query_one(client, path: Path, camera, prior, args: argparse.Namespace) -> dict:
    """Returns the JSON record of one image: its Registration, or the error that stopped it."""
    import zenoh

    from service.client import ServiceError

    try:
        image = _wire_image(path, camera)
        reg = client.localize(image, camera, prior, timeout=args.timeout, return_matches=args.matches)
    except zenoh.ZError as e:  # the session broke (router gone): this image is not answered
        return {"image": str(path), "error": "unreachable", "message": f"{path}: {e}"}
    except ServiceError as e:
        record = {"image": str(path), "error": e.code, "message": f"{path}: {e.message}"}
        return record | {"input_error": True} if e.code in INPUT_ERRORS else record
    except LineregError as e:  # a file this side cannot use: named, and the batch goes on
        message = str(e) if str(path) in str(e) else f"{path}: {e}"
        return {"image": str(path), "error": "bad_input", "message": message, "input_error": True}
    return {"image": str(path), **reg.to_dict()} | ({} if prior is None else {"prior": prior.to_dict()})


def _wire_image(path: Path, camera):
    """Returns what is sent for an image file: its bytes (PNG, JPEG), else its decoded pixels.

    The file is decoded here first, so that a missing, empty or corrupt file or one of another size than
    its camera is named at once, as by ``linereg localize``.
    """
    from .. import io

    pixels = io.read_image(path)
    height, width = pixels.shape[:2]
    if (width, height) != (camera.width, camera.height):
        raise InvalidInputError(
            f"{path}: image is {width}x{height} px but the camera is {camera.width}x{camera.height}"
        )
    from protocols.images import JPEG_MAGIC, PNG_MAGIC

    data = path.read_bytes()
    return data if data.startswith((PNG_MAGIC, JPEG_MAGIC)) else pixels


def _check_served(client) -> None:
    """Says "no service for map X" at once (liveliness), rather than after a timeout per image."""
    from service.client import ServiceError

    try:
        client.check_served()
    except ServiceError as e:
        raise LineregError(e.message) from None


def _check_map_name(name: str | None) -> None:
    from protocols import keys

    if name is None:
        return
    try:
        keys.check_chunk(name, "--map")
    except ValueError as e:
        raise InvalidInputError(str(e)) from None


def _connect(args: argparse.Namespace):
    """Returns an open Client; a LineregError naming the endpoints when no session can be opened."""
    import zenoh

    from service.client import Client
    from service.zconfig import DEFAULT_ENDPOINT

    try:
        return Client(args.connect, map_name=args.map, config_file=args.zenoh_config)
    except zenoh.ZError as e:
        where = ", ".join(args.connect) if args.connect else (args.zenoh_config or DEFAULT_ENDPOINT)
        detail = str(e).split("  at ")[0].strip()  # zenoh appends its Rust source location
        raise LineregError(
            f"cannot connect to {where}: {detail} (is `linereg serve` or a zenoh router running there?)"
        ) from None
