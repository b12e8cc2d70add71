"""The gray and RGB JBF band kernels as they were before the merge (0.2.0), for bench_jbf only.

``sparsetools.ops._jbf_kernels`` keeps one band kernel for any number of guide channels (issue
22); these two near copies, one per channel count, stay here verbatim so that the benchmark
can time the merged kernel against them on the same input, interleaved. Not part of the
package: nothing in ``src/`` imports this file.
"""

from __future__ import annotations

import numba
import numpy as np

from sparsetools.ops._jbf_kernels import (
    _BYTES_GATHER,
    _BYTES_LOW,
    _SEED_CONF,
    _better,
    mark_seeds,
    prologue,
)

__all__ = ["expand_gray", "expand_rgb"]


@numba.njit(cache=True, nogil=True)
def _band_gray(
    rows,
    cols,
    depths,
    half_u,
    half_v,
    guide,
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
    """Rows ``y_lo:y_hi`` of the expansion for an (H, W) uint8 guidance."""
    width = guide.shape[1]
    mask = np.zeros(8 * ((width + 7) // 8 + 1), dtype=np.uint8)
    words = mask.view(np.uint64)
    for s in range(rows.shape[0]):
        y0 = rows[s]
        x0 = cols[s]
        d = depths[s]
        g0 = np.int32(guide[y0, x0])
        hv = min(half_v[s], half_width.shape[0] - 1)
        for y in range(max(y0 - hv, y_lo), min(y0 + hv, y_hi - 1) + 1):
            j = abs(y - y0)
            hu = min(half_u[s], half_width[j])
            left = max(x0 - hu, 0)
            right = min(x0 + hu, width - 1) + 1
            m = right - left
            if m <= 0:
                continue
            g_seg = guide[y, left:right]
            d_seg = depth[y, left:right]
            t_seg = pass_t[j if use_spatial else 0, center + left - x0 : center + right - x0]
            if max_confidence:
                for k in range(m):
                    diff = np.int32(g_seg[k]) - g0
                    mask[k] = np.uint8(diff * diff <= t_seg[k])
            else:
                for k in range(m):
                    diff = np.int32(g_seg[k]) - g0
                    bd = d_seg[k]
                    mask[k] = np.uint8((diff * diff <= t_seg[k]) & ((bd == 0) | (bd >= d)))
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
                    t = 0
                    if use_range:
                        diff = np.int64(g_seg[k]) - g0
                        t = diff * diff
                    if use_spatial:
                        i = left + k - x0
                        c = np.float32(spatial_lut[i * i + j2] * range_lut[t])
                    else:
                        c = np.float32(range_lut[t])
                    if _better(d, c, d_seg[k], bc, max_confidence):
                        d_seg[k] = d
                        c_seg[k] = c


@numba.njit(cache=True, nogil=True)
def _band_rgb(
    rows,
    cols,
    depths,
    half_u,
    half_v,
    guide,
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
    """Rows ``y_lo:y_hi`` for an (H, W, 3) guidance compared by Euclidean RGB distance."""
    width = guide.shape[1]
    mask = np.zeros(8 * ((width + 7) // 8 + 1), dtype=np.uint8)
    words = mask.view(np.uint64)
    for s in range(rows.shape[0]):
        y0 = rows[s]
        x0 = cols[s]
        d = depths[s]
        r0 = np.int32(guide[y0, x0, 0])
        g0 = np.int32(guide[y0, x0, 1])
        b0 = np.int32(guide[y0, x0, 2])
        hv = min(half_v[s], half_width.shape[0] - 1)
        for y in range(max(y0 - hv, y_lo), min(y0 + hv, y_hi - 1) + 1):
            j = abs(y - y0)
            hu = min(half_u[s], half_width[j])
            left = max(x0 - hu, 0)
            right = min(x0 + hu, width - 1) + 1
            m = right - left
            if m <= 0:
                continue
            p_seg = guide[y, left:right]
            d_seg = depth[y, left:right]
            t_seg = pass_t[j if use_spatial else 0, center + left - x0 : center + right - x0]
            for k in range(m):
                dr = np.int32(p_seg[k, 0]) - r0
                dg = np.int32(p_seg[k, 1]) - g0
                db = np.int32(p_seg[k, 2]) - b0
                ok = dr * dr + dg * dg + db * db <= t_seg[k]
                if not max_confidence:
                    bd = d_seg[k]
                    ok = ok & ((bd == 0) | (bd >= d))
                mask[k] = np.uint8(ok)
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
                    t = 0
                    if use_range:
                        dr = np.int64(p_seg[k, 0]) - r0
                        dg = np.int64(p_seg[k, 1]) - g0
                        db = np.int64(p_seg[k, 2]) - b0
                        t = dr * dr + dg * dg + db * db
                    if use_spatial:
                        i = left + k - x0
                        c = np.float32(spatial_lut[i * i + j2] * range_lut[t])
                    else:
                        c = np.float32(range_lut[t])
                    if _better(d, c, d_seg[k], bc, max_confidence):
                        d_seg[k] = d
                        c_seg[k] = c


@numba.njit(cache=True, nogil=True)
def expand_gray(rows, cols, depths, half_u, half_v, guide, spatial_lut, range_lut, use_spatial,
                use_range, threshold, max_confidence, depth, conf):  # fmt: skip  # pragma: no cover
    """Expansion for an (H, W) uint8 guidance, one thread."""
    pass_t, half_width, center, positions, counts = prologue(
        rows, cols, depths, spatial_lut, range_lut, use_spatial, use_range, threshold, depth, conf
    )
    _band_gray(rows, cols, depths, half_u, half_v, guide, spatial_lut, range_lut, use_spatial,
               use_range, max_confidence, pass_t, half_width, center, positions, counts, depth,
               conf, 0, depth.shape[0])  # fmt: skip
    mark_seeds(rows, cols, depths, depth, conf)


@numba.njit(cache=True, nogil=True)
def expand_rgb(rows, cols, depths, half_u, half_v, guide, spatial_lut, range_lut, use_spatial,
               use_range, threshold, max_confidence, depth, conf):  # fmt: skip  # pragma: no cover
    """Expansion for an (H, W, 3) uint8 guidance (Euclidean RGB distance), one thread."""
    pass_t, half_width, center, positions, counts = prologue(
        rows, cols, depths, spatial_lut, range_lut, use_spatial, use_range, threshold, depth, conf
    )
    _band_rgb(rows, cols, depths, half_u, half_v, guide, spatial_lut, range_lut, use_spatial,
              use_range, max_confidence, pass_t, half_width, center, positions, counts, depth,
              conf, 0, depth.shape[0])  # fmt: skip
    mark_seeds(rows, cols, depths, depth, conf)
