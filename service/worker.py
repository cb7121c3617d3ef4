"""A worker process: loads the map once, then answers localize payloads from its pipe until told to stop.

Pipe protocol (parent <-> worker, both bytes): the worker first sends a ``ready`` document (map name,
version, info) or a ``failed`` one; then for each request payload it sends ``b"R" + reply`` or
``b"E" + error``; an empty message from the parent means stop. A payload starting with ``b"S"`` is a
track job of a tracking session (``trackers.py``), any other a localize request.
"""

from __future__ import annotations

import logging
import signal
import traceback

import protocols
from protocols import Limits

from .engine import load_engine
from .handlers import handle_localize
from .trackers import TRACK_JOB, Trackers

log = logging.getLogger(__name__)


def _quiet_opencv() -> None:
    """Silences OpenCV's warnings on stderr: an image that does not decode is answered, not logged twice."""
    try:
        import cv2

        cv2.setLogLevel(2)  # type: ignore[attr-defined]  # errors only
    except (ImportError, AttributeError):
        pass


def worker_main(conn, loader: str, loader_args: tuple, limits: Limits) -> None:
    """Runs in the child process: load, announce, serve the pipe until EOF or an empty message."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when workers stop
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _quiet_opencv()
    try:
        engine = load_engine(loader, loader_args)
    except Exception as e:
        conn.send_bytes(
            protocols.pack("failed", {"error": f"{type(e).__name__}: {e}", "trace": traceback.format_exc()})
        )
        return
    info = {"map_name": engine.map_name, "map_version": engine.map_version, "info": engine.info,
            "tracking": engine.tracker is not None, "warm_up_s": engine.warm_up_s}  # fmt: skip
    conn.send_bytes(protocols.pack("ready", info))
    trackers = Trackers(engine, limits)
    while True:
        try:
            payload = conn.recv_bytes()
        except (EOFError, OSError):
            return
        if not payload:
            return
        if payload[:1] == TRACK_JOB:
            reply = trackers.handle(payload)
        else:
            reply = handle_localize(payload, engine, limits)
        kind = b"E" if protocols.message_type(reply) == "error" else b"R"
        conn.send_bytes(kind + reply)
