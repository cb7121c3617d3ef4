"""The compiled kernels' disk cache kept consistent with the source it was compiled from.

numba caches each ``cache=True`` kernel next to its module (``__pycache__/*.nbi``, ``*.nbc``) and checks
only that module's own file when it loads one: a kernel that calls a kernel of another module keeps the
callee it was compiled with after that other module changes. Editing ``score.py`` left ``search.py``'s
local solve running the old pair test (session 57: an experiment measured nothing until the cache was
emptied by hand). So on import the package compares a fingerprint of its sources (each ``.py`` file's
path, size and modification time) with the one its cache was filled under, and empties the cache when
they differ: every kernel then compiles once from the code as it is (``warm.warm_up``).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

STAMP = "linereg-sources.stamp"  # in the package's top __pycache__, beside the cached kernels


def fingerprint(package: Path) -> str:
    """Returns a hex digest of every ``.py`` file under ``package``: relative path, size, mtime (ns)."""
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        stat = path.stat()
        digest.update(f"{path.relative_to(package)}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def clear_stale(package: Path = Path(__file__).parent) -> bool:
    """Empties ``package``'s (this one's by default) kernel cache (its ``__pycache__/*.nbi``, ``*.nbc``) when its sources changed
    since the cache was filled, and records their fingerprint. Returns True if it emptied the cache. A
    package it cannot write to (a read-only install) is left alone: numba then caches elsewhere or not."""
    try:
        stamp = package / "__pycache__" / STAMP
        now = fingerprint(package)
        if stamp.is_file() and stamp.read_text() == now:
            return False
        for cached in package.rglob("__pycache__/*.nb[ic]"):
            cached.unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        partial = stamp.with_name(f"{STAMP}.{os.getpid()}")
        partial.write_text(now)
        partial.replace(stamp)  # whole or not at all: processes starting together read one stamp
        return True
    except OSError:
        return False
