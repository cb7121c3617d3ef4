"""Small compiled helpers shared by the compiled loops of several modules (numba, cached on disk).

Written out instead of numpy's own: inside a compiled loop numba's sorts and LAPACK bindings cost seconds
of compile in every fresh process (``linereg/warm.py``).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def stable_argsort(keys: np.ndarray) -> np.ndarray:  # pragma: no cover - numba
    """Returns (n,) int64: ``np.argsort(keys, kind="stable")`` of finite (n,) keys, by a bottom-up merge
    sort."""
    n = len(keys)
    order, other = np.arange(n), np.empty(n, np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid, hi = min(lo + width, n), min(lo + 2 * width, n)
            a, b = lo, mid
            for k in range(lo, hi):  # the left run's element first among equal keys: stable
                if a < mid and (b >= hi or keys[order[a]] <= keys[order[b]]):
                    other[k] = order[a]
                    a += 1
                else:
                    other[k] = order[b]
                    b += 1
        order, other = other, order
        width *= 2
    return order


@numba.njit(cache=True, nogil=True)
def jacobi_rotation(a: np.ndarray, v: np.ndarray, p: int, q: int) -> None:  # pragma: no cover - numba
    """Zeroes a[p, q] of the symmetric (n, n) ``a`` by a rotation in the (p, q) plane (a <- J^T a J),
    accumulated into the eigenvectors ``v`` (v <- v J): one step of the cyclic Jacobi eigenvalue method."""
    if a[p, q] == 0.0:
        return
    theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
    t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
    c = 1.0 / np.sqrt(t * t + 1.0)
    s = t * c
    n = len(a)
    for r in range(n):
        arp, arq = a[r, p], a[r, q]
        a[r, p], a[r, q] = c * arp - s * arq, s * arp + c * arq
    for r in range(n):
        apr, aqr = a[p, r], a[q, r]
        a[p, r], a[q, r] = c * apr - s * aqr, s * apr + c * aqr
    for r in range(n):
        vrp, vrq = v[r, p], v[r, q]
        v[r, p], v[r, q] = c * vrp - s * vrq, s * vrp + c * vrq
