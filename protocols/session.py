"""Tracking sessions on the wire (SPEC.md, "Tracking sessions"): open, one ``track_request`` per frame, close.

A session's state (the tracker) lives in one worker of one instance: the ``session_opened`` reply names the
instance, and every later message of the session goes to that instance's session key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from linereg.camera import Camera

from .arrays import decode_array, encode_array
from .codec import (
    decode_camera,
    decode_frame,
    decode_options,
    decode_prior,
    encode_prior,
    expect,
    frame_fields,
    options_fields,
    pack,
    reply_fields,
    reply_of,
    unpack,
)
from .errors import ProtocolError
from .fields import number, optional, require, text
from .messages import PROTOCOL_VERSION, Limits, LocalizeReply, Prior

_DEFAULT_LIMITS = Limits()
MAX_SESSION_CHARS = 64
# how a tracked frame's pose was obtained (``linereg.Tracker.event``)
HOW = ("initialized", "tracked", "relocalized", "predicted", "lost")


@dataclass(frozen=True)
class SessionOpen:
    """Opens a tracking session for one camera; ``start``: a pose prior (``cam_from_world`` (4, 4) float64
    with ``sigma_rot_deg``, ``sigma_pos_m``) where tracking begins, or None (the first frame is registered
    globally)."""

    id: str
    camera: Camera
    start: Prior | None = None
    version: int = PROTOCOL_VERSION


@dataclass(frozen=True)
class SessionOpened:
    """The service's answer to SessionOpen: the session id and the instance that holds it."""

    id: str
    session: str
    instance: str
    idle_timeout_s: float
    map_name: str = ""
    map_version: str = ""
    map_id: str = ""
    version: int = PROTOCOL_VERSION


@dataclass(frozen=True)
class TrackRequest:
    """One frame of a session: exactly one of ``image`` (as in LocalizeRequest) and ``segments`` ((N, 4)
    float64 pixels); ``relative_pose``: (4, 4) float64 measured ``cam_prev_from_cam_this`` (odometry since
    the session's previous frame) or None; ``timestamp``: seconds, increasing, or None."""

    id: str
    session: str
    image: bytes | np.ndarray | None = None
    image_format: str = ""
    segments: np.ndarray | None = None
    relative_pose: np.ndarray | None = None
    timestamp: float | None = None
    deadline_ms: int | None = None
    return_matches: bool = False
    version: int = PROTOCOL_VERSION


@dataclass(frozen=True)
class TrackReply:
    """The pose of one frame (``reply``: as a LocalizeReply) and how it was obtained (``how``, one of HOW);
    ``frame``: the frame's 0-based index in the session; ``restarted``: the session's tracker was recreated
    (its worker was lost) and this frame was registered globally."""

    reply: LocalizeReply
    session: str
    frame: int
    how: str
    restarted: bool = False


@dataclass(frozen=True)
class SessionClose:
    """Ends a session (its tracker is freed)."""

    id: str
    session: str
    version: int = PROTOCOL_VERSION


@dataclass(frozen=True)
class SessionClosed:
    """The answer to SessionClose: the number of frames the session answered."""

    id: str
    session: str
    frames: int
    version: int = PROTOCOL_VERSION


def encode_session_open(msg: SessionOpen) -> bytes:
    """Returns the wire bytes of a SessionOpen."""
    body: dict = {"id": msg.id, "camera": msg.camera.to_dict()}
    if msg.start is not None:
        body["start"] = encode_prior(msg.start)
    return pack("session_open", body)


def decode_session_open(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> SessionOpen:
    """Returns the validated SessionOpen in ``payload``; ProtocolError otherwise."""
    doc = expect(payload, "session_open", limits)
    camera = decode_camera(require(doc, "camera", dict), limits)
    start = decode_prior(optional(doc, "start", dict))
    if start is not None and start.cam_from_world is None:
        raise ProtocolError("bad_request", "start must be a pose: cam_from_world, sigma_rot_deg, sigma_pos_m")
    return SessionOpen(text(doc, "id", limits.max_id_chars), camera, start)


def encode_session_opened(msg: SessionOpened) -> bytes:
    """Returns the wire bytes of a SessionOpened."""
    return pack("session_opened", {
        "id": msg.id, "session": msg.session, "instance": msg.instance,
        "idle_timeout_s": float(msg.idle_timeout_s),
        "map": {"name": msg.map_name, "id": msg.map_id, "version": msg.map_version},
    })  # fmt: skip


def decode_session_opened(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> SessionOpened:
    """Returns the SessionOpened in ``payload``; ProtocolError otherwise."""
    doc = expect(payload, "session_opened", limits)
    map_doc = optional(doc, "map", dict) or {}
    return SessionOpened(
        id=text(doc, "id", limits.max_id_chars),
        session=text(doc, "session", MAX_SESSION_CHARS),
        instance=require(doc, "instance", str),
        idle_timeout_s=number(doc, "idle_timeout_s", positive=True),
        map_name=optional(map_doc, "name", str) or "",
        map_version=str(map_doc.get("version", "")),
        map_id=str(map_doc.get("id", "")),
    )


def encode_track_request(msg: TrackRequest) -> bytes:
    """Returns the wire bytes of a TrackRequest."""
    body: dict = {"id": msg.id, "session": msg.session}
    body |= frame_fields(msg.image, msg.image_format, msg.segments)
    if msg.relative_pose is not None:
        body["relative_pose"] = encode_array(np.asarray(msg.relative_pose, dtype=np.float64))
    if msg.timestamp is not None:
        body["timestamp"] = float(msg.timestamp)
    body["options"] = options_fields(msg.deadline_ms, msg.return_matches)
    return pack("track_request", body)


def session_of(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> tuple[str, str]:
    """Returns (message type, session id) of a session message; ProtocolError if it has neither."""
    doc = unpack(payload, limits)
    if doc["type"] == "session_open":
        return "session_open", ""
    if doc["type"] not in ("track_request", "session_close"):
        raise ProtocolError("bad_request", f"not a session message: {doc['type'][:40]!r}")
    return doc["type"], text(doc, "session", MAX_SESSION_CHARS)


def decode_track_request(payload: bytes, camera: Camera, limits: Limits = _DEFAULT_LIMITS) -> TrackRequest:
    """Returns the validated TrackRequest in ``payload`` for a session of ``camera`` (the image must have
    its size); ProtocolError otherwise. Rigidity of ``relative_pose`` is the tracker's check."""
    doc = expect(payload, "track_request", limits)
    image, image_format, segments = decode_frame(doc, camera, limits)
    relative = None
    if doc.get("relative_pose") is not None:
        relative = decode_array(doc["relative_pose"], "relative_pose", ("float64",), (2,), 16)
        if relative.shape != (4, 4) or not np.isfinite(relative).all():
            raise ProtocolError("bad_request", "relative_pose must be a finite (4, 4) float64 array")
        relative = relative.copy()
    timestamp = None if doc.get("timestamp") is None else number(doc, "timestamp")
    if timestamp is not None and math.isinf(timestamp):
        raise ProtocolError("bad_request", "field 'timestamp' must be finite")
    deadline, return_matches = decode_options(doc, limits)
    return TrackRequest(
        text(doc, "id", limits.max_id_chars), text(doc, "session", MAX_SESSION_CHARS), image, image_format,
        segments, relative, timestamp, deadline, return_matches,
    )  # fmt: skip


def encode_track_reply(msg: TrackReply) -> bytes:
    """Returns the wire bytes of a TrackReply: a localize reply's fields and the session's."""
    extra = {
        "session": msg.session,
        "frame": int(msg.frame),
        "how": msg.how,
        "restarted": bool(msg.restarted),
    }
    return pack("track_reply", reply_fields(msg.reply) | extra)


def decode_track_reply(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> TrackReply:
    """Returns the TrackReply in ``payload``; ProtocolError otherwise."""
    doc = expect(payload, "track_reply", limits)
    how = require(doc, "how", str)
    if how not in HOW:
        raise ProtocolError("bad_request", f"how must be one of {', '.join(HOW)}, got {how[:40]!r}")
    frame = require(doc, "frame", int)
    return TrackReply(
        reply_of(doc, limits), text(doc, "session", MAX_SESSION_CHARS), frame, how,
        optional(doc, "restarted", bool) or False,
    )  # fmt: skip


def encode_session_close(msg: SessionClose) -> bytes:
    """Returns the wire bytes of a SessionClose."""
    return pack("session_close", {"id": msg.id, "session": msg.session})


def decode_session_close(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> SessionClose:
    """Returns the SessionClose in ``payload``; ProtocolError otherwise."""
    doc = expect(payload, "session_close", limits)
    return SessionClose(text(doc, "id", limits.max_id_chars), text(doc, "session", MAX_SESSION_CHARS))


def encode_session_closed(msg: SessionClosed) -> bytes:
    """Returns the wire bytes of a SessionClosed."""
    return pack("session_closed", {"id": msg.id, "session": msg.session, "frames": int(msg.frames)})


def decode_session_closed(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> SessionClosed:
    """Returns the SessionClosed in ``payload``; ProtocolError otherwise."""
    doc = expect(payload, "session_closed", limits)
    return SessionClosed(
        text(doc, "id", limits.max_id_chars),
        text(doc, "session", MAX_SESSION_CHARS),
        require(doc, "frames", int),
    )


ENCODERS = {
    SessionOpen: encode_session_open,
    SessionOpened: encode_session_opened,
    TrackRequest: encode_track_request,
    TrackReply: encode_track_reply,
    SessionClose: encode_session_close,
    SessionClosed: encode_session_closed,
}


def encode_session_message(msg: object) -> bytes:
    """Returns the wire bytes of any session message."""
    return ENCODERS[type(msg)](msg)  # type: ignore[operator]
