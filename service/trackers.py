"""The tracking sessions of one worker process: a tracker per session, made on the session's first frame.

The service process routes every frame of a session to the same worker (``sessions.SessionTable``) in a
track job: ``b"S"``, a 4-byte big-endian header length, the header (a msgpack ``track_job``: op, session,
the ``session_open`` message, frames answered so far) and the client's ``track_request`` bytes. A worker
that has no tracker for the session (it is new, or replaced a dead worker) makes one from the open
message; when the session had answered frames already, the reply says ``restarted``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

import protocols
from linereg.camera import Camera
from linereg.errors import InvalidInputError
from protocols import Limits, session

from .engine import Engine
from .handlers import decode_pixels, error_bytes, guarded, reply_of

log = logging.getLogger(__name__)
TRACK_JOB = b"S"  # the first byte of a track job (never the first byte of a msgpack map)


def track_job(
    op: str, session_id: str, open_payload: bytes = b"", frames: int = 0, request: bytes = b""
) -> bytes:
    """Returns the pipe bytes of a track job: ``op`` "step" (a track_request) or "drop" (free the tracker)."""
    header = protocols.pack(
        "track_job", {"op": op, "session": session_id, "open": open_payload, "frames": frames}
    )
    return TRACK_JOB + len(header).to_bytes(4, "big") + header + request


@dataclass
class _Tracked:
    tracker: Any  # engine.tracker(line_map, camera): linereg.Tracker or a stand-in
    camera: Camera
    next_frame: int  # the index of the session's next frame
    restarted: bool  # made for a session that had frames: said in the next reply


class Trackers:
    """The trackers of the sessions routed to this worker, by session id."""

    def __init__(self, engine: Engine, limits: Limits) -> None:
        self.engine, self.limits = engine, limits
        self._sessions: dict[str, _Tracked] = {}

    def __len__(self) -> int:
        return len(self._sessions)

    def handle(self, job: bytes) -> bytes:
        """Returns the reply bytes of a track job (a track_reply or an error; never raises)."""
        size = int.from_bytes(job[1:5], "big")
        try:
            header = protocols.unpack(job[5 : 5 + size])
        except protocols.ProtocolError as e:  # only a bug of the service process can get here
            return error_bytes("internal", f"unreadable track job: {e.message}")
        request = job[5 + size :]
        if header.get("op") == "drop":
            self._sessions.pop(header["session"], None)
            return protocols.pack("dropped", {"session": header["session"]})  # nobody waits for this answer
        return guarded(protocols.request_id(request), lambda: self._step(header, request))

    def _step(self, header: dict, request: bytes) -> bytes:
        """Returns the track_reply bytes of one frame; raises on bad input (the tracker is as it was)."""
        session_id = header["session"]
        tracked = self._tracked(header)
        req = session.decode_track_request(request, tracked.camera, self.limits)
        frame = req.segments
        if frame is None:
            frame = decode_pixels(req.image, req.image_format, tracked.camera)
        try:
            reg = tracked.tracker.step(frame, req.relative_pose, req.timestamp)
        except InvalidInputError:
            raise
        except Exception:
            self._sessions.pop(
                session_id, None
            )  # a tracker in an unknown state: the next frame makes another
            raise
        reply = reply_of(req.id, reg, self.engine, req.return_matches)
        answer = session.TrackReply(reply, session_id, tracked.next_frame, str(tracked.tracker.event),
                                    tracked.restarted)  # fmt: skip
        tracked.next_frame, tracked.restarted = tracked.next_frame + 1, False
        return session.encode_track_reply(answer)

    def _tracked(self, header: dict) -> _Tracked:
        """Returns the session's tracker, made from its open message if this worker has none; at the
        ``start`` pose only for the session's first frame (a restarted session relocalizes globally)."""
        found = self._sessions.get(header["session"])
        if found is not None:
            return found
        if self.engine.tracker is None:
            raise protocols.ProtocolError("not_found", "this service's engine tracks no sessions")
        opened = session.decode_session_open(header["open"], self.limits)
        tracker = self.engine.tracker(self.engine.line_map, opened.camera)
        start, frames = opened.start, int(header["frames"])
        if start is not None and start.cam_from_world is not None and frames == 0:
            tracker.start_at(np.asarray(start.cam_from_world), start.sigma_rot_deg, start.sigma_pos_m)
        found = _Tracked(tracker, opened.camera, frames, restarted=frames > 0)
        self._sessions[header["session"]] = found
        return found
