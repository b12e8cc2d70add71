"""Compiled z-buffer kernels of :mod:`sparsetools.ops.projection` (numba).

Kept apart so that importing :mod:`~sparsetools.ops.projection` does not import numba: a
process pays numba's load (about 0.5 s) only once its projections are many enough to gain
from the compiled loop (see ``projection._use_compiled``).

One pass over the points, a scatter with a min: O(N), no sort, no allocation per point. The
arithmetic is float64 whatever the input dtype, in the order a matrix product would use, with
no fused multiply-add (numba does not contract without ``fastmath``), so the numpy
implementation in :mod:`~sparsetools.ops.projection` lands every point in the same pixel with
the same depth.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["zbuffer_depth", "zbuffer_index"]


#: Margin of the division-free pre-test, in pixels: far above the rounding of ``U / w`` near
#: the image (relative 1e-16 of at most ~1e5), far below a pixel.
_PRETEST_MARGIN = 1e-6


@njit(cache=True, nogil=True)
def zbuffer_depth(points, M, min_depth, max_depth, offset, depth):  # pragma: no cover - jitted
    """Nearest depth per pixel into ``depth`` (zeros on entry); returns the points that landed."""
    height, width = depth.shape
    m00, m01, m02, m03 = M[0, 0], M[0, 1], M[0, 2], M[0, 3]
    m10, m11, m12, m13 = M[1, 0], M[1, 1], M[1, 2], M[1, 3]
    m20, m21, m22, m23 = M[2, 0], M[2, 1], M[2, 2], M[2, 3]
    # A point lands only if rint(U / w) + offset is in 0 .. width - 1, i.e. U / w in
    # [-offset - 0.5, width - 1 - offset + 0.5]: with w > 0 the widened test on U and u_lo * w
    # (no division) rejects only points the exact test rejects too, and spares the divisions
    # of the many points in front of the sensor but outside the image.
    u_lo = -offset - 0.5 - _PRETEST_MARGIN
    u_hi = width - 1 - offset + 0.5 + _PRETEST_MARGIN
    v_hi = height - 1 - offset + 0.5 + _PRETEST_MARGIN
    n_in = 0
    for i in range(points.shape[0]):
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        w = m20 * x + m21 * y + m22 * z + m23
        # Written so that NaN fails every test and is dropped.
        if not (w > min_depth and w <= max_depth):
            continue
        U = m00 * x + m01 * y + m02 * z + m03
        if U < u_lo * w or U > u_hi * w:
            continue
        V = m10 * x + m11 * y + m12 * z + m13
        if V < u_lo * w or V > v_hi * w:
            continue
        fu = np.rint(U / w) + offset
        fv = np.rint(V / w) + offset
        if not (fu >= 0.0 and fu < width and fv >= 0.0 and fv < height):
            continue
        d = np.float32(w)
        if d <= 0.0:  # below float32's range: cannot be told from "empty"
            continue
        n_in += 1
        iu = int(fu)
        iv = int(fv)
        cur = depth[iv, iu]
        if cur == 0.0 or d < cur:
            depth[iv, iu] = d
    return n_in


@njit(cache=True, nogil=True)
def zbuffer_index(points, M, min_depth, max_depth, offset, depth, index):  # pragma: no cover
    """:func:`zbuffer_depth` that also records the winning row per pixel in ``index``."""
    height, width = depth.shape
    # Exact float64 depth of each point that landed: ties are judged in float64, not in the
    # float32 of the output map.
    w_of = np.empty(points.shape[0], dtype=np.float64)
    n_in = 0
    for i in range(points.shape[0]):
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        w = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + M[2, 3]
        if not (w > min_depth and w <= max_depth):
            continue
        fu = np.rint((M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + M[0, 3]) / w) + offset
        fv = np.rint((M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + M[1, 3]) / w) + offset
        if not (fu >= 0.0 and fu < width and fv >= 0.0 and fv < height):
            continue
        d = np.float32(w)
        if d <= 0.0:
            continue
        n_in += 1
        w_of[i] = w
        iu = int(fu)
        iv = int(fv)
        j = index[iv, iu]
        if j < 0 or w < w_of[j] or (w == w_of[j] and _before(points, i, j)):
            index[iv, iu] = i
            depth[iv, iu] = d
    return n_in


@njit(cache=True, nogil=True, inline="always")
def _before(points, i, j):  # pragma: no cover - jitted
    # A tie in depth goes to the lexicographically smaller (x, y, z): a rule on content, not on
    # position, so the winner does not depend on point order. Exact duplicates keep the earlier
    # (smaller) index because i > j here.
    for c in range(3):
        a = np.float64(points[i, c])
        b = np.float64(points[j, c])
        if a != b:
            return a < b
    return False
