"""Per-stage wall-clock timings for ``Registration.timings``."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager


class StageTimer:
    """Accumulates seconds per stage name: ``with timer("rotation"): ...``; ``timer.seconds`` is the dict."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._start = time.perf_counter()

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - start

    def finish(self) -> dict[str, float]:
        """Returns the stage timings plus ``total`` since construction."""
        return self.seconds | {"total": time.perf_counter() - self._start}
