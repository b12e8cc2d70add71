"""Intrinsic error of a sparse or expanded depth map against LiDAR (Lo & Vandewalle 2024, 3.3).

The paper's Tables 1 and 5 compare each radar format with the projected LiDAR at the pixels
where both have a value (LiDAR depth <= 80 m) and list delta1, delta2, RMSE, the number of
points of the radar map and its density.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from ..validate import check_positive, check_same_shape, check_shape

__all__ = ["INTRINSIC_KEYS", "intrinsic_error", "mean_intrinsic_error"]

#: Keys of the dictionary returned by :func:`intrinsic_error`, in table order.
INTRINSIC_KEYS = ("delta1", "delta2", "rmse", "points", "density_percent", "evaluated")


def intrinsic_error(expanded: np.ndarray, lidar: np.ndarray, *, max_depth: float = 80.0) -> dict:
    """Compare a (sparse or expanded) depth map with LiDAR depth where both are valid.

    Parameters
    ----------
    expanded : (H, W) float, metres
        Radar depth (raw, expanded, height-extended...); 0 or non-finite = empty.
    lidar : (H, W) float, metres
        Reference depth; 0 or non-finite = empty. Pixels with LiDAR depth above ``max_depth``
        are not evaluated.
    max_depth : float, metres
        Evaluation cap (the paper uses 80 m).

    Returns
    -------
    dict
        ``delta1``, ``delta2``: fraction of evaluated pixels with ``max(r/l, l/r) < 1.25^k``;
        ``rmse``: metres (NaN when no pixel is evaluated, as are the deltas);
        ``points``: valid pixels of ``expanded`` (the paper's "# points");
        ``density_percent``: ``points`` in percent of all pixels;
        ``evaluated``: pixels valid in both maps with LiDAR <= ``max_depth``.
    """
    r = np.asarray(expanded)
    l = np.asarray(lidar)
    check_shape(r, "(H, W)", "expanded")
    check_shape(l, "(H, W)", "lidar")
    check_same_shape(r, l, "expanded", "lidar")
    check_positive(max_depth, "max_depth")
    r = r.astype(np.float64, copy=False)
    l = l.astype(np.float64, copy=False)
    r_valid = np.isfinite(r) & (r > 0)
    both = r_valid & np.isfinite(l) & (l > 0) & (l <= max_depth)
    points = int(np.count_nonzero(r_valid))
    out = {
        "points": points,
        "density_percent": 100.0 * points / r.size if r.size else 0.0,
        "evaluated": int(np.count_nonzero(both)),
    }
    if out["evaluated"] == 0:
        out.update(delta1=math.nan, delta2=math.nan, rmse=math.nan)
    else:
        rv = r[both]
        lv = l[both]
        ratio = np.maximum(rv / lv, lv / rv)
        out.update(
            delta1=float(np.mean(ratio < 1.25)),
            delta2=float(np.mean(ratio < 1.25**2)),
            rmse=float(np.sqrt(np.mean((rv - lv) ** 2))),
        )
    return {k: out[k] for k in INTRINSIC_KEYS}


def mean_intrinsic_error(results: Iterable[dict]) -> dict:
    """Average per-frame :func:`intrinsic_error` results, as the paper's tables do.

    Every key is the mean over frames; frames without evaluated pixels (NaN metrics) are left
    out of the delta and RMSE means. ``frames`` gives how many results were averaged.
    """
    results = list(results)
    out: dict = {}
    for key in INTRINSIC_KEYS:
        values = np.array([float(r[key]) for r in results], dtype=np.float64)
        values = values[np.isfinite(values)]
        out[key] = float(values.mean()) if values.size else math.nan
    out["frames"] = len(results)
    return out
