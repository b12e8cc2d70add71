"""What a predicted log-variance says: URL's uncertainty gate, sigma, and its calibration.

A learned densifier (``densify --method learned``, SpaDe of the all-day depth completion in
the DepthDark survey, section 6) gives, beside its coarse dense depth ``D_c``, a map
``U = log sigma^2`` per pixel (sigma in metres): the log of the variance of a Gaussian whose
mean is ``D_c``. This module turns ``U`` into what a user does with it:

- :func:`uncertainty_gate`: URL's gate ``lambda(U) = 1 / (1 + exp(alpha (U - beta)))``, the
  weight of ``D_c`` when it is fused with another dense prediction (the survey's typical
  values: ``alpha = 0.8``, ``beta = 0``). ``lambda`` is 0.5 at ``U = beta``, decreases
  monotonically with ``U`` and tends to 1 (trust ``D_c``) for ``U -> -inf``, 0 for ``U -> +inf``.
- :func:`gated_fusion`: ``lambda(U) D_c + (1 - lambda(U)) D_other``.
- :func:`sigma_from_log_var`: ``sigma = exp(U / 2)``, metres.
- :func:`calibration_bins`: the error of ``D_c`` against ground truth per bin of predicted
  sigma. For a calibrated ``U`` the errors of a bin are Gaussian with that sigma: their mean
  absolute value is ``sigma sqrt(2 / pi)`` (about ``0.80 sigma``) and their RMS ``sigma``.

Pure numpy (and :func:`scipy.special.expit` for a gate that never overflows); no torch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit

from ..validate import (
    check_all_finite,
    check_array,
    check_dtype,
    check_finite,
    check_increasing,
    check_positive,
    check_same_shape,
)

__all__ = [
    "GATE_ALPHA",
    "GATE_BETA",
    "GAUSSIAN_MAE_PER_SIGMA",
    "CalibrationBins",
    "calibration_bins",
    "gated_fusion",
    "sigma_from_log_var",
    "uncertainty_gate",
]

#: The survey's typical gate parameters (URL, section 6).
GATE_ALPHA = 0.8
GATE_BETA = 0.0
#: E|e| / sigma for a zero-mean Gaussian error e: sqrt(2 / pi).
GAUSSIAN_MAE_PER_SIGMA = float(np.sqrt(2.0 / np.pi))


def _float_map(a, name: str) -> np.ndarray:
    check_array(a, name)
    check_dtype(a, name, "f")
    check_all_finite(a, name)
    return a


def uncertainty_gate(
    log_var: np.ndarray, *, alpha: float = GATE_ALPHA, beta: float = GATE_BETA
) -> np.ndarray:
    """URL's uncertainty gate ``lambda(U) = 1 / (1 + exp(alpha (U - beta)))``.

    Parameters
    ----------
    log_var : (...) float32 or float64 array, log of square metres
        ``U = log sigma^2`` per pixel (any shape).
    alpha : float, 1 / log of square metres
        Steepness (> 0; the survey: 0.8).
    beta : float, log of square metres
        Where the gate is 0.5 (the survey: 0).

    Returns
    -------
    lam : (...) array of ``log_var``'s dtype, in [0, 1]
        The weight of the coarse depth ``D_c``: 0.5 at ``U = beta``, decreasing in ``U``.
        Computed as ``expit(-alpha (U - beta))``, which equals the formula and neither
        overflows nor divides by zero for any finite ``U``.

    Raises
    ------
    ParameterError
        ``log_var`` not a float array or holding NaN / Inf; ``alpha <= 0``; ``beta`` not finite.

    Examples
    --------
    >>> float(uncertainty_gate(np.array([0.0]))[0])
    0.5
    """
    _float_map(log_var, "log_var")
    alpha = check_positive(alpha, "alpha")
    beta = check_finite(beta, "beta")
    z = log_var.dtype.type(-alpha) * (log_var - log_var.dtype.type(beta))
    return expit(z).astype(log_var.dtype, copy=False)


def gated_fusion(
    coarse: np.ndarray,
    other: np.ndarray,
    log_var: np.ndarray,
    *,
    alpha: float = GATE_ALPHA,
    beta: float = GATE_BETA,
) -> np.ndarray:
    """``lambda(U) coarse + (1 - lambda(U)) other`` (URL's gated fusion).

    Parameters
    ----------
    coarse : (H, W) float array, metres
        The densifier's ``D_c``.
    other : (H, W) float array, metres
        Another dense prediction (a learned model's).
    log_var : (H, W) float array, log of square metres
        ``U`` of ``coarse``.
    alpha, beta : float
        Gate parameters (:func:`uncertainty_gate`).

    Returns
    -------
    (H, W) float array, metres (the dtype numpy gives the three inputs)
    """
    _float_map(coarse, "coarse")
    _float_map(other, "other")
    check_same_shape(coarse, other, "coarse", "other")
    check_same_shape(coarse, log_var, "coarse", "log_var")
    lam = uncertainty_gate(log_var, alpha=alpha, beta=beta)
    return lam * coarse + (1 - lam) * other


def sigma_from_log_var(log_var: np.ndarray) -> np.ndarray:
    """Standard deviation ``sigma = exp(U / 2)``, metres, of a log-variance map ``U``.

    Parameters
    ----------
    log_var : (...) float array, log of square metres

    Returns
    -------
    (...) array of ``log_var``'s dtype, metres, > 0
    """
    _float_map(log_var, "log_var")
    return np.exp(log_var * log_var.dtype.type(0.5))


@dataclass(frozen=True)
class CalibrationBins:
    """Error of a depth map against ground truth per bin of predicted sigma.

    Attributes
    ----------
    edges : (K + 1,) float64, metres
        Bin edges of sigma (bin k holds ``edges[k] <= sigma < edges[k + 1]``).
    count : (K,) int64
        Pixels per bin.
    sigma : (K,) float64, metres
        Mean predicted sigma of each bin (NaN for an empty bin).
    mae : (K,) float64, metres
        Mean absolute error of each bin (NaN for an empty bin).
    rmse : (K,) float64, metres
        Root mean square error of each bin (NaN for an empty bin).

    Notes
    -----
    A calibrated ``U`` gives ``mae`` close to :data:`GAUSSIAN_MAE_PER_SIGMA` ``* sigma`` and
    ``rmse`` close to ``sigma`` in every bin; ``mae / sigma`` above 0.80 means the errors are
    larger than predicted (over-confident), below it smaller (under-confident).
    """

    edges: np.ndarray
    count: np.ndarray
    sigma: np.ndarray
    mae: np.ndarray
    rmse: np.ndarray

    def rows(self) -> list[dict]:
        """One dict per bin: ``low``, ``high``, ``count``, ``sigma``, ``mae``, ``rmse``,
        ``mae_per_sigma`` (metres; None for an empty bin)."""

        def num(x: float) -> float | None:
            return None if not np.isfinite(x) else float(x)

        return [
            {
                "low": float(self.edges[k]),
                "high": float(self.edges[k + 1]),
                "count": int(self.count[k]),
                "sigma": num(self.sigma[k]),
                "mae": num(self.mae[k]),
                "rmse": num(self.rmse[k]),
                "mae_per_sigma": num(self.mae[k] / self.sigma[k]) if self.count[k] else None,
            }
            for k in range(self.count.size)
        ]


def calibration_bins(
    pred: np.ndarray, log_var: np.ndarray, gt: np.ndarray, *, edges: np.ndarray
) -> CalibrationBins:
    """Per bin of predicted sigma: the mean absolute and RMS error of ``pred`` against ``gt``.

    Parameters
    ----------
    pred : (...) float array, metres
        Predicted depth (``D_c``).
    log_var : (...) float array, log of square metres
        Its ``U``, same shape.
    gt : (...) float array, metres
        Ground truth, same shape; pixels with ``gt <= 0`` or non-finite are not counted.
    edges : (K + 1,) float array, metres
        Strictly increasing finite bin edges of sigma; pixels whose sigma lies outside
        ``[edges[0], edges[-1])`` are not counted.

    Returns
    -------
    CalibrationBins
    """
    _float_map(pred, "pred")
    _float_map(log_var, "log_var")
    check_array(gt, "gt")
    check_dtype(gt, "gt", "f")
    check_same_shape(pred, log_var, "pred", "log_var")
    check_same_shape(pred, gt, "pred", "gt")
    edges = check_increasing(np.asarray(edges, dtype=np.float64), "edges")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(gt) & (gt > 0)
    sigma = np.exp(0.5 * log_var[valid].astype(np.float64))
    err = pred[valid].astype(np.float64) - gt[valid].astype(np.float64)
    k = np.searchsorted(edges, sigma, side="right") - 1
    inside = (k >= 0) & (k < edges.size - 1)
    k, sigma, err = k[inside], sigma[inside], err[inside]
    n_bins = edges.size - 1
    count = np.bincount(k, minlength=n_bins).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_sigma = np.bincount(k, sigma, minlength=n_bins) / count
        mae = np.bincount(k, np.abs(err), minlength=n_bins) / count
        rmse = np.sqrt(np.bincount(k, err * err, minlength=n_bins) / count)
    return CalibrationBins(edges=edges, count=count, sigma=mean_sigma, mae=mae, rmse=rmse)
