"""The progress bar of every entry point (CLI commands, benchmarks): tqdm on stderr; library code only logs."""

from __future__ import annotations

import sys
import time
from typing import IO


class Progress:
    """``Progress(total, label)``; ``update(n, note)``; ``note(line)``; ``close()``.

    On a terminal, a tqdm bar with the last note after it. Elsewhere (a log file, a pipe) no bar: with
    ``log_steps`` one line per update that carries a note, else nothing; ``note`` lines are printed in
    both cases (above the bar on a terminal).
    """

    def __init__(
        self, total: int, label: str = "", stream: IO[str] | None = None, log_steps: bool = False
    ) -> None:
        from tqdm import tqdm

        self.stream = stream if stream is not None else sys.stderr
        self.total, self.label, self.done, self.log_steps = max(total, 0), label, 0, log_steps
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._start = time.monotonic()
        self._bar = tqdm(
            total=self.total, desc=label or None, file=self.stream, disable=not self.tty, dynamic_ncols=True
        )

    def update(self, n: int = 1, note: str = "") -> None:
        """Counts ``n`` more finished units (0: only show ``note``, e.g. the stage that starts)."""
        self.done += n
        if note:
            self._bar.set_postfix_str(note[:40], refresh=False)
        self._bar.update(n)
        if n == 0:
            self._bar.refresh()
        if note and self.log_steps and not self.tty:
            elapsed = time.monotonic() - self._start
            prefix = f"{self.label} " if self.label else ""
            self.stream.write(f"{prefix}{self.done}/{self.total} {elapsed:.1f}s {note}\n")
            self.stream.flush()

    def advance(self, label: str = "", n: int = 1) -> None:
        """``update(n, label)`` under the name the benchmarks use."""
        self.update(n, label)

    def note(self, line: str) -> None:
        """Prints a line (above the bar on a terminal)."""
        self._bar.write(line, file=self.stream)

    def close(self) -> None:
        self._bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
