"""The instance's tracking sessions, as the service process sees them: ids, worker slots, expiry, caps.

The trackers live in the workers (``trackers.py``); this table fixes which worker slot holds each session
(the one with the fewest sessions when it opens), so that every frame of a session reaches the same
worker, and keeps what a replacement worker needs to make the tracker again (the ``session_open``
message). Thread-safe: the zenoh handler threads and the reply callbacks share it.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass

from linereg.camera import Camera
from protocols import ProtocolError


@dataclass
class Session:
    """One open session: its worker slot, camera and open message, and its use."""

    id: str
    slot: int
    camera: Camera
    open_payload: bytes  # the session_open message (a replacement worker makes the tracker from it)
    last_used: float  # clock seconds of the last message received or answered
    frames: int = 0  # frames answered
    in_flight: int = 0  # frames sent to the worker and not answered yet (never expires meanwhile)


@dataclass(frozen=True)
class SessionLimits:
    """How long an idle session lives and how many there may be (``linereg serve`` flags)."""

    idle_timeout_s: float = 60.0
    max_sessions: int = 64  # on this instance
    per_worker: int = 32  # on one worker process

    def __post_init__(self) -> None:
        if not (self.idle_timeout_s > 0 and self.max_sessions >= 1 and self.per_worker >= 1):
            raise ValueError(f"session limits must be positive, got {self}")


class SessionTable:
    """The open sessions of an instance with ``workers`` worker slots."""

    def __init__(
        self, workers: int, limits: SessionLimits, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.workers, self.limits, self.clock = workers, limits, clock
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()
        self.opened = self.expired = 0

    def open(self, camera: Camera, open_payload: bytes) -> Session:
        """Returns a new session on the slot holding the fewest; ProtocolError("busy") at a cap."""
        with self._lock:
            counts = self._per_slot()
            slot = min(range(self.workers), key=lambda i: counts[i])
            if len(self._sessions) >= self.limits.max_sessions or counts[slot] >= self.limits.per_worker:
                raise ProtocolError(
                    "busy",
                    f"tracking sessions are at their cap ({len(self._sessions)} open, at most "
                    f"{self.limits.max_sessions} in all and {self.limits.per_worker} per worker)",
                )
            found = Session(uuid.uuid4().hex[:16], slot, camera, open_payload, self.clock())
            self._sessions[found.id] = found
            self.opened += 1
            return found

    def begin(self, session_id: str) -> Session:
        """Returns the open session ``session_id`` with one more frame in flight; ProtocolError
        ("unknown_session") if it is not open (closed, expired, never opened)."""
        with self._lock:
            found = self._get(session_id)
            found.in_flight += 1
            found.last_used = self.clock()
            return found

    def end(self, found: Session, answered: bool) -> None:
        """Records the reply of a frame ``begin`` started (``answered``: a track_reply, not an error)."""
        with self._lock:
            found.in_flight -= 1
            found.frames += int(answered)
            found.last_used = self.clock()

    def close(self, session_id: str) -> Session:
        """Returns the session ``session_id``, removed; ProtocolError("unknown_session") if not open."""
        with self._lock:
            return self._sessions.pop(self._get(session_id).id)

    def expire(self) -> list[Session]:
        """Returns the sessions idle for longer than the timeout (none with a frame in flight), removed."""
        with self._lock:
            now = self.clock()
            idle = [
                s
                for s in self._sessions.values()
                if not s.in_flight and now - s.last_used > self.limits.idle_timeout_s
            ]
            for s in idle:
                del self._sessions[s.id]
            self.expired += len(idle)
            return idle

    def slot_of(self, session_id: str) -> int:
        """Returns the worker slot holding an open session; ProtocolError("unknown_session") otherwise."""
        with self._lock:
            return self._get(session_id).slot

    def snapshot(self) -> dict:
        """Returns the session counters of the stats document."""
        with self._lock:
            return {"open": len(self._sessions), "opened": self.opened, "expired": self.expired,
                    "per_worker": self._per_slot()}  # fmt: skip

    def _get(self, session_id: str) -> Session:
        found = self._sessions.get(session_id)
        if found is None:
            raise ProtocolError(
                "unknown_session",
                f"no tracking session {session_id[:64]!r} here (never opened, closed, or idle for more than "
                f"{self.limits.idle_timeout_s:g} s): open a new one",
            )
        return found

    def _per_slot(self) -> list[int]:
        counts = [0] * self.workers
        for s in self._sessions.values():
            counts[s.slot] += 1
        return counts
