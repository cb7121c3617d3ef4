"""Benchmarks of linereg: each module runs one experiment, prints a table and writes results + plots.

- ``synthetic``: the paper's Monte-Carlo sweeps (section IV-A) for ours, the RANSAC-6 baseline and the
  known-correspondence oracle.
- ``report``: shared statistics, tables, atomic writes, plots and the progress bar.

Run them through the CLI (``linereg bench <name> --help``); see ``linereg.cli.bench`` to add one.
"""
