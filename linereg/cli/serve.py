"""``linereg serve``: run the zenoh localization service of one line map.

Examples:
  linereg serve --map site.linemap --workers 4    # listens on tcp/127.0.0.1:7447
  linereg query --camera camera.json photo.png    # a client, from another terminal

Clients reach it at linereg/<map>/localize.
"""

from __future__ import annotations

import argparse

from service.options import DEFAULT_ENGINE, add_arguments, config_from_args


def add_parser(subparsers) -> None:
    from . import description

    parser = subparsers.add_parser(
        "serve",
        help="serve a map over zenoh",
        description=description(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging

    from service import logs, server  # the service layer (zenoh) only when serving: linereg never imports it

    from ..map.linemap import check_map_file

    if args.engine == DEFAULT_ENGINE:  # a test engine may take no map file
        check_map_file(args.map)  # a wrong --map in one line, before workers and a session start

    logs.configure(
        logging.getLogger().getEffectiveLevel() if args.verbose else logging.INFO, not args.plain_logs
    )
    return server.run(config_from_args(args))
