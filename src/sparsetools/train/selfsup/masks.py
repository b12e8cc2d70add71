"""Masks of the photometric loss: monodepth2's auto-mask and RNW's statistics-based mask (SBM).

Auto-mask (monodepth2): a pixel is used only when warping explains it better than not warping
at all, ``mu = [min_s pe(I_t, I_s->t) < min_s pe(I_t, I_s)]``. Pixels that do not change between
frames -- a stopped ego car, an object moving with it, textureless regions -- fail the test.
Exact ties (both errors 0, e.g. a perfectly static frame warped with the identity) are broken
at random by adding Gaussian noise of standard deviation 1e-5 to the identity errors, as
monodepth2 does: with two sources the minimum of the two noisy identity errors is below 0 with
probability 3/4, so about a quarter of such pixels stay in (the SBM removes them).

SBM (RNW, arXiv 2108.03830): the temporal change ``d_ts(p) = |I_t(p) - I_s(p)|_1`` (here the
mean over the colour channels, i.e. the L1 norm / 3) is compared with a running threshold,
the EWMA (factor beta = 0.98) of a percentile of d_ts over the batch; pixels whose change is
at or below it are masked. The threshold is the state of :class:`StatisticsMask` (it is saved
in checkpoints for an exact resume). The percentile (``sbm_percentile``, default 10) is this
toolkit's choice, not a number from the paper. The final mask is auto-mask x SBM, where the
SBM of a pixel is that of the source frame chosen by the minimum reprojection.
"""

from __future__ import annotations

import math

import torch

from ...errors import ParameterError

__all__ = ["AUTOMASK_NOISE_STD", "StatisticsMask", "auto_mask", "percentile", "temporal_change"]

#: Standard deviation of the tie-breaking noise added to the identity errors (monodepth2).
AUTOMASK_NOISE_STD = 1e-5


def auto_mask(
    reprojection: torch.Tensor,
    identity: torch.Tensor,
    *,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """monodepth2's auto-mask.

    Parameters
    ----------
    reprojection : (B, S, H, W) float
        pe(I_t, I_s->t) for each of the S source frames.
    identity : (B, S, H, W) float
        pe(I_t, I_s) (the unwarped sources).
    generator : torch.Generator, optional
        Source of the tie-breaking noise (CPU); None uses torch's global generator.

    Returns
    -------
    (B, 1, H, W) bool
        True where the best warped source beats the best unwarped one.
    """
    if reprojection.shape != identity.shape or reprojection.ndim != 4:
        raise ParameterError(
            f"reprojection {tuple(reprojection.shape)} and identity {tuple(identity.shape)} "
            "must be (B, S, H, W) of one shape"
        )
    noise = torch.randn(identity.shape, generator=generator, dtype=identity.dtype)
    noisy = identity.detach() + AUTOMASK_NOISE_STD * noise.to(identity.device)
    best_reprojection = reprojection.detach().min(dim=1, keepdim=True).values
    return best_reprojection < noisy.min(dim=1, keepdim=True).values


def temporal_change(target: torch.Tensor, sources: torch.Tensor) -> torch.Tensor:
    """``d_ts = |I_t - I_s|`` per pixel, mean over the colour channels.

    Parameters
    ----------
    target : (B, C, H, W) float
    sources : (B, S, C, H, W) float

    Returns
    -------
    (B, S, H, W) float
    """
    if (
        sources.ndim != 5
        or sources.shape[0] != target.shape[0]
        or sources.shape[2:] != target.shape[1:]
    ):
        raise ParameterError(
            f"sources must be (B, S, C, H, W) matching the target {tuple(target.shape)}, "
            f"got {tuple(sources.shape)}"
        )
    return (sources - target[:, None]).abs().mean(dim=2)


def percentile(values: torch.Tensor, q: float) -> torch.Tensor:
    """The ``q``-th percentile (0-100) of all values, nearest rank (no interpolation).

    The value of rank ``max(1, ceil(q / 100 n))`` in ascending order, the definition of
    ``numpy.percentile(..., method="inverted_cdf")``.
    """
    flat = values.detach().reshape(-1)
    if flat.numel() == 0:
        raise ParameterError("percentile of an empty tensor")
    k = min(flat.numel(), max(1, math.ceil(q / 100 * flat.numel())))
    return torch.kthvalue(flat, k).values


class StatisticsMask:
    """RNW's statistics-based mask with its running threshold.

    Parameters
    ----------
    beta : float
        EWMA factor of the threshold (RNW: 0.98).
    q : float
        Percentile (0-100) of the temporal change tracked by the threshold.
    threshold : float, optional
        Running threshold to start from (a resumed run); None = the first batch's percentile.
    """

    def __init__(self, *, beta: float = 0.98, q: float = 10.0, threshold: float | None = None):
        if not 0 <= beta < 1:
            raise ParameterError(f"beta must be in [0, 1), got {beta}", param="sbm_beta")
        if not 0 <= q <= 100:
            raise ParameterError(f"percentile must be in [0, 100], got {q}", param="sbm_percentile")
        self.beta = float(beta)
        self.q = float(q)
        self.threshold = None if threshold is None else float(threshold)

    def update(self, change: torch.Tensor) -> None:
        """Fold a training batch's percentile of ``change`` (B, S, H, W) into the threshold."""
        stat = float(percentile(change, self.q))
        if self.threshold is None:
            self.threshold = stat
        else:
            self.threshold = self.beta * self.threshold + (1 - self.beta) * stat

    def mask(self, change: torch.Tensor) -> torch.Tensor:
        """(B, S, H, W) bool: True where the change is above the threshold (kept pixels).

        Before the first :meth:`update` every pixel is kept.
        """
        if self.threshold is None:
            return torch.ones_like(change, dtype=torch.bool)
        return change > self.threshold
