"""The zenoh layer of the service: session, queryables, liveliness token; the work is in the pool."""

from __future__ import annotations

import logging
import os
import re
import signal
import socket
import threading
import time
import uuid
from dataclasses import dataclass, field

import zenoh

import protocols
from protocols import Limits, ProtocolError, keys, session

from .handlers import error_bytes, handle_info, handle_stats
from .pool import Job, WorkerPool
from .sessions import Session, SessionLimits, SessionTable
from .stats import Stats
from .trackers import track_job
from .zconfig import DEFAULT_ENDPOINT, session_config

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ServiceConfig:
    """How to run one service instance (``linereg serve`` flags)."""

    loader: str = "service.engine:load_map_engine"  # "module:function" building the Engine in each worker
    loader_args: tuple = ()
    map_name: str | None = None  # default: the map's own name
    instance: str | None = None  # default: host name and a short random suffix
    tile: str | None = None  # also serve linereg/<map>/tile/<tile>/localize (a map split over instances)
    workers: int = 2
    queue_size: int = 8
    mode: str | None = "router"  # None: the zenoh config file's
    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    connect: tuple[str, ...] = ()
    zenoh_config: str | None = None  # a json5 file; mode/endpoints above override its values
    multicast: bool = False
    limits: Limits = field(default_factory=Limits)
    drain_timeout_s: float = 30.0
    threads_per_worker: int | None = None  # BLAS/OpenMP threads per worker; default cores // workers
    hard_grace_s: float = 30.0
    sessions: SessionLimits = field(default_factory=SessionLimits)  # tracking sessions: idle expiry, caps


class Service:
    """One running instance: ``start()``, then ``stop()`` (drains) — or ``with Service(cfg) as svc:``."""

    def __init__(self, config: ServiceConfig) -> None:
        self.config = config
        self.instance = config.instance or default_instance()
        self.stats = Stats()
        self.pool = WorkerPool(
            config.loader,
            config.loader_args,
            config.workers,
            config.queue_size,
            config.limits,
            config.hard_grace_s,
            config.threads_per_worker,
        )
        self.sessions = SessionTable(config.workers, config.sessions)
        self.map_name = ""
        self.info: dict = {}
        self._stopping = threading.Event()
        self.session: zenoh.Session | None = None
        self._draining = False
        self._threads: list[threading.Thread] = []
        self._token: zenoh.LivelinessToken | None = None

    def __enter__(self) -> Service:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> Service:
        """Loads the map in every worker, opens the session, declares queryables and the liveliness token."""
        ready = self.pool.start()
        self.map_name = keys.check_chunk(self.config.map_name or ready["map_name"], "map name")
        self.info = {
            "name": self.map_name,
            "version": ready.get("map_version", ""),
            **(ready.get("info") or {}),
        }
        self.info["name"] = self.map_name
        self.info["instance"] = self.instance
        cfg = self.config
        if ready.get("tracking"):
            limits = cfg.sessions
            self.info["sessions"] = {"idle_timeout_s": limits.idle_timeout_s, "max_sessions": limits.max_sessions,
                                     "per_worker": limits.per_worker}  # fmt: skip
        try:
            self.session = zenoh.open(
                session_config(cfg.mode, cfg.listen, cfg.connect, cfg.zenoh_config, cfg.multicast)
            )
        except Exception:  # e.g. the port is taken: do not leave the workers behind
            self.pool.close(drain_timeout_s=0.0)
            raise
        routes = [
            (keys.localize_key(self.map_name), self._on_localize),
            (keys.instance_localize_key(self.map_name, self.instance), self._on_localize),
            (keys.info_key(self.map_name), lambda q, k: self._reply(q, k, handle_info(b"", self.info))),
            (
                keys.stats_key(self.map_name),
                lambda q, k: self._reply(q, k, handle_stats(b"", self.snapshot())),
            ),
        ]
        if cfg.tile:
            routes.append((keys.tile_localize_key(self.map_name, cfg.tile), self._on_localize))
        if ready.get("tracking"):
            routes += [(keys.session_key(self.map_name), self._on_session),
                       (keys.instance_session_key(self.map_name, self.instance), self._on_session)]  # fmt: skip
            threading.Thread(target=self._expire_loop, name="linereg-sessions", daemon=True).start()
        for key, handler in routes:
            queryable = self.session.declare_queryable(key, zenoh.handlers.FifoChannel(256))
            thread = threading.Thread(
                target=self._serve, args=(queryable, key, handler), daemon=True, name=key
            )
            thread.start()
            self._threads.append(thread)
        self._token = self.session.liveliness().declare_token(keys.alive_key(self.map_name, self.instance))
        log.info("service up", extra={"fields": {"map": self.map_name, "instance": self.instance,
                                                  "workers": cfg.workers, "listen": list(cfg.listen)}})  # fmt: skip
        return self

    def snapshot(self) -> dict:
        """Returns the stats document: counters, latency percentiles, queue depth, worker health."""
        pool = self.pool
        return self.stats.snapshot(
            instance=self.instance, queue_depth=pool.jobs.qsize(), queue_size=self.config.queue_size,
            in_flight=pool.in_flight, workers=self.config.workers, workers_alive=pool.alive(),
            worker_restarts=pool.restarts, draining=self._draining, sessions=self.sessions.snapshot(),
            session_queue_depth=pool.queued_for_slots(),
        )  # fmt: skip

    def stop(self) -> None:
        """Drains: new queries get ``busy``, queued and in-flight ones are answered; then closes the session."""
        if self.session is None:
            return
        self._draining = True
        self._stopping.set()
        if self._token is not None:  # clients choosing an instance by liveliness stop picking this one
            self._token.undeclare()
            self._token = None
        log.info(
            "draining", extra={"fields": {"queued": self.pool.jobs.qsize(), "in_flight": self.pool.in_flight}}
        )
        self.pool.close(self.config.drain_timeout_s)
        session, self.session = self.session, None
        session.close()  # ends the receive loops
        for thread in self._threads:
            thread.join(timeout=5)
        log.info("service stopped", extra={"fields": self.stats.snapshot()})

    # --- zenoh side ------------------------------------------------------------------------------------

    def _serve(self, queryable, key: str, handler) -> None:
        while True:
            try:
                query = queryable.recv()
            except Exception:  # the session closed: this instance is stopping
                return
            try:
                handler(query, key)
            except Exception:
                log.exception("handler failed on %s", key)

    def _on_localize(self, query, key: str) -> None:
        """Pre-validates in this process (garbage never reaches a worker), then queues the request."""
        start = time.monotonic()
        payload = query.payload.to_bytes() if query.payload is not None else b""
        limits = self.config.limits
        try:
            req = protocols.decode_request(payload, limits)
        except ProtocolError as e:
            request_id = protocols.request_id(payload)
            reply = error_bytes(e.code, e.message, request_id)
            self._answer(query, key, start, request_id, False, reply, e.code)
            return
        deadline = start + (req.deadline_ms or limits.default_deadline_ms) / 1000.0
        job = Job(
            payload, deadline, lambda ok, b, c: self._answer(query, key, start, req.id, ok, b, c), req.id
        )
        if self._draining:
            job.fail("busy", "service shutting down")
        elif not self.pool.submit(job):
            job.fail("busy", f"queue full ({self.config.queue_size} waiting)")

    def _on_session(self, query, key: str) -> None:
        """Opens or closes a tracking session here, or queues a frame for the worker holding it."""
        start = time.monotonic()
        payload = query.payload.to_bytes() if query.payload is not None else b""
        request_id = protocols.request_id(payload)
        self._expire()
        try:
            kind, session_id = session.session_of(payload, self.config.limits)
            if kind == "track_request":
                self._track(query, key, start, payload, self.sessions.begin(session_id))
                return
            reply = self._open(payload) if kind == "session_open" else self._close(payload)
        except ProtocolError as e:
            self._answer(
                query, key, start, request_id, False, error_bytes(e.code, e.message, request_id), e.code
            )
            return
        self._answer(query, key, start, request_id, True, reply, "")

    def _open(self, payload: bytes) -> bytes:
        if self._draining:
            raise ProtocolError("busy", "service shutting down")
        req = session.decode_session_open(payload, self.config.limits)
        found = self.sessions.open(req.camera, payload)
        log.info("session opened", extra={"fields": {"session": found.id, "worker": found.slot}})
        return session.encode_session_opened(protocols.SessionOpened(
            req.id, found.id, self.instance, self.config.sessions.idle_timeout_s, self.map_name,
            str(self.info.get("version", "")), str(self.info.get("map_id", "")),
        ))  # fmt: skip

    def _close(self, payload: bytes) -> bytes:
        req = session.decode_session_close(payload, self.config.limits)
        found = self.sessions.close(req.session)
        self._drop(found, "closed")
        return session.encode_session_closed(protocols.SessionClosed(req.id, found.id, found.frames))

    def _track(self, query, key: str, start: float, payload: bytes, found: Session) -> None:
        """Queues one frame of ``found`` on its worker slot (``found`` has it counted in flight)."""
        limits = self.config.limits
        try:
            req = session.decode_track_request(payload, found.camera, limits)
        except ProtocolError:
            self.sessions.end(found, answered=False)
            raise

        def done(ok: bool, reply: bytes, code: str) -> None:
            self.sessions.end(found, answered=ok)
            self._answer(query, key, start, req.id, ok, reply, code)

        deadline = start + (req.deadline_ms or limits.default_deadline_ms) / 1000.0
        job = Job(
            track_job("step", found.id, found.open_payload, found.frames, payload), deadline, done, req.id
        )
        if self._draining:
            job.fail("busy", "service shutting down")
        elif not self.pool.submit_to(found.slot, job):
            job.fail("busy", f"the session's worker has {self.config.queue_size} frames waiting")

    def _drop(self, found: Session, why: str) -> None:
        """Frees the session's tracker in its worker (after any frame of it still queued there)."""
        job = Job(track_job("drop", found.id), time.monotonic() + 1e6, lambda ok, b, c: None, found.id)
        self.pool.submit_to(found.slot, job, always=True)
        log.info(f"session {why}", extra={"fields": {"session": found.id, "frames": found.frames}})

    def _expire(self) -> None:
        for found in self.sessions.expire():
            self._drop(found, "expired")

    def _expire_loop(self) -> None:
        period = min(1.0, self.config.sessions.idle_timeout_s / 4)
        while not self._stopping.wait(period):
            self._expire()

    def _answer(
        self, query, key: str, start: float, request_id: str, ok: bool, payload: bytes, code: str
    ) -> None:
        """Sends the one reply of a query, counts it and logs it (one JSON line per request)."""
        outcome = _outcome(payload) if ok else code
        latency_ms = (time.monotonic() - start) * 1000.0
        self.stats.record(outcome, latency_ms)
        self._reply(query, key, payload, ok)
        fields = {"id": request_id, "key": key, "outcome": outcome, "latency_ms": round(latency_ms, 3)}
        log.info("reply", extra={"fields": fields})

    @staticmethod
    def _reply(query, key: str, payload: bytes, ok: bool = True) -> None:
        try:
            if ok:
                query.reply(key, payload)
            else:
                query.reply_err(payload)
            query.drop()  # the final reply: the client stops waiting now
        except Exception as e:  # the client is gone; nothing to answer
            log.info("reply not delivered", extra={"fields": {"error": str(e)}})


def _outcome(reply: bytes) -> str:
    """Returns the stats outcome of a normal reply: ``not_localized`` for a frame without a pose, else ok."""
    return "not_localized" if protocols.unpack(reply).get("status") == "not_localized" else "ok"


def default_instance() -> str:
    """Returns ``<host>-<4 hex>``: readable in logs, unique among replicas on one host."""
    host = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:40] or "host"
    return f"{host}-{uuid.uuid4().hex[:4]}"


def run(config: ServiceConfig) -> int:
    """Runs a service until SIGTERM or SIGINT, then drains and exits; returns the exit code."""
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with Service(config) as service:
        log.info("serving", extra={"fields": {"pid": os.getpid(), "map": service.map_name}})
        stop.wait()
    return 0
