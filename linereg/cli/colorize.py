"""``linereg colorize``: colour a point cloud from localized photos (a .ply or .las / .laz copy of it).

Example:
  linereg localize --map site.linemap --camera camera.json photos/*.jpg --out poses.json
  linereg colorize scan.laz --poses poses.json --camera camera.json -o scan_rgb.laz --workers 2

Every point takes its colour from the photos that see it: visibility from a depth buffer of the cloud
itself (a point behind a pillar never takes the pillar's colour), colours weighted for viewing angle,
range, image border and blur, exposure differences between photos compensated. The output keeps every
point in the input's order and adds ``red green blue`` and ``photo_count``, the number of photos that
coloured the point: 0 flags a point no photo sees (its RGB 0 is no colour, not black).

The cloud is streamed in chunks (LAS / LAZ by laspy, binary PLY memory-mapped) in two passes, depth
buffers then colours, so memory stays bounded whatever its size. ``--scheduler ADDRESS`` runs the passes
on an existing Dask cluster whose workers see the cloud under the same path. The output appears only
when complete (a temporary file in its folder until then).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..errors import InvalidInputError
from . import check_output_file, description
from .progress import Progress

OUTPUT_SUFFIXES = (".ply", ".las", ".laz")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "colorize",
        help="colour a point cloud from localized photos",
        description=description(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("cloud", type=Path, metavar="CLOUD", help="point cloud (.ply, .las, .laz, ...)")
    p.add_argument("--poses", required=True, type=Path, help="poses JSON as `linereg localize --out` writes")
    p.add_argument(
        "--camera", required=True, type=Path, help="camera JSON (shared or per image) or COLMAP cameras.txt"
    )
    p.add_argument("--images", type=Path, metavar="DIR", help="find the photos here by file name")
    p.add_argument("-o", "--out", required=True, type=Path, help="coloured cloud: .ply, .las or .laz")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run on this dask.distributed scheduler (tcp://host:8786) instead of local processes",
    )
    p.add_argument("--config", type=Path, help="JSON file of colorize overrides, nested per section")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .. import batch, io
    from ..color.config import ColorizeConfig
    from ..colorization import colorize_file, read_localized_photos

    if args.workers < 1:
        raise InvalidInputError(f"--workers must be >= 1, got {args.workers}")
    check_output(args.out)
    config = ColorizeConfig()
    if args.config:
        try:
            config = ColorizeConfig.from_dict(io.read_json(args.config))
        except InvalidInputError as e:
            raise InvalidInputError(f"{args.config}: {e}") from None
    if args.images is not None and not args.images.is_dir():
        raise InvalidInputError(f"--images {args.images}: not a directory")
    io.open_cloud(args.cloud).close()  # readable, a known format, at least one point: before any work
    photos = read_localized_photos(args.poses, args.camera, args.images)
    start = time.perf_counter()
    with batch.runner(args.workers, args.scheduler, fork=False) as runner, _PassBars() as bars:
        histogram = colorize_file(args.cloud, args.out, photos, config, runner, bars)
    total = int(histogram.sum())
    print(
        f"coloured {total - int(histogram[0])}/{total} points from {len(photos)} photos "
        f"in {time.perf_counter() - start:.1f} s -> {args.out} ({int(histogram[0])} seen by no photo: "
        "photo_count 0)",
        file=sys.stderr,
    )
    return 0


def check_output(out: Path) -> None:
    """Raises InvalidInputError unless ``out`` is a .ply / .las / .laz file name in an existing folder."""
    if out.suffix.lower() not in OUTPUT_SUFFIXES:
        raise InvalidInputError(f"-o {out}: write the coloured cloud as {', '.join(OUTPUT_SUFFIXES)}")
    if not out.parent.is_dir():
        raise InvalidInputError(f"-o {out}: the folder {out.parent} does not exist")
    check_output_file("-o", out)


class _PassBars:
    """A progress bar per pass of ``colorize_file`` (its ``progress`` callback)."""

    def __init__(self) -> None:
        self.bar: Progress | None = None
        self.name = ""

    def __call__(self, name: str, done: int, total: int) -> None:
        if name != self.name:
            self.close()
            self.bar, self.name = Progress(total, name), name
        assert self.bar is not None
        self.bar.update(done - self.bar.done)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> _PassBars:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
