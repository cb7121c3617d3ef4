"""Small compiled helpers shared by the compiled loops of several modules (numba, cached on disk).

Written out instead of numpy's own: inside a compiled loop numba's sorts and LAPACK bindings cost seconds
of compile in every fresh process (``linereg/warm.py``).
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic


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


@numba.njit(cache=True, nogil=True)
def numpy_sum(a: np.ndarray) -> float:  # pragma: no cover - numba
    """Returns the sum of the (n,) float64 ``a`` as ``np.sum`` gives it for a contiguous array, to the last
    bit: numpy's pairwise summation (``_block_sum`` on blocks of at most 128, left half plus right half
    above that, the halves cut at multiples of 8). A compiled loop that compares scores must rank them as
    numpy does. The halving runs on a stack of its own: numba's cache cannot keep a recursive function."""
    if len(a) <= 128:
        return _block_sum(a, 0, len(a))
    start, size = np.zeros(64, np.int64), np.zeros(64, np.int64)
    state, left = np.zeros(64, np.int64), np.zeros(64)  # state: 0 fresh, 1 left half summed, 2 both
    size[0] = len(a)
    top, value = 1, 0.0  # value: what the frame last popped summed to
    while top > 0:
        f = top - 1
        if size[f] <= 128:
            value = _block_sum(a, start[f], size[f])
            top -= 1
            continue
        half = size[f] // 2
        half -= half % 8
        if state[f] == 0:
            start[top], size[top], state[top] = start[f], half, 0
        elif state[f] == 1:
            left[f] = value
            start[top], size[top], state[top] = start[f] + half, size[f] - half, 0
        else:
            value = left[f] + value
            top -= 1
            continue
        state[f] += 1
        top += 1
    return value


@numba.njit(cache=True, nogil=True)
def _block_sum(a: np.ndarray, start: int, n: int) -> float:  # pragma: no cover - numba
    """Returns numpy's sum of ``a[start:start + n]``, n <= 128: in turn below 8, else 8 running sums."""
    if n < 8:
        total = 0.0
        for k in range(start, start + n):
            total += a[k]
        return total
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    k = start + 8
    end = start + n - n % 8
    while k < end:
        r0, r1, r2, r3 = r0 + a[k], r1 + a[k + 1], r2 + a[k + 2], r3 + a[k + 3]
        r4, r5, r6, r7 = r4 + a[k + 4], r5 + a[k + 5], r6 + a[k + 6], r7 + a[k + 7]
        k += 8
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while k < start + n:
        total += a[k]
        k += 1
    return total


@numba.njit(cache=True, nogil=True)
def invert_rigid(a_from_b: np.ndarray) -> np.ndarray:  # pragma: no cover - numba
    """Returns (4, 4) ``b_from_a`` of a rigid transform, as ``geometry.invert`` gives it to the last bit
    (``R^T``, ``-R^T t`` summed in index order)."""
    out = np.zeros((4, 4))
    out[3, 3] = 1.0
    for r in range(3):
        total = 0.0
        for k in range(3):
            out[r, k] = a_from_b[k, r]
            total += -a_from_b[k, r] * a_from_b[k, 3]
        out[r, 3] = total
    return out


@intrinsic
def _prefetch(typingctx, array, index):  # pragma: no cover - numba
    """``prefetch(array, index)`` in a compiled loop: asks the CPU to load the cache line of
    ``array[index]`` (1-D) for writing, and goes on (LLVM's ``llvm.prefetch``; no effect on any value). The
    vote grids are 32 MB arrays read at scattered voxels: loads requested a ray ahead arrive together
    instead of one cache miss after another."""

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        byte_ptr = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [byte_ptr, i32, i32, i32]), "llvm.prefetch.p0i8"
        )
        address = builder.bitcast(builder.gep(data, [args[1]]), byte_ptr)
        # (address, write, locality: keep in all cache levels, data cache)
        builder.call(fn, [address, ir.Constant(i32, 1), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(array, index), codegen


# as compiled code calls it (numba passes the typing context itself)
prefetch: Callable[[np.ndarray, int], None] = _prefetch  # type: ignore[assignment]
