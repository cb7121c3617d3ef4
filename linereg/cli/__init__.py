"""``linereg`` command line: one module per subcommand, each with ``add_parser(subparsers)``.

Only entry points configure logging and print; user errors (LineregError) end with a one-line message
and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from ..errors import LineregError

# subcommand -> module under linereg.cli (serve/query live in the service layer, imported only when run)
SUBCOMMANDS = ("demo", "bench", "map", "localize", "serve", "query")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="linereg",
        description="Camera pose in an untextured 3D point-cloud map from line segments alone.",
        epilog="Start with `linereg demo`; `linereg COMMAND --help` for each command.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"linereg.cli.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"linereg.cli.{name}":
                raise
            continue
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except LineregError as e:
        print(f"linereg {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
