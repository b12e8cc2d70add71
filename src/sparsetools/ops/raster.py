"""Rasterisation of linear interpolants on triangles (the linear fill of ``densify``).

The same values as ``scipy.interpolate.LinearNDInterpolator`` on the same triangulation,
without its per-triangle LAPACK calls (which OpenBLAS's threads make seconds slow on a busy
machine). Pure numpy: batches of pixels, no loop over triangles or pixels.
"""

from __future__ import annotations

import numpy as np

from ..validate import check_dtype, check_int_range, check_shape

__all__ = ["rasterise_triangles"]


def rasterise_triangles(
    xy: np.ndarray,
    values: np.ndarray,
    simplices: np.ndarray,
    out: np.ndarray,
    *,
    chunk: int = 1 << 22,
) -> None:
    """Write the linear interpolant of every triangle into the pixels it covers (in place).

    Parameters
    ----------
    xy : (M, 2) int64, pixels
        Column and row of each vertex (inside ``out``).
    values : (M,) float64
        Value at each vertex (depth in metres for :func:`sparsetools.ops.densify.fill_linear`).
    simplices : (T, 3) int
        Vertex indices of each triangle (``scipy.spatial.Delaunay(...).simplices``).
    out : (H, W) float array
        Pixels inside or on a triangle get the barycentric combination of its vertex values;
        the others are left alone. Triangles of zero area are skipped.
    chunk : int
        Pixels of bounding boxes handled per batch (bounds the memory).

    Notes
    -----
    Every triangle's bounding box is tested with exact integer edge functions, all triangles
    of a batch at once; a pixel on an edge shared by two triangles gets either value (they
    agree up to rounding).
    """
    n_vertices = check_shape(xy, "(M, 2)", "xy")["M"]
    check_dtype(xy, "xy", "iu")  # exact integer edge functions
    check_shape(values, f"({n_vertices})", "values")
    check_shape(simplices, "(T, 3)", "simplices")
    check_dtype(simplices, "simplices", "iu")
    check_shape(out, "(H, W)", "out")
    chunk = check_int_range(chunk, "chunk", low=1)
    a, b, c = (xy[simplices[:, k]] for k in range(3))
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    tri = np.flatnonzero(area != 0)
    lo = np.minimum(np.minimum(a, b), c)
    span = np.maximum(np.maximum(a, b), c) - lo + 1
    n_px = span[:, 0] * span[:, 1]
    ends = np.cumsum(n_px[tri])
    for start in range(0, int(ends[-1]) if tri.size else 0, chunk):  # batches, not points
        sel = tri[(ends > start) & (ends - n_px[tri] < start + chunk)]
        t = np.repeat(sel, n_px[sel])
        k = np.arange(t.size) - np.repeat(np.cumsum(n_px[sel]) - n_px[sel], n_px[sel])
        px = lo[t, 0] + k % span[t, 0]
        py = lo[t, 1] + k // span[t, 0]
        # Twice the signed areas of (p, b, c) and (a, p, c): barycentric weights of a and b.
        wa = (b[t, 0] - px) * (c[t, 1] - py) - (c[t, 0] - px) * (b[t, 1] - py)
        wb = (c[t, 0] - px) * (a[t, 1] - py) - (a[t, 0] - px) * (c[t, 1] - py)
        wc = area[t] - wa - wb
        sign = np.sign(area[t])
        inside = (wa * sign >= 0) & (wb * sign >= 0) & (wc * sign >= 0)
        t, px, py = t[inside], px[inside], py[inside]
        wa, wb, wc = wa[inside], wb[inside], wc[inside]
        vs = values[simplices[t]]
        z = (wa * vs[:, 0] + wb * vs[:, 1] + wc * vs[:, 2]) / area[t]
        out[py, px] = z.astype(out.dtype)
