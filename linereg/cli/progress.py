"""A dependency-free progress bar on stderr for entry points (library code only logs)."""

from __future__ import annotations

import sys
import time


class Progress:
    """``Progress(total, label)``; ``update(n, note)``; ``close()``. One line per step when not on a TTY."""

    def __init__(self, total: int, label: str, stream=None) -> None:
        self.total, self.label, self.done = max(total, 0), label, 0
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.monotonic()

    def update(self, n: int = 1, note: str = "") -> None:
        self.done += n
        elapsed = time.monotonic() - self.start
        eta = elapsed / self.done * (self.total - self.done) if self.done else 0.0
        if self.tty:
            width = 28
            filled = int(width * self.done / self.total) if self.total else width
            bar = "#" * filled + "-" * (width - filled)
            line = (
                f"\r{self.label} [{bar}] {self.done}/{self.total} {elapsed:5.1f}s eta {eta:4.0f}s {note[:40]}"
            )
            self.stream.write(line.ljust(100))
        else:
            self.stream.write(f"{self.label} {self.done}/{self.total} {elapsed:.1f}s {note}\n")
        self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
