"""Batch work: one function over many items in this process, a local process pool, or a Dask cluster.

A task is ``fn(shared, item)`` with ``fn`` a module-level function (workers import it by name), ``shared``
what every task needs (sent once per worker: the pool's initializer, Dask's ``scatter``) and ``item`` what
differs. Runners are context managers; ``runner(workers, scheduler)`` picks one. ``dask.distributed`` is
optional (``pip install 'linereg[cluster]'``) and imported only when a scheduler address is given.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import multiprocessing
import sys
import uuid
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from .errors import InvalidInputError

Task = Callable[[Any, Any], Any]
CONNECT_TIMEOUT = "10s"  # how long to try reaching a Dask scheduler
_shared: dict[str, Any] = {}  # in a pool worker: token -> shared


class InlineRunner:
    """Runs every task here, in order (no pickling: the default for one worker, and easy to debug)."""

    workers = 1

    def unordered(self, fn: Task, shared: Any, items: Iterable) -> Iterator[tuple[int, Any]]:
        """Yields (item position, result) as tasks finish (here: in order)."""
        for i, item in enumerate(items):
            yield i, fn(shared, item)

    def ordered(self, fn: Task, shared: Any, items: Iterable) -> Iterator[Any]:
        """Yields the results in the order of ``items``, holding a bounded number of them at once."""
        for item in items:
            yield fn(shared, item)

    def __enter__(self) -> InlineRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


class PoolRunner(InlineRunner):
    """A local process pool per call (``shared`` reaches each worker once, by its initializer)."""

    def __init__(self, workers: int, fork: bool = True) -> None:
        self.workers, self.fork = workers, fork

    def _pool(self, shared: Any) -> tuple[ProcessPoolExecutor, str]:
        token = uuid.uuid4().hex
        # fork=False: workers start from a clean fork server, not forked from this process. A thread pool
        # of this process (OpenCV's) does not survive fork, and a forked worker calling into it hangs.
        method = "fork" if self.fork else "forkserver" if sys.platform == "linux" else "spawn"
        context = multiprocessing.get_context(method)
        pool = ProcessPoolExecutor(self.workers, context, initializer=_keep, initargs=(token, shared))
        return pool, token

    def unordered(self, fn: Task, shared: Any, items: Iterable) -> Iterator[tuple[int, Any]]:
        with _explained():
            yield from self._unordered(fn, shared, items)

    def ordered(self, fn: Task, shared: Any, items: Iterable) -> Iterator[Any]:
        with _explained():
            pool, token = self._pool(shared)
            with pool:
                yield from _bounded_in_order(
                    lambda item: pool.submit(_call, fn, token, item), items, 2 * self.workers
                )

    def _unordered(self, fn: Task, shared: Any, items: Iterable) -> Iterator[tuple[int, Any]]:
        pool, token = self._pool(shared)
        with pool:
            futures = {pool.submit(_call, fn, token, item): i for i, item in enumerate(items)}
            pending = set(futures)
            try:
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for future in done:  # popped: a finished future holds its result until dropped
                        yield futures.pop(future), future.result()
            finally:
                for future in pending:
                    future.cancel()


@contextlib.contextmanager
def _explained() -> Iterator[None]:
    """Re-raises a broken pool with its usual causes, the script's missing main guard first."""
    try:
        yield
    except BrokenProcessPool as e:
        raise BrokenProcessPool(
            f'{e} Usual causes: a script that starts the pool without `if __name__ == "__main__":` '
            "round its work (workers started clean import the script again and run it), a worker killed "
            "(out of memory)."
        ) from e


class DaskRunner(InlineRunner):
    """Tasks on an existing ``dask.distributed`` cluster; ``shared`` is scattered to every worker once.

    Workers must import linereg (the same version) and reach the files named in the items (a shared file
    system): the cluster runs the very functions of a local run, so the results are the same.
    """

    def __init__(self, address: str) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise InvalidInputError(
                "--scheduler needs dask.distributed: pip install 'linereg[cluster]'"
            ) from None
        try:
            self.client = Client(address, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError, ValueError) as e:
            raise InvalidInputError(
                f"--scheduler {address}: cannot connect to a Dask scheduler ({e})"
            ) from None
        self.workers = max(len(self.client.scheduler_info(n_workers=-1).get("workers", {})), 1)

    def _scatter(self, shared: Any) -> Any:
        return self.client.scatter(shared, broadcast=True, hash=False) if shared is not None else None

    def unordered(self, fn: Task, shared: Any, items: Iterable) -> Iterator[tuple[int, Any]]:
        from distributed import as_completed

        remote = self._scatter(shared)
        futures = {self.client.submit(fn, remote, item, pure=False): i for i, item in enumerate(items)}
        try:
            for future in as_completed(
                futures
            ):  # popped: the cluster keeps a result while a future refers to it
                yield futures.pop(future), future.result()
        finally:
            self.client.cancel(list(futures))

    def ordered(self, fn: Task, shared: Any, items: Iterable) -> Iterator[Any]:
        remote = self._scatter(shared)
        yield from _bounded_in_order(
            lambda item: self.client.submit(fn, remote, item, pure=False), items, 2 * self.workers
        )

    def __exit__(self, *exc: object) -> None:
        self.client.close()


def runner(workers: int = 1, scheduler: str | None = None, fork: bool = True) -> InlineRunner:
    """Returns the runner of a batch: a Dask cluster if ``scheduler`` is an address, else ``workers``
    local processes (1: this process), forked from this one or (``fork=False``) started clean: slower to
    start, but safe after this process ran OpenCV's thread pool.

    Workers started clean (``fork=False``, and any pool on macOS / Windows) import the script that
    started them again, so a script must keep its work under ``if __name__ == "__main__":``.
    """
    if scheduler:
        return DaskRunner(scheduler)
    if workers < 1:
        raise InvalidInputError(f"--workers must be >= 1, got {workers}")
    return PoolRunner(workers, fork) if workers > 1 else InlineRunner()


def _bounded_in_order(submit: Callable[[Any], Any], items: Iterable, ahead: int) -> Iterator[Any]:
    """Yields results in item order with at most ``ahead`` tasks submitted and not yet yielded."""
    queue: collections.deque = collections.deque()
    iterator = iter(items)
    try:
        for item in itertools.islice(iterator, ahead):
            queue.append(submit(item))
        while queue:
            result = queue.popleft().result()
            for item in itertools.islice(iterator, 1):
                queue.append(submit(item))
            yield result
    finally:
        for future in queue:
            future.cancel()


def _keep(token: str, shared: Any) -> None:
    """A pool worker's initializer: holds ``shared`` for the tasks of its pool."""
    _shared.clear()
    _shared[token] = shared


def _call(fn: Task, token: str, item: Any) -> Any:
    return fn(_shared[token], item)
