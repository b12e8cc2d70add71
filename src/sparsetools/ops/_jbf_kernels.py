"""Compiled kernels of :func:`sparsetools.ops.jbf.jbf_expand` (numba, ``cache=True``).

One band kernel serves every guidance, gray or RGB, as an (H, W, C) array (as scikit-image's
``denoise_bilateral`` keeps one kernel for any channel count): the channel count C travels as
the length of a tuple, which is part of its numba type, so numba compiles one machine code per
C, with the channel loop unrolled and constant pixel strides (``benchmarks/bench_jbf.py
--kernels`` times it against the two kernels it replaced).

For every seed the kernel visits the rows of its window, cut to the pruning disc, in two
passes per row:

1. a candidate mask, computed with affine loads only so that LLVM vectorises it: a pixel at
   offset (i, j) passes iff its squared intensity distance t is <= pass_t[j, i], the
   largest t that passes at that offset (an exact integer form of C >= threshold, see
   :func:`_offset_table`), and, for conflict="nearest", it is not already taken by a nearer
   seed;
2. the few candidates, found 8 mask bytes at a time, get their confidence from the lookup
   tables and are updated.

Loop indices start at 0 so that numba emits no negative-index wraparound code.
"""

from __future__ import annotations

import numba
import numpy as np
from numba.np.unsafe.ndarray import to_fixed_tuple

__all__ = ["band", "expand", "mark_seeds", "prologue"]

# Internal confidence of a seed pixel: above any real confidence, so nothing replaces it.
_SEED_CONF = np.float32(2.0)
_ANY_T = 1 << 30  # passes whatever the intensity difference (above 3 * 255^2)
_BYTES_LOW = np.uint64(0x0101010101010101)
_BYTES_GATHER = np.uint64(0x0102040810204080)


@numba.njit(cache=True, nogil=True)
def _largest_passing_t(w, range_lut, threshold):  # pragma: no cover - compiled
    """Largest t with ``w * range_lut[t] >= threshold`` (-1: none).

    ``range_lut`` is non-increasing and multiplying by ``w > 0`` is monotone in IEEE
    arithmetic, so the passing t form a prefix and a binary search finds its end exactly.
    """
    if not (w * range_lut[0] >= threshold):
        return -1
    lo = 0
    hi = range_lut.shape[0] - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if w * range_lut[mid] >= threshold:
            lo = mid
        else:
            hi = mid - 1
    return lo


@numba.njit(cache=True, nogil=True)
def _offset_table(spatial_lut, range_lut, use_spatial, use_range, threshold, height, width):
    """Largest passing squared intensity difference at each pixel offset.

    Returns ``(pass_t, half_width, center)``. With the spatial kernel, ``pass_t[j, center + i]``
    is the table for offsets (i, j), |i|, |j| <= R (the disc radius), and ``half_width[j]``
    the largest |i| that can pass in row offset j (-1: none). Without it, every offset is
    alike: one row of ``2 width + 1`` entries and no row limit.
    """  # pragma: no cover - compiled
    if not use_spatial:
        t = _largest_passing_t(1.0, range_lut, threshold) if use_range else _ANY_T
        pass_t = np.full((1, 2 * width + 1), t, dtype=np.int32)
        half_width = np.full(height + 1, width + 1, dtype=np.int64)
        return pass_t, half_width, width
    r2_last = spatial_lut.shape[0] - 1
    R = np.int64(np.sqrt(r2_last)) + 1
    pass_t = np.full((R + 1, 2 * R + 1), -1, dtype=np.int32)
    half_width = np.full(R + 1, -1, dtype=np.int64)
    for j in range(R + 1):
        for i in range(R + 1):
            r2 = i * i + j * j
            if r2 > r2_last:
                break
            if use_range:
                t = _largest_passing_t(spatial_lut[r2], range_lut, threshold)
            else:
                t = _ANY_T if spatial_lut[r2] >= threshold else -1
            pass_t[j, R + i] = t
            pass_t[j, R - i] = t
            if t >= 0:
                half_width[j] = i
    return pass_t, half_width, R


@numba.njit(cache=True, nogil=True)
def _byte_positions():  # pragma: no cover - compiled
    """For each 8-bit pattern: how many bits are set, and their positions."""
    positions = np.zeros((256, 8), dtype=np.int64)
    counts = np.zeros(256, dtype=np.int64)
    for b in range(256):
        c = 0
        for p in range(8):
            if (b >> p) & 1:
                positions[b, c] = p
                c += 1
        counts[b] = c
    return positions, counts


@numba.njit(cache=True, nogil=True)
def _mark_seeds(rows, cols, depths, depth, conf, value):  # pragma: no cover - compiled
    for s in range(rows.shape[0]):
        depth[rows[s], cols[s]] = depths[s]
        conf[rows[s], cols[s]] = value


@numba.njit(cache=True, nogil=True)
def _better(d, c, bd, bc, max_confidence):  # pragma: no cover - compiled
    """Whether (d, c) replaces the current (bd, bc) of a pixel that is not a seed.

    A total order on (depth, confidence) pairs, so the result does not depend on the order
    of the seeds (equal pairs are the same output).
    """
    if bd == 0:
        return True
    if max_confidence:
        return c > bc or (c == bc and d < bd)
    return d < bd or (d == bd and c > bc)


@numba.njit(cache=True, nogil=True)
def _dist2(p_seg, k, p0):  # pragma: no cover - compiled
    """Squared Euclidean distance (int32) between the tuple ``p0`` and pixel k of ``p_seg``,
    a row segment with its channels interleaved (``len(p0)`` values a pixel).

    ``len(p0)`` is part of the tuple's type: the channel loop and the pixel stride are
    constants, so LLVM unrolls the one and the caller's pixel loop stays vectorisable.
    """
    n_ch = len(p0)
    dist2 = np.int32(0)
    for ch in range(n_ch):
        diff = np.int32(p_seg[k * n_ch + ch]) - np.int32(p0[ch])
        dist2 += diff * diff
    return dist2


@numba.njit(cache=True, nogil=True)
def _band(
    rows,
    cols,
    depths,
    half_u,
    half_v,
    guide,
    channels,
    spatial_lut,
    range_lut,
    use_spatial,
    use_range,
    max_confidence,
    pass_t,
    half_width,
    center,
    positions,
    counts,
    depth,
    conf,
    y_lo,
    y_hi,
):  # pragma: no cover - compiled
    """Rows ``y_lo:y_hi`` of the expansion for an (H, W, C) uint8 guidance.

    Intensities are compared by their squared Euclidean distance over the C channels (C = 1:
    gray, C = 3: RGB). ``channels`` is ``tuple(range(C))``: its length is part of its numba
    type, so every C compiles to its own machine code with a fully unrolled channel loop (as
    fast as a kernel written for that C alone; a run-time C loop is about twice as slow).
    """
    height, width = guide.shape[:2]
    n_ch = len(channels)  # a compile-time constant
    rows_flat = guide.reshape(height, width * n_ch)  # each row's channels interleaved
    mask = np.zeros(8 * ((width + 7) // 8 + 1), dtype=np.uint8)
    words = mask.view(np.uint64)
    for s in range(rows.shape[0]):
        y0 = rows[s]
        x0 = cols[s]
        d = depths[s]
        p0 = to_fixed_tuple(guide[y0, x0], n_ch)
        hv = min(half_v[s], half_width.shape[0] - 1)
        for y in range(max(y0 - hv, y_lo), min(y0 + hv, y_hi - 1) + 1):
            j = abs(y - y0)
            hu = min(half_u[s], half_width[j])
            left = max(x0 - hu, 0)
            right = min(x0 + hu, width - 1) + 1
            m = right - left
            if m <= 0:
                continue
            p_seg = rows_flat[y, left * n_ch : right * n_ch]
            d_seg = depth[y, left:right]
            t_seg = pass_t[j if use_spatial else 0, center + left - x0 : center + right - x0]
            if max_confidence:
                for k in range(m):
                    mask[k] = np.uint8(_dist2(p_seg, k, p0) <= t_seg[k])
            else:
                for k in range(m):
                    bd = d_seg[k]
                    mask[k] = np.uint8((_dist2(p_seg, k, p0) <= t_seg[k]) & ((bd == 0) | (bd >= d)))
            n_words = (m + 7) // 8
            for k in range(m, n_words * 8):
                mask[k] = 0
            c_seg = conf[y, left:right]
            j2 = (y - y0) * (y - y0)
            for w in range(n_words):
                word = words[w]
                if word == 0:
                    continue
                b = ((word & _BYTES_LOW) * _BYTES_GATHER) >> np.uint64(56)
                for p in range(counts[b]):
                    k = w * 8 + positions[b, p]
                    bc = c_seg[k]
                    if bc == _SEED_CONF:
                        continue
                    t = _dist2(p_seg, k, p0) if use_range else 0
                    if use_spatial:
                        i = left + k - x0
                        c = np.float32(spatial_lut[i * i + j2] * range_lut[t])
                    else:
                        c = np.float32(range_lut[t])
                    if _better(d, c, d_seg[k], bc, max_confidence):
                        d_seg[k] = d
                        c_seg[k] = c


# -- entry points -------------------------------------------------------------------------------
# The serial kernel runs every row as one band. For several threads, ``jbf._expand`` runs
# :func:`prologue`, then :func:`band` on bands of rows that each thread owns (no two threads
# write one pixel; nogil, so Python threads run them in parallel), then :func:`mark_seeds`.
# Every pixel ends with the best (depth, confidence) pair of the seeds that reach it, in a
# total order, so the result is the same for any split into bands, whatever the number of
# threads.


@numba.njit(cache=True, nogil=True)
def prologue(rows, cols, depths, spatial_lut, range_lut, use_spatial, use_range, threshold,
             depth, conf):  # fmt: skip  # pragma: no cover - compiled
    """Clear the outputs, reserve the seed pixels; the tables every band uses."""
    height, width = depth.shape
    depth[:, :] = 0.0
    conf[:, :] = 0.0
    _mark_seeds(rows, cols, depths, depth, conf, _SEED_CONF)
    pass_t, half_width, center = _offset_table(
        spatial_lut, range_lut, use_spatial, use_range, threshold, height, width
    )
    positions, counts = _byte_positions()
    return pass_t, half_width, center, positions, counts


@numba.njit(cache=True, nogil=True)
def mark_seeds(rows, cols, depths, depth, conf):  # pragma: no cover - compiled
    """Seeds keep their own depth, with confidence 1."""
    _mark_seeds(rows, cols, depths, depth, conf, np.float32(1.0))


band = _band


@numba.njit(cache=True, nogil=True)
def expand(rows, cols, depths, half_u, half_v, guide, channels, spatial_lut, range_lut,
           use_spatial, use_range, threshold, max_confidence, depth, conf):  # fmt: skip  # pragma: no cover
    """Expansion for an (H, W, C) uint8 guidance, one thread (arguments: see ``jbf._expand``)."""
    pass_t, half_width, center, positions, counts = prologue(
        rows, cols, depths, spatial_lut, range_lut, use_spatial, use_range, threshold, depth, conf
    )
    _band(rows, cols, depths, half_u, half_v, guide, channels, spatial_lut, range_lut,
          use_spatial, use_range, max_confidence, pass_t, half_width, center, positions, counts,
          depth, conf, 0, depth.shape[0])  # fmt: skip
    mark_seeds(rows, cols, depths, depth, conf)
