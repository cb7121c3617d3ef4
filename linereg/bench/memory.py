"""Peak resident memory of this process and every process it starts, sampled while a benchmark runs.

``resource.getrusage(RUSAGE_CHILDREN)`` only counts children this process has waited for: workers started
by a fork server (or spawned by it) are the fork server's children, never reaped by us, and read 0. So a
thread reads ``/proc`` every ``interval_s`` instead: each descendant's ``VmHWM`` (the kernel's own peak
RSS of that process, so a short peak between two samples still counts while the process lives) and the
sum of their current ``VmRSS`` (the tree's footprint at that moment). Linux only; elsewhere the
descendants read as unknown (NaN) and only this process's ``ru_maxrss`` is reported.

    with PeakMemory() as peak:
        run()
    peak.result()  # {"parent_mb": ..., "largest_child_mb": ..., "tree_mb": ..., "children": ...}
"""

from __future__ import annotations

import math
import os
import resource
import sys
import threading
from pathlib import Path

PROC = Path("/proc")


class PeakMemory:
    """A context manager sampling the memory of this process tree in a thread (see the module doc)."""

    def __init__(self, interval_s: float = 0.1) -> None:
        self.interval_s = interval_s
        self.child_peak_kib: dict[int, int] = {}  # pid -> VmHWM, the largest seen
        self.tree_kib = 0  # the largest sum of VmRSS over the tree in one sample
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="peak-memory", daemon=True)
        self.supported = sys.platform.startswith("linux") and PROC.is_dir()

    def __enter__(self) -> PeakMemory:
        if self.supported:
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.supported:
            self._stop.set()
            self._thread.join()

    def _run(self) -> None:
        while True:
            self.sample()
            if self._stop.wait(self.interval_s):
                break

    def sample(self) -> None:
        """Reads the tree once: each descendant's peak, and the tree's current total."""
        me = os.getpid()
        total = _status_kib(me).get("VmRSS", 0)
        for pid in descendants(me):
            status = _status_kib(pid)
            if not status:
                continue  # ended meanwhile
            total += status.get("VmRSS", 0)
            self.child_peak_kib[pid] = max(self.child_peak_kib.get(pid, 0), status.get("VmHWM", 0))
        self.tree_kib = max(self.tree_kib, total)

    def result(self) -> dict[str, float]:
        """Returns peak RSS in MB (2^20 bytes): this process, the largest descendant, the whole tree at
        once (NaN where unknown), and how many descendants were seen."""
        parent_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        if not self.supported:
            return {"parent_mb": parent_mb, "largest_child_mb": math.nan, "tree_mb": math.nan, "children": 0}
        return {
            "parent_mb": parent_mb,
            "largest_child_mb": max(self.child_peak_kib.values(), default=0) / 1024,
            "tree_mb": self.tree_kib / 1024,
            "children": len(self.child_peak_kib),
        }


def descendants(root: int) -> list[int]:
    """Returns the pids of every process below ``root`` (children, theirs, ...), from ``/proc/*/stat``."""
    children: dict[int, list[int]] = {}
    for entry in PROC.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue  # ended meanwhile
        # "pid (comm) state ppid ...": comm may hold spaces and parentheses, so split after the last ')'
        ppid = int(stat[stat.rindex(")") + 2 :].split()[1])
        children.setdefault(ppid, []).append(int(entry.name))
    found, todo = [], [root]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def _status_kib(pid: int) -> dict[str, int]:
    """Returns the ``kB`` fields of ``/proc/PID/status`` (VmRSS, VmHWM, ...), {} if the process ended."""
    try:
        lines = (PROC / str(pid) / "status").read_text().splitlines()
    except OSError:
        return {}
    out = {}
    for line in lines:
        key, _, value = line.partition(":")
        if value.endswith(" kB"):
            out[key] = int(value[:-3])
    return out
