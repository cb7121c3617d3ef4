"""``linereg bench <name>``: benchmarks, one sub-subcommand each, registered from a table.

To add a benchmark, add one line to ``BENCHMARKS``: ``name -> "module:function"``. The module is imported
when the parser is built (keep its top-level imports light: import matplotlib, poselib, ... inside
functions) and ``function(parser)`` receives the ``argparse.ArgumentParser`` of ``linereg bench <name>``:
it adds its own arguments and must call ``parser.set_defaults(func=run)`` with ``run(args) -> int``.
The help line of ``linereg bench --help`` is the first line of the module's docstring. A module that does
not exist yet is skipped, so entries may be listed before their code lands.
"""

from __future__ import annotations

import argparse
import importlib

from . import description

BENCHMARKS: dict[str, str] = {
    "synthetic": "linereg.bench.synthetic:configure",
    "demo": "linereg.bench.demo:configure",
    "service": "linereg.bench.service:configure",
    "lines2d": "linereg.bench.lines2d:configure",
    "lines3d": "linereg.bench.lines3d:configure",
    "real": "linereg.bench.real:configure",
    "sequence": "linereg.bench.sequence:configure",
    "colorize": "linereg.bench.colorize:configure",
    "large": "linereg.bench.large:configure",
    "calibrate": "linereg.bench.calibrate:configure",
}


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers ``bench`` and one sub-subcommand per importable entry of BENCHMARKS."""
    parser = subparsers.add_parser(
        "bench",
        help="run a benchmark, print a table, write results and plots",
        description="Runs one benchmark: it prints a table and writes its results and plots. "
        "`linereg bench BENCHMARK --help` says what each measures.",
    )
    sub = parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    for name, target in BENCHMARKS.items():
        module_name, _, function = target.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as e:
            if e.name != module_name:  # the module exists but one of its imports is missing: a real bug
                raise
            continue
        help_line = description(module.__doc__ or name).strip().splitlines()[0]
        getattr(module, function)(
            sub.add_parser(
                name,
                help=help_line,
                description=description(module.__doc__),
                formatter_class=argparse.RawDescriptionHelpFormatter,
            )
        )
