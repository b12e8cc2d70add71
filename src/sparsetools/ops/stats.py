"""Depth map statistics: point count, density and depth range.

The intrinsic error against a reference map (``sparsetools stats --reference``) is
:func:`sparsetools.ops.intrinsic.intrinsic_error` (METHODS.md section 3).
"""

from __future__ import annotations

import numpy as np

from ..validate import check_dtype, check_shape

__all__ = ["depth_stats"]


def _valid(depth: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > 0)


def _as_map(depth, name: str) -> np.ndarray:
    d = np.asarray(depth)
    check_shape(d, "(H, W)", name)
    check_dtype(d, name, "fiu")
    return d


def depth_stats(depth: np.ndarray) -> dict:
    """Point count, density and depth range of a depth map.

    Parameters
    ----------
    depth : (H, W) float, metres
        0, negative or non-finite = no measurement.

    Returns
    -------
    dict
        ``points`` (valid pixels), ``pixels`` (H * W), ``density_percent``
        (100 * points / pixels), and ``min``, ``median``, ``mean``, ``max`` depth in metres
        over valid pixels (None when there are none).
    """
    d = _as_map(depth, "depth")
    valid = _valid(d)
    vals = d[valid].astype(np.float64)
    n = int(vals.size)
    pixels = int(d.size)
    out = {
        "points": n,
        "pixels": pixels,
        "density_percent": 100.0 * n / pixels if pixels else 0.0,
        "min": None,
        "median": None,
        "mean": None,
        "max": None,
    }
    if n:
        out.update(
            min=float(vals.min()),
            median=float(np.median(vals)),
            mean=float(vals.mean()),
            max=float(vals.max()),
        )
    return out
