"""A pool of worker processes behind a bounded queue, with deadlines, crash recovery and draining.

Each worker slot has one thread in this process that owns one child process and its pipe: it takes a
job from the shared queue, sends it, waits for the reply, the child's death or the hard deadline, and
replaces a dead or hung child. A watcher thread answers ``timeout`` when a job's deadline passes first.
Tracking sessions live in one worker: their jobs go to that slot's own queue (``submit_to``), which the
slot serves in turn with the shared one.
"""

from __future__ import annotations

import collections
import contextlib
import heapq
import itertools
import logging
import multiprocessing as mp
import os
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from typing import Literal

import protocols
from protocols import Limits

from .handlers import error_bytes
from .worker import worker_main

log = logging.getLogger(__name__)
_CTX = mp.get_context("spawn")  # never fork: the zenoh session runs native threads


# the workers share the cores: each gets cores // workers BLAS/OpenMP threads (no oversubscription)
_THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",  # OpenCV's own pool (LSD bands run in turn then; same segments)
)
_ENV_LOCK = threading.Lock()


@contextlib.contextmanager
def _thread_env(threads: int) -> Iterator[None]:
    """Sets the thread-pool variables a spawned child inherits to ``threads`` (unless the operator set them)."""
    with _ENV_LOCK:
        added = [k for k in _THREAD_VARS if k not in os.environ]
        os.environ.update({k: str(threads) for k in added})
        try:
            yield
        finally:
            for k in added:
                os.environ.pop(k, None)


def _nothing(ok: bool, reply: bytes, code: str) -> None:
    """The callback of a job already answered."""


@dataclass
class Job:
    """One request in flight; ``done(ok, reply_bytes, code)`` is called exactly once."""

    payload: bytes
    deadline: float  # time.monotonic() seconds
    done: Callable[[bool, bytes, str], None]
    request_id: str = ""
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    finished: bool = False

    def finish(self, ok: bool, reply: bytes, code: str = "") -> bool:
        """Delivers the outcome unless one was delivered already; returns whether this one was."""
        with self._lock:
            if self.finished:
                return False
            self.finished = True
        done, self.done, self.payload = self.done, _nothing, b""  # the deadline heap may outlive the job
        try:
            done(ok, reply, code)
        except Exception:
            log.exception("reply callback failed for request %s", self.request_id)
        return True

    def fail(self, code: str, message: str) -> bool:
        return self.finish(False, error_bytes(code, message, self.request_id), code)


class WorkerPool:
    """``workers`` processes, each with the engine ``loader(*loader_args)`` loaded once."""

    def __init__(self, loader: str, loader_args: tuple, workers: int = 2, queue_size: int = 8,
                 limits: Limits | None = None, hard_grace_s: float = 30.0,
                 threads_per_worker: int | None = None) -> None:  # fmt: skip
        self.loader, self.loader_args = loader, tuple(loader_args)
        self.num_workers, self.limits, self.hard_grace_s = workers, limits or Limits(), hard_grace_s
        self.jobs: queue.Queue = queue.Queue(maxsize=queue_size)
        self.threads_per_worker = threads_per_worker or max(1, (os.cpu_count() or 1) // workers)
        self.ready_info: dict = {}
        self.restarts = 0
        self.in_flight = 0
        self._procs: list = [None] * workers
        self._threads: list[threading.Thread] = []
        self._deadlines: list = []
        self._cv = threading.Condition()
        self._seq = itertools.count()
        self._closing = False
        self._stopped = False  # the slot threads return
        self._count_lock = threading.Lock()
        self._own: list[collections.deque] = [collections.deque() for _ in range(workers)]
        self._work = threading.Condition()  # a job was queued (shared or a slot's own), or the pool stops

    def start(self, timeout_s: float = 300.0) -> dict:
        """Starts every worker, waits until each has loaded the map; returns the first one's ready doc."""
        log.info(
            "starting workers",
            extra={"fields": {"workers": self.num_workers, "note": "each loads the map and makes its "
                              "compiled kernels ready (the first time after an install: compiled, ~30 s)"}},
        )  # fmt: skip
        started = [self._spawn(i) for i in range(self.num_workers)]
        for i, (proc, conn) in enumerate(started):
            self._procs[i] = (proc, conn, self._await_ready(proc, conn, timeout_s))
        for i in range(self.num_workers):
            thread = threading.Thread(
                target=self._slot_loop, args=(i,), name=f"linereg-slot-{i}", daemon=True
            )
            thread.start()
            self._threads.append(thread)
        threading.Thread(target=self._watch_deadlines, name="linereg-deadlines", daemon=True).start()
        return self.ready_info

    def submit(self, job: Job) -> bool:
        """Queues ``job``; returns False (the caller answers ``busy``) when the queue is full or closing."""
        if self._closing:
            return False
        with self._work:
            try:
                self.jobs.put_nowait(job)
            except queue.Full:
                return False
            self._work.notify_all()
        self._watch(job)
        return True

    def submit_to(self, slot: int, job: Job, always: bool = False) -> bool:
        """Queues ``job`` for worker slot ``slot`` only (a tracking session's); returns False (``busy``)
        when that slot already has ``queue_size`` waiting or the pool is closing, unless ``always``."""
        if self._closing and not always:
            return False
        with self._work:
            if len(self._own[slot]) >= self.jobs.maxsize and not always:
                return False
            self._own[slot].append(job)
            self._work.notify_all()
        self._watch(job)
        return True

    def queued_for_slots(self) -> int:
        """Returns how many jobs wait in the slots' own queues."""
        return sum(len(q) for q in self._own)

    def _watch(self, job: Job) -> None:
        with self._cv:
            heapq.heappush(self._deadlines, (job.deadline, next(self._seq), job))
            self._cv.notify()

    def alive(self) -> int:
        """Returns how many worker processes are alive."""
        return sum(1 for p in self._procs if p is not None and p[0].is_alive())

    def pids(self) -> list[int]:
        """Returns the worker process ids (tests kill them)."""
        return [p[0].pid for p in self._procs if p is not None]

    def close(self, drain_timeout_s: float = 30.0) -> None:
        """Stops taking jobs, lets queued and in-flight ones finish (up to the timeout), stops the workers."""
        self._closing = True
        end = time.monotonic() + drain_timeout_s
        while (self.jobs.qsize() or self.queued_for_slots() or self.in_flight) and time.monotonic() < end:
            time.sleep(0.01)
        with self._work:  # whatever is left after the drain timeout is answered, never dropped
            left = [*self._drain_shared(), *(job for q in self._own for job in q)]
            for q in self._own:
                q.clear()
            self._stopped = True
            self._work.notify_all()
        for job in left:
            job.fail("busy", "service shutting down")
        for thread in self._threads:
            thread.join(timeout=max(0.1, end - time.monotonic()) + 5)
        for slot in self._procs:
            if slot is not None:
                self._stop_process(*slot[:2])
        with self._cv:
            self._cv.notify()

    # --- internals -------------------------------------------------------------------------------------

    def _drain_shared(self) -> list[Job]:
        jobs = []
        while True:
            try:
                jobs.append(self.jobs.get_nowait())
            except queue.Empty:
                return jobs

    def _next_job(self, index: int, own_first: bool) -> Job | Literal[False] | None:
        """Returns the slot's next job (its own queue first when ``own_first``, else the shared one
        first), False after a second without work, None when the pool stops."""
        with self._work:
            for attempt in range(2):
                if self._stopped:
                    return None
                own = self._own[index]
                if own and (own_first or self.jobs.empty()):
                    return own.popleft()
                try:
                    return self.jobs.get_nowait()
                except queue.Empty:
                    if own:
                        return own.popleft()
                if attempt == 0:
                    self._work.wait(timeout=1.0)
            return False

    def _spawn(self, index: int):
        parent, child = _CTX.Pipe()
        proc = _CTX.Process(
            target=worker_main, args=(child, self.loader, self.loader_args, self.limits),
            name=f"linereg-worker-{index}", daemon=True,
        )  # fmt: skip
        with _thread_env(self.threads_per_worker):
            proc.start()
        child.close()  # so that the parent sees EOF when the child dies
        return proc, parent

    def _await_ready(self, proc, conn, timeout_s: float) -> dict:
        if not conn.poll(timeout_s):
            proc.kill()
            raise RuntimeError(f"worker did not load the map within {timeout_s:.0f} s")
        try:
            doc = protocols.unpack(conn.recv_bytes())
        except (EOFError, OSError, protocols.ProtocolError):
            raise RuntimeError(f"worker died while loading the map (exit code {proc.exitcode})") from None
        if doc["type"] != "ready":
            raise RuntimeError(f"worker failed to load the map: {doc.get('error')}\n{doc.get('trace', '')}")
        self.ready_info = self.ready_info or doc
        fields = {"pid": proc.pid, "map": doc.get("map_name")}
        if doc.get("warm_up_s") is not None:  # compiled kernels made ready (a fresh install: compiled)
            fields["warm_up_s"] = round(float(doc["warm_up_s"]), 2)
        log.info("worker ready", extra={"fields": fields})
        return doc

    def _replace(self, index: int, reason: str) -> None:
        proc, conn, _ = self._procs[index]
        self._stop_process(proc, conn, kill=True)
        self.restarts += 1
        log.warning(
            "worker replaced", extra={"fields": {"pid": proc.pid, "reason": reason, "exit": proc.exitcode}}
        )
        if self._closing:
            self._procs[index] = None
            return
        while True:  # a worker that cannot start (out of memory, ...) is retried, never left missing
            proc, conn = self._spawn(index)
            try:
                self._procs[index] = (proc, conn, self._await_ready(proc, conn, 300.0))
                return
            except RuntimeError as e:
                log.error("worker failed to start", extra={"fields": {"error": str(e)}})
                self._stop_process(proc, conn, kill=True)
                time.sleep(1.0)
                if self._closing:
                    self._procs[index] = None
                    return

    @staticmethod
    def _stop_process(proc, conn, kill: bool = False) -> None:
        if not kill:
            try:
                conn.send_bytes(b"")
            except OSError:
                pass
            proc.join(timeout=5)
        if proc.is_alive():
            proc.kill()
        proc.join(timeout=5)
        conn.close()

    def _slot_loop(self, index: int) -> None:
        own_first = True
        while True:
            job = self._next_job(index, own_first)
            own_first = not own_first  # sessions' frames and shared queries in turn: neither starves
            if job is None:
                return
            if not self._procs[index][0].is_alive():  # died while idle: replace before it gets work
                self._replace(index, "died while idle")
            if job is False:
                continue
            if job.finished:  # answered ``timeout`` while it waited in the queue
                continue
            with self._count_lock:
                self.in_flight += 1
            try:
                self._run(index, job)
            finally:
                with self._count_lock:
                    self.in_flight -= 1

    def _run(self, index: int, job: Job) -> None:
        """Runs one job on the slot's worker; answers ``internal`` and replaces the worker if it dies."""
        proc, conn, _ = self._procs[index]
        payload = job.payload  # an answered job's payload is b"", which a worker reads as "stop"
        if not payload:
            return
        try:
            conn.send_bytes(payload)
            hard_deadline = job.deadline + self.hard_grace_s
            while not wait([conn, proc.sentinel], timeout=0.5):
                if time.monotonic() > hard_deadline:
                    job.fail("timeout", "deadline passed")
                    self._replace(index, "hung past its deadline")
                    return
            reply = conn.recv_bytes()
        except (EOFError, OSError):
            job.fail("internal", "the worker processing this request crashed")
            self._replace(index, "crashed")
            return
        ok = reply[:1] == b"R"
        job.finish(ok, reply[1:], "" if ok else protocols.decode_error(reply[1:]).code)

    def _watch_deadlines(self) -> None:
        while True:
            with self._cv:
                if self._closing and not self._threads_alive():
                    return
                now = time.monotonic()
                while self._deadlines and (self._deadlines[0][2].finished or self._deadlines[0][0] <= now):
                    _, _, job = heapq.heappop(self._deadlines)
                    if not job.finished:
                        job.fail("timeout", "deadline passed before the request was answered")
                timeout = self._deadlines[0][0] - now if self._deadlines else 0.5
                self._cv.wait(timeout=min(max(timeout, 0.001), 0.5))

    def _threads_alive(self) -> bool:
        return any(t.is_alive() for t in self._threads)
