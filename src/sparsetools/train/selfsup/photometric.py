"""Photometric error of view synthesis (METHODS.md section 8; monodepth2's settings).

``pe(a, b) = alpha / 2 (1 - SSIM(a, b)) + (1 - alpha) |a - b|`` with alpha = 0.85, per pixel
and averaged over the colour channels. SSIM uses 3x3 windows of equal weights on images
padded by reflection (so border pixels have full windows), C1 = 0.01^2 and C2 = 0.03^2 (for
images in [0, 1]):

    SSIM = (2 mu_a mu_b + C1) (2 sigma_ab + C2) / ((mu_a^2 + mu_b^2 + C1) (sigma_a^2 + sigma_b^2 + C2))

with the (biased) window variances and covariance ``sigma_ab = mean(ab) - mu_a mu_b``. The
dissimilarity ``(1 - SSIM) / 2`` is clamped to [0, 1] as monodepth2 does (rounding can push it
a hair outside).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ...errors import ParameterError

__all__ = ["ALPHA", "C1", "C2", "photometric_error", "ssim", "ssim_dissimilarity"]

ALPHA = 0.85
C1 = 0.01**2
C2 = 0.03**2


def _check_pair(a: torch.Tensor, b: torch.Tensor) -> None:
    if a.shape != b.shape or a.ndim != 4:
        raise ParameterError(
            f"images must be two (B, C, H, W) tensors of one shape, got {tuple(a.shape)} "
            f"and {tuple(b.shape)}"
        )
    if a.shape[-1] < 2 or a.shape[-2] < 2:
        raise ParameterError(f"SSIM needs images of at least 2x2 pixels, got {tuple(a.shape)}")


def _window_mean(x: torch.Tensor) -> torch.Tensor:
    return F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="reflect"), 3, stride=1)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel, per-channel SSIM over 3x3 reflection-padded windows.

    Parameters
    ----------
    a, b : (B, C, H, W) float, intensities in [0, 1]

    Returns
    -------
    (B, C, H, W) float, in [-1, 1] (1 = identical windows).
    """
    _check_pair(a, b)
    mu_a, mu_b = _window_mean(a), _window_mean(b)
    var_a = _window_mean(a * a) - mu_a * mu_a
    var_b = _window_mean(b * b) - mu_b * mu_b
    cov = _window_mean(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + C1) * (2 * cov + C2)
    den = (mu_a * mu_a + mu_b * mu_b + C1) * (var_a + var_b + C2)
    return num / den


def ssim_dissimilarity(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(1 - SSIM) / 2`` clamped to [0, 1], per pixel and channel, (B, C, H, W)."""
    return torch.clamp((1 - ssim(a, b)) / 2, 0, 1)


def photometric_error(a: torch.Tensor, b: torch.Tensor, *, alpha: float = ALPHA) -> torch.Tensor:
    """Per-pixel photometric error, averaged over channels.

    Parameters
    ----------
    a, b : (B, C, H, W) float, intensities in [0, 1]
    alpha : float
        Weight of the SSIM term (monodepth2: 0.85).

    Returns
    -------
    (B, 1, H, W) float
        ``alpha (1 - SSIM) / 2 + (1 - alpha) |a - b|``, channel mean.
    """
    if not 0 <= alpha <= 1:
        raise ParameterError(f"alpha must be in [0, 1], got {alpha}", param="alpha")
    _check_pair(a, b)
    l1 = (a - b).abs()
    if alpha == 0:
        return l1.mean(dim=1, keepdim=True)
    return (alpha * ssim_dissimilarity(a, b) + (1 - alpha) * l1).mean(dim=1, keepdim=True)
