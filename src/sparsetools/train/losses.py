"""Depth losses on the valid ground-truth pixels of a batch (METHODS.md section 6).

Every loss takes ``pred`` and ``gt`` of shape (B, 1, H, W) in metres; the pixels used are those
with a finite ``gt > 0`` (the KITTI "no measurement" value is 0). Each valid pixel of the whole
batch is counted exactly once and the loss is their mean. A batch without any valid pixel gives
a zero loss that still depends on ``pred`` (so ``backward`` works and changes nothing).

BerHu (reverse Huber, Laina et al. 2016) with e = pred - gt on valid pixels and
c = 0.2 max|e| (over the valid pixels of the batch, detached from the graph)::

    berhu(e) = |e|                    if |e| <= c
               (e^2 + c^2) / (2 c)    otherwise

When c = 0 every error is 0 and the loss is 0 (no division by zero, finite gradients). The
version copied across many repositories thresholds the signed error and adds the L1 and L2
parts of every pixel (counting each pixel twice); this one does neither.

SILog (Eigen et al. 2014, with the scale of BTS): d = log pred - log gt on valid pixels,
``alpha * sqrt(mean d^2 - lambda (mean d)^2)`` with lambda = 0.85, alpha = 10.
"""

from __future__ import annotations

import torch

from ..errors import ParameterError

__all__ = ["LOSSES", "berhu_loss", "depth_loss", "l1_loss", "mse_loss", "silog_loss", "valid_mask"]

#: Predictions are clamped to this before the logarithm of SILog (metres).
SILOG_MIN_DEPTH = 1e-3


def valid_mask(gt: torch.Tensor) -> torch.Tensor:
    """Bool mask of pixels with a measurement: finite and > 0."""
    return torch.isfinite(gt) & (gt > 0)


def _check(pred: torch.Tensor, gt: torch.Tensor) -> None:
    if pred.shape != gt.shape:
        raise ParameterError(f"prediction {tuple(pred.shape)} and gt {tuple(gt.shape)} differ")


def _empty(pred: torch.Tensor) -> torch.Tensor:
    # Keeps the graph connected: zero loss, zero gradient.
    return pred.sum() * 0.0


def l1_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean |pred - gt| over valid pixels (metres)."""
    _check(pred, gt)
    m = valid_mask(gt)
    if not bool(m.any()):
        return _empty(pred)
    return (pred[m] - gt[m]).abs().mean()


def mse_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean (pred - gt)^2 over valid pixels (square metres)."""
    _check(pred, gt)
    m = valid_mask(gt)
    if not bool(m.any()):
        return _empty(pred)
    e = pred[m] - gt[m]
    return (e * e).mean()


def berhu_loss(pred: torch.Tensor, gt: torch.Tensor, *, ratio: float = 0.2) -> torch.Tensor:
    """Reverse Huber loss with c = ``ratio`` * max|e| over the valid pixels of the batch."""
    _check(pred, gt)
    m = valid_mask(gt)
    if not bool(m.any()):
        return _empty(pred)
    a = (pred[m] - gt[m]).abs()
    c = ratio * a.detach().max()
    # c = 0 means every |e| = 0: the L1 branch applies everywhere; the clamp only keeps the
    # (unused) quadratic branch and its gradient finite.
    c_safe = torch.clamp(c, min=torch.finfo(a.dtype).tiny)
    quadratic = (a * a + c * c) / (2 * c_safe)
    return torch.where(a <= c, a, quadratic).mean()


def silog_loss(
    pred: torch.Tensor, gt: torch.Tensor, *, lam: float = 0.85, alpha: float = 10.0
) -> torch.Tensor:
    """Scale-invariant log loss ``alpha * sqrt(mean d^2 - lam (mean d)^2)``, d = log pred - log gt.

    Predictions are clamped to 1e-3 m before the logarithm; the value under the square root is
    clamped at 0 (it can only be negative by rounding when ``lam`` = 1).
    """
    _check(pred, gt)
    m = valid_mask(gt)
    if not bool(m.any()):
        return _empty(pred)
    d = torch.log(torch.clamp(pred[m], min=SILOG_MIN_DEPTH)) - torch.log(gt[m])
    var = (d * d).mean() - lam * d.mean() ** 2
    # sqrt'(0) is infinite: at var <= 0 the loss is exactly 0 with a zero (not NaN) gradient.
    positive = var > 0
    root = torch.sqrt(torch.where(positive, var, torch.ones_like(var)))
    return alpha * torch.where(positive, root, torch.zeros_like(var))


LOSSES = {"l1": l1_loss, "mse": mse_loss, "berhu": berhu_loss, "silog": silog_loss}


def depth_loss(name: str, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Dispatch to the loss called ``name`` (one of :data:`LOSSES`)."""
    try:
        fn = LOSSES[name]
    except KeyError:
        raise ParameterError(f"unknown loss {name!r}; choose one of {sorted(LOSSES)}") from None
    return fn(pred, gt)
