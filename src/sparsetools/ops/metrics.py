"""Depth-estimation metrics, per image then averaged (monodepth2 / KITTI conventions).

Every metric is computed on the pixels where the ground truth is valid
(``min_depth < gt < max_depth``, finite), with predictions clipped to
``[min_depth, max_depth]`` as monodepth2 does. Metrics are computed per image and then
averaged over images (:func:`aggregate_metrics`), never pooled over all pixels of a set.

=============  ==============================================  =======
name           definition (g = ground truth, p = prediction)    unit
=============  ==============================================  =======
abs_rel        mean |g - p| / g                                  -
sq_rel         mean (g - p)^2 / g  (monodepth2 "sq_rel")        m
sq_rel_kitti   mean ((g - p) / g)^2  (KITTI devkit "sqErrorRel") -
rmse           sqrt(mean (g - p)^2)                              m
rmse_log       sqrt(mean (log g - log p)^2)                      -
log10          mean |log10 g - log10 p|  (BTS "log10")          -
silog          100 sqrt(mean d^2 - (mean d)^2), d = log p - log g  100 log(m)
delta1..3      fraction of max(g/p, p/g) < 1.25^k                -
mae            mean |g - p|                                      m
irmse          sqrt(mean (1/g - 1/p)^2)                          1/km
imae           mean |1/g - 1/p|                                  1/km
=============  ==============================================  =======

``silog`` is the KITTI depth-prediction benchmark's scale-invariant log error (as in the KITTI
devkit and BTS's evaluation), distinct from the SILog *training loss* (lambda = 0.85).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np

from ..errors import ParameterError
from ..validate import (
    check_dtype,
    check_increasing,
    check_int_range,
    check_ordered,
    check_positive,
    check_same_shape,
    check_shape,
)

__all__ = [
    "METRIC_NAMES",
    "aggregate_depth_bins",
    "aggregate_metrics",
    "depth_bin_edges",
    "depth_metrics",
    "evaluated_mask",
    "format_metrics_table",
    "garg_crop_mask",
]

#: Metric names in report order.
METRIC_NAMES = (
    "abs_rel",
    "sq_rel",
    "sq_rel_kitti",
    "rmse",
    "rmse_log",
    "log10",
    "silog",
    "delta1",
    "delta2",
    "delta3",
    "mae",
    "irmse",
    "imae",
)

#: Metrics where larger is better (the others are errors).
HIGHER_IS_BETTER = frozenset({"delta1", "delta2", "delta3"})


def garg_crop_mask(height: int, width: int) -> np.ndarray:
    """The Garg/Eigen evaluation crop of monodepth2 as an (H, W) bool mask.

    Rows ``[0.40810811 H, 0.99189189 H)`` and columns ``[0.03594771 W, 0.96405229 W)``,
    truncated to integers as monodepth2 does.
    """
    height = check_int_range(height, "height", low=1)
    width = check_int_range(width, "width", low=1)
    top, bottom, left, right = np.array(
        [0.40810811 * height, 0.99189189 * height, 0.03594771 * width, 0.96405229 * width]
    ).astype(np.int32)
    mask = np.zeros((height, width), dtype=bool)
    mask[top:bottom, left:right] = True
    return mask


def evaluated_mask(
    gt: np.ndarray, *, min_depth: float = 1e-3, max_depth: float = 80.0, garg_crop: bool = False
) -> np.ndarray:
    """The pixels :func:`depth_metrics` evaluates: finite ``min_depth < gt < max_depth`` (and
    inside the Garg crop when asked).

    Parameters
    ----------
    gt : (H, W) array, metres

    Returns
    -------
    (H, W) bool
    """
    g = np.asarray(gt, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(g) & (g > min_depth) & (g < max_depth)
    if garg_crop:
        valid &= garg_crop_mask(*g.shape)
    return valid


def depth_metrics(
    pred: np.ndarray,
    gt: np.ndarray,
    *,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    garg_crop: bool = False,
    median_scaling: bool = False,
    bin_edges: tuple[float, ...] | None = None,
) -> dict:
    """All depth metrics of one image.

    Parameters
    ----------
    pred : (H, W) float, metres
        Predicted depth. Clipped to ``[min_depth, max_depth]`` before the metrics (so a 0 =
        "no prediction" counts as ``min_depth``, as in monodepth2).
    gt : (H, W) float, metres
        Ground truth; 0 or non-finite = no measurement.
    min_depth, max_depth : float, metres
        Pixels with ``min_depth < gt < max_depth`` are evaluated.
    garg_crop : bool
        Only evaluate inside the Garg crop (:func:`garg_crop_mask`). For KITTI Eigen-split
        monocular evaluation; off by default.
    median_scaling : bool
        Scale the prediction by ``median(gt) / median(pred)`` over the evaluated pixels
        (before clipping), for scale-ambiguous monocular methods. Never for depth completion.
    bin_edges : (K + 1,) float, metres, optional
        Also the errors of the same pixels by ground-truth depth bin ``[e_k, e_k+1)``:
        ``depth_bins`` holds ``pixels``, ``abs_err_sum`` (m) and ``sq_err_sum`` (m^2), K each
        (sums, so that :func:`aggregate_depth_bins` pools them over images).

    Returns
    -------
    dict
        One float per name of :data:`METRIC_NAMES` (NaN when no pixel is valid) and
        ``n_pixels`` (int, evaluated pixels); with ``median_scaling`` also ``scale``; with
        ``bin_edges`` also ``depth_bins``.

    Raises
    ------
    ParameterError
        Shapes differ or are not 2-D, bad depth range, or a non-finite prediction on an
        evaluated pixel.
    """
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    check_shape(pred, "(H, W)", "pred")
    check_shape(gt, "(H, W)", "gt")
    check_same_shape(pred, gt, "pred", "gt")
    check_dtype(pred, "pred", "fiu")
    check_dtype(gt, "gt", "fiu")
    check_positive(min_depth, "min_depth")
    check_positive(max_depth, "max_depth")
    check_ordered(min_depth, max_depth, "min_depth", "max_depth")
    g = gt.astype(np.float64)
    valid = evaluated_mask(g, min_depth=min_depth, max_depth=max_depth, garg_crop=garg_crop)
    g = g[valid]
    p = pred[valid].astype(np.float64)
    n = int(g.size)
    out: dict = {}
    if bin_edges is not None:
        edges = check_increasing(bin_edges, "bin_edges")
    if n == 0:
        out = dict.fromkeys(METRIC_NAMES, math.nan)
        out["n_pixels"] = 0
        if median_scaling:
            out["scale"] = math.nan
        if bin_edges is not None:
            zeros = [0] * (edges.size - 1)
            out["depth_bins"] = {"pixels": zeros, "abs_err_sum": [0.0] * len(zeros),
                                 "sq_err_sum": [0.0] * len(zeros)}  # fmt: skip
        return out
    bad = int(np.count_nonzero(np.isnan(p)))
    if bad:
        raise ParameterError(f"prediction is NaN on {bad} of {n} evaluated pixels")
    if median_scaling:
        med = float(np.median(p))
        if not med > 0:
            raise ParameterError("median scaling needs a positive median prediction")
        scale = float(np.median(g)) / med
        p = p * scale
        out["scale"] = scale
    p = np.clip(p, min_depth, max_depth)

    err = g - p
    abs_err = np.abs(err)
    sq_err = err * err
    log_diff = np.log(p) - np.log(g)
    ratio = np.maximum(g / p, p / g)
    inv_err = 1000.0 / g - 1000.0 / p  # 1/km

    mean_log = float(np.mean(log_diff))
    silog_var = max(float(np.mean(log_diff * log_diff)) - mean_log * mean_log, 0.0)
    out.update(
        abs_rel=float(np.mean(abs_err / g)),
        sq_rel=float(np.mean(sq_err / g)),
        sq_rel_kitti=float(np.mean(sq_err / (g * g))),
        rmse=float(np.sqrt(np.mean(sq_err))),
        rmse_log=float(np.sqrt(np.mean(log_diff * log_diff))),
        log10=float(np.mean(np.abs(np.log10(p) - np.log10(g)))),
        silog=100.0 * math.sqrt(silog_var),
        delta1=float(np.mean(ratio < 1.25)),
        delta2=float(np.mean(ratio < 1.25**2)),
        delta3=float(np.mean(ratio < 1.25**3)),
        mae=float(np.mean(abs_err)),
        irmse=float(np.sqrt(np.mean(inv_err * inv_err))),
        imae=float(np.mean(np.abs(inv_err))),
        n_pixels=n,
    )
    keys = (*METRIC_NAMES, "n_pixels", *(("scale",) if median_scaling else ()))
    result = {k: out[k] for k in keys}
    if bin_edges is not None:
        k = edges.size - 1
        which = np.searchsorted(edges, g, side="right") - 1  # bin [e_k, e_k+1) of each pixel
        inside = (which >= 0) & (which < k)
        which = which[inside]
        result["depth_bins"] = {
            "pixels": np.bincount(which, minlength=k).tolist(),
            "abs_err_sum": np.bincount(which, abs_err[inside], minlength=k).tolist(),
            "sq_err_sum": np.bincount(which, sq_err[inside], minlength=k).tolist(),
        }
    return result


def aggregate_metrics(per_image: Iterable[Mapping]) -> dict:
    """Average per-image metrics over the images that had evaluated pixels.

    Parameters
    ----------
    per_image : iterable of dict
        Results of :func:`depth_metrics`.

    Returns
    -------
    dict
        The mean of each metric of :data:`METRIC_NAMES` over images with ``n_pixels > 0``,
        ``n_images`` (images averaged), ``n_empty`` (images without a valid pixel, left out)
        and ``n_pixels`` (total evaluated pixels).

    Raises
    ------
    ParameterError
        No image had a valid ground-truth pixel.
    """
    rows = list(per_image)
    used = [r for r in rows if r.get("n_pixels", 0) > 0]
    if not used:
        raise ParameterError(
            f"no valid ground-truth pixel in any of the {len(rows)} image(s): nothing to evaluate"
        )
    out = {k: float(np.mean([float(r[k]) for r in used])) for k in METRIC_NAMES}
    out["n_images"] = len(used)
    out["n_empty"] = len(rows) - len(used)
    out["n_pixels"] = int(sum(int(r["n_pixels"]) for r in used))
    return out


def depth_bin_edges(max_depth: float = 80.0, *, step: float = 10.0) -> tuple[float, ...]:
    """Ground-truth depth bins of ``eval --plot``: 0-5, 5-10 m, then ``step`` m up to
    ``max_depth`` (the last bin ends there), metres."""
    check_positive(max_depth, "max_depth")
    check_positive(step, "step")
    edges = [e for e in (0.0, 5.0) if e < max_depth]
    edges += [float(e) for e in np.arange(10.0, max_depth, step)]
    return (*edges, float(max_depth))


def aggregate_depth_bins(per_image: Iterable[Mapping], bin_edges) -> dict:
    """Errors by ground-truth depth bin pooled over images (every evaluated pixel counts once).

    Parameters
    ----------
    per_image : iterable of dict
        Results of :func:`depth_metrics` with ``bin_edges`` (their ``depth_bins``).
    bin_edges : (K + 1,) float, metres

    Returns
    -------
    dict
        ``edges_m`` (K + 1), and per bin ``pixels``, ``mae`` (m) and ``rmse`` (m) (None for a
        bin without pixels: the dict is JSON as it is).
    """
    edges = [float(e) for e in bin_edges]
    k = len(edges) - 1
    pixels = np.zeros(k, np.int64)
    abs_sum = np.zeros(k)
    sq_sum = np.zeros(k)
    for r in per_image:
        b = r["depth_bins"]
        pixels += np.asarray(b["pixels"], np.int64)
        abs_sum += np.asarray(b["abs_err_sum"], np.float64)
        sq_sum += np.asarray(b["sq_err_sum"], np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mae = np.where(pixels > 0, abs_sum / pixels, np.nan)
        rmse = np.where(pixels > 0, np.sqrt(sq_sum / pixels), np.nan)

    def listed(a):
        return [float(v) if np.isfinite(v) else None for v in a]

    return {"edges_m": edges, "pixels": pixels.tolist(), "mae": listed(mae),
            "rmse": listed(rmse)}  # fmt: skip


_UNITS = {
    "sq_rel": "m",
    "rmse": "m",
    "mae": "m",
    "irmse": "1/km",
    "imae": "1/km",
}


def format_metrics_table(metrics: Mapping, *, title: str = "") -> str:
    """A two-column text table (metric, value with unit) of :data:`METRIC_NAMES`."""
    lines = [title] if title else []
    for k in METRIC_NAMES:
        if k not in metrics:
            continue
        v = float(metrics[k])
        unit = _UNITS.get(k, "")
        lines.append(f"{k:<13} {v:>10.4f} {unit}".rstrip())
    for k in ("n_images", "n_empty", "n_pixels"):
        if k in metrics:
            lines.append(f"{k:<13} {int(metrics[k]):>10d}")
    return "\n".join(lines)
