"""``linereg`` command line: one module per subcommand, each with ``add_parser(subparsers)``.

A subcommand's ``--help`` shows its module docstring through ``description`` (reST literals made plain).

Only entry points configure logging and print; user errors (LineregError) end with a one-line message
and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from pathlib import Path

from ..errors import InvalidInputError, LineregError

# subcommand -> module under linereg.cli (serve/query live in the service layer, imported only when run)
SUBCOMMANDS = ("demo", "bench", "map", "localize", "calibrate", "track", "colorize", "serve", "query")


def description(doc: str | None) -> str:
    """Returns a module docstring as ``--help`` text: without reST's double backticks around literals."""
    return (doc or "").replace("``", "")


def check_output_file(flag: str, path: Path) -> None:
    """Raises InvalidInputError naming ``flag`` unless ``path`` can become a file (checked before any work)."""
    if path.is_dir():
        raise InvalidInputError(f"{flag} {path}: is a directory; give a file name")
    _check_writable_parent(flag, path, path.parent)


def check_output_dir(flag: str, path: Path) -> None:
    """Raises InvalidInputError naming ``flag`` unless ``path`` is or can become a writable directory."""
    if path.exists() and not path.is_dir():
        raise InvalidInputError(f"{flag} {path}: is an existing file; give a directory")
    _check_writable_parent(flag, path, path)


def _check_writable_parent(flag: str, path: Path, folder: Path) -> None:
    """The closest existing ancestor of ``folder`` (itself included) must be a directory we may write in."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise InvalidInputError(f"{flag} {path}: {existing} is a file, not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InvalidInputError(f"{flag} {path}: cannot write in {existing} (permission denied)")


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
