"""``python -m service --map MAP``: the same as ``linereg serve``."""

from __future__ import annotations

import argparse
import sys

from . import logs, server
from .options import add_arguments, config_from_args


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service", description="linereg localization service")
    add_arguments(parser)
    args = parser.parse_args(argv)
    logs.configure(json_lines=not args.plain_logs)
    return server.run(config_from_args(args))


if __name__ == "__main__":
    sys.exit(main())
