"""Service counters and latency percentiles (what the ``stats`` queryable answers)."""

from __future__ import annotations

import threading
import time
from collections import Counter, deque

import numpy as np


class Stats:
    """Thread-safe outcome counters and the latencies of the last ``window`` replies."""

    def __init__(self, window: int = 2000) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()
        self._latencies_ms: deque[float] = deque(maxlen=window)
        self._started = time.time()

    def record(self, outcome: str, latency_ms: float) -> None:
        """Counts one answered request: ``outcome`` = ok | not_localized | an error code."""
        with self._lock:
            self._counts[outcome] += 1
            self._latencies_ms.append(latency_ms)

    def snapshot(self, **gauges: object) -> dict:
        """Returns counters, latency percentiles (ms) and the given gauges (queue depth, workers, ...)."""
        with self._lock:
            counts, lat = dict(self._counts), np.array(self._latencies_ms)
        percentiles = {f"p{q}": float(np.percentile(lat, q)) for q in (50, 90, 99)} if len(lat) else {}
        return {
            "uptime_s": time.time() - self._started,
            "requests": sum(counts.values()),
            "outcomes": counts,
            "latency_ms": percentiles | {"max": float(lat.max())} if len(lat) else {},
            **gauges,
        }
