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
from protocols import Limits, ProtocolError, keys

from .handlers import error_bytes, handle_info, handle_stats
from .pool import Job, WorkerPool
from .stats import Stats
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
        self.map_name = ""
        self.info: dict = {}
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
            worker_restarts=pool.restarts, draining=self._draining,
        )  # fmt: skip

    def stop(self) -> None:
        """Drains: new queries get ``busy``, queued and in-flight ones are answered; then closes the session."""
        if self.session is None:
            return
        self._draining = True
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

    def _answer(
        self, query, key: str, start: float, request_id: str, ok: bool, payload: bytes, code: str
    ) -> None:
        """Sends the one reply of a localize query, counts it and logs it (one JSON line per request)."""
        outcome = ("ok" if protocols.decode_reply(payload).success else "not_localized") if ok else code
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
