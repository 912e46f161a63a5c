"""numpy's pairwise summation as numba kernels, shared by the compiled paths
(vio_graph/frontend/compiled.py, vio_graph/filter/compiled_imu.py) so that their sums and
means are the same floats as the numpy reference paths' ``np.add.reduce`` / ``np.mean``.
Imported only where numba is installed."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def block_sum(a, lo, n):  # pragma: no cover - compiled
    """numpy's pairwise_sum of a[lo:lo + n] for n <= 128: in order below 8, else eight
    accumulators combined as ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)), then the
    rest in order."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    m = n - n % 8
    while i < m:
        b = lo + i
        r0 += a[b]
        r1 += a[b + 1]
        r2 += a[b + 2]
        r3 += a[b + 3]
        r4 += a[b + 4]
        r5 += a[b + 5]
        r6 += a[b + 6]
        r7 += a[b + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@numba.njit(cache=True)
def pairwise_sum(a, lo, n):  # pragma: no cover - compiled
    """np.add.reduce of a[lo:lo + n] (contiguous float64): numpy's pairwise summation (blocks
    of at most 128 summed by :func:`block_sum`, longer runs split in halves at a multiple of
    8 and the halves' sums added), so the same float. The halving is walked with an explicit
    stack: numba's cache does not load recursive functions reliably."""
    if n <= 128:
        return block_sum(a, lo, n)
    los = np.empty(64, np.int64)
    ns = np.empty(64, np.int64)
    stage = np.zeros(64, np.int64)  # 0: left half next, 1: right half next, 2: add them
    vals = np.empty(64)
    los[0] = lo
    ns[0] = n
    sp = 1
    nv = 0
    while sp > 0:
        top = sp - 1
        cnt = ns[top]
        if cnt <= 128:
            vals[nv] = block_sum(a, los[top], cnt)
            nv += 1
            sp -= 1
            continue
        n2 = cnt // 2
        n2 -= n2 % 8
        if stage[top] == 0:
            stage[top] = 1
            los[sp], ns[sp], stage[sp] = los[top], n2, 0
            sp += 1
        elif stage[top] == 1:
            stage[top] = 2
            los[sp], ns[sp], stage[sp] = los[top] + n2, cnt - n2, 0
            sp += 1
        else:
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            sp -= 1
    return vals[0]


@numba.njit(cache=True)
def add_reduce(a):  # pragma: no cover - compiled
    """``np.add.reduce`` of a 1-D contiguous float64 array, the same float."""
    return pairwise_sum(a, 0, a.size)
