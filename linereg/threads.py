"""Threads for work that releases the GIL (OpenCV calls, ``nogil`` numba kernels).

A process may use more than one thread when OpenCV may (``cv2.getNumThreads() > 1``): service workers are
held to one, so the same switch keeps them to one core each. Work split this way gives the same result on
any number of threads.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from typing import Any, TypeVar

import cv2

A = TypeVar("A")
B = TypeVar("B")
T = TypeVar("T")


def thread_count(limit: int) -> int:
    """Returns how many threads to run parallel work in: OpenCV's thread count, at most ``limit``, >= 1."""
    return max(1, min(int(cv2.getNumThreads()), limit))


def run_parallel(run: Callable[[int], None], n: int) -> None:
    """Calls ``run(0) .. run(n - 1)``, all but the first in threads of their own when ``thread_count`` allows
    more than one, else in turn; re-raises the first error.

    Fresh threads rather than a pool: a pool's idle workers do not survive a fork into worker processes.
    """
    errors: list[BaseException] = []

    def guarded(k: int) -> None:
        try:
            run(k)
        except BaseException as e:  # re-raised in the caller's thread below
            errors.append(e)

    parallel = thread_count(n) > 1
    threads = [threading.Thread(target=guarded, args=(k,), daemon=True) for k in range(1, n) if parallel]
    for thread in threads:
        thread.start()
    for k in range(1 if parallel else n):
        guarded(k)
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]


def both(first: Callable[[], A], second: Callable[[], B]) -> tuple[A, B]:
    """Returns ``(first(), second())``, the second in a thread of its own when ``thread_count`` allows (for
    work that releases the GIL beside work that does not all the time)."""
    out: list[Any] = [None, None]

    def run(k: int) -> None:
        out[k] = (first, second)[k]()

    run_parallel(run, 2)
    return out[0], out[1]


def map_threads(f: Callable[[T], A], items: list[T], limit: int) -> list[A]:
    """Returns ``[f(item) for item in items]``, the items taken in turn by up to ``limit`` threads, each
    the next item when it is free (``thread_count``; for work that releases the GIL and whose result
    depends on its item alone; dealt in advance, one thread could be left with the slow ones)."""
    out: list[Any] = [None] * len(items)
    workers = thread_count(min(limit, len(items)))
    taken = itertools.count()  # the next item; next() on it is atomic under the GIL

    def run(worker: int) -> None:
        while (i := next(taken)) < len(items):
            out[i] = f(items[i])

    run_parallel(run, workers)
    return out
