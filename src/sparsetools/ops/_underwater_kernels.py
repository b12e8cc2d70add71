"""numba kernels of :mod:`sparsetools.ops.underwater` (imported on first use: numba is heavy).

The kernels are serial and release the GIL (``nogil=True``); :func:`run_split` runs them on
disjoint pixel ranges in a short-lived thread pool. No OpenMP/TBB thread pool stays alive,
so a process that used them can still fork workers (GNU OpenMP aborts a forked child).
"""

from __future__ import annotations

import itertools
import os
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

#: Pixels per inner block: one block's window (n x BLOCK values) stays in the L2 cache.
BLOCK = 4096
#: Below this many pixels one thread does the work (thread start-up would dominate).
MIN_SPLIT = 1 << 16


@numba.njit(cache=True, nogil=True)
def select_rank(buf, rank, nbits, out, start, stop):
    """out[i] = rank-th smallest (0-based) of buf[:, i] for start <= i < stop.

    buf is (n, P) uint8 or uint16. Found bit by bit from the top: bit k is set when at most
    `rank` samples lie below prefix + 2^k. The inner loops are branch-free over contiguous
    memory, so LLVM vectorises them.
    """
    n = buf.shape[0]
    for a in range(start, stop, BLOCK):
        b = min(stop, a + BLOCK)
        m = b - a
        prefix = np.zeros(m, buf.dtype)
        cand = np.empty(m, buf.dtype)
        count = np.empty(m, np.uint16)
        for bit in range(nbits - 1, -1, -1):
            step = 1 << bit
            for i in range(m):
                cand[i] = prefix[i] + step  # never overflows: the lower bits of prefix are 0
                count[i] = 0
            for f in range(n):
                row = buf[f, a:b]
                for i in range(m):
                    count[i] += row[i] < cand[i]
            for i in range(m):
                if count[i] <= rank:
                    prefix[i] = cand[i]
        out[a:b] = prefix


@numba.njit(cache=True, nogil=True)
def compensate(frame, median, backscatter, a_ref, eps, albedo, valid, start, stop):
    """Fused ``F = (M - B) / A_ref``, ``A = (I - B) / max(F, eps)``, ``valid = all(F >= eps)``.

    frame, median : (H*W*C,) real; backscatter, albedo : (H*W*C,) float32; a_ref : (C,)
    float32; valid : (H*W,) bool; pixels start <= p < stop.
    """
    C = a_ref.shape[0]
    for p in range(start, stop):
        ok = True
        for c in range(C):
            k = p * C + c
            b = backscatter[k]
            f = (np.float32(median[k]) - b) / a_ref[c]
            if f < eps:
                ok = False
                f = eps
            albedo[k] = (np.float32(frame[k]) - b) / f
        valid[p] = ok


def cpu_threads() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def run_split(kernel, n_items: int, args: tuple, *, parallel: bool = True) -> None:
    """Call ``kernel(*args, start, stop)`` over [0, n_items), split across threads."""
    threads = min(cpu_threads(), max(1, n_items // MIN_SPLIT)) if parallel else 1
    if threads == 1:
        kernel(*args, 0, n_items)
        return
    bounds = np.linspace(0, n_items, threads + 1).astype(np.int64)
    # Block-align the cuts so no block straddles two threads (keeps blocks full).
    bounds[1:-1] = (bounds[1:-1] // BLOCK) * BLOCK
    with ThreadPoolExecutor(max_workers=threads) as pool:
        futures = [pool.submit(kernel, *args, int(a), int(b))
                   for a, b in itertools.pairwise(bounds) if b > a]  # fmt: skip
        for f in futures:
            f.result()
