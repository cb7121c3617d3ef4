"""linereg's network service over zenoh: ``Service`` (queryables + worker pool) and ``Client``.

Run it with ``linereg serve --map MAP`` or ``python -m service --map MAP``. The names below load on first
use: ``service.options`` (the flags, which ``linereg``'s command line lists) must not start zenoh.
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "Client": "service.client",
    "ServiceError": "service.client",
    "TrackingSession": "service.client",
    "Service": "service.server",
    "ServiceConfig": "service.server",
    "run": "service.server",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module 'service' has no attribute {name!r}")
    return getattr(importlib.import_module(_LAZY[name]), name)
