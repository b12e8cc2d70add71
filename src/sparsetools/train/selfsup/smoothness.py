"""Edge-aware smoothness of disparity (monodepth2; METHODS.md section 8).

``L_s = mean |dx d*| exp(-|dx I|) + mean |dy d*| exp(-|dy I|)`` with ``d* = d / mean(d)``
(mean per image, so the term does not push the disparity towards 0), forward differences
between neighbouring pixels, and ``|dx I|`` the mean over the colour channels of the image
gradient. The training loss weighs it by ``smoothness / 2^scale`` (monodepth2: 1e-3), at each
scale on the disparity of that scale and the image resized to it.
"""

from __future__ import annotations

import torch

from ...errors import ParameterError

__all__ = ["edge_aware_smoothness"]

#: Added to the mean disparity before normalising (keeps an all-zero disparity finite).
_EPS = 1e-7


def edge_aware_smoothness(disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Edge-aware smoothness of mean-normalised disparity.

    Parameters
    ----------
    disparity : (B, 1, H, W) float
    image : (B, C, H, W) float, intensities in [0, 1]

    Returns
    -------
    () float
        Mean over the x differences plus mean over the y differences.
    """
    if disparity.ndim != 4 or disparity.shape[1] != 1:
        raise ParameterError(f"disparity must be (B, 1, H, W), got {tuple(disparity.shape)}")
    if image.shape[0] != disparity.shape[0] or image.shape[-2:] != disparity.shape[-2:]:
        raise ParameterError(
            f"image {tuple(image.shape)} does not match the disparity {tuple(disparity.shape)}"
        )
    if min(disparity.shape[-2:]) < 2:
        raise ParameterError(f"smoothness needs at least 2x2 pixels, got {tuple(disparity.shape)}")
    d = disparity / (disparity.mean(dim=(2, 3), keepdim=True) + _EPS)
    dx = (d[:, :, :, 1:] - d[:, :, :, :-1]).abs()
    dy = (d[:, :, 1:, :] - d[:, :, :-1, :]).abs()
    ix = (image[:, :, :, 1:] - image[:, :, :, :-1]).abs().mean(dim=1, keepdim=True)
    iy = (image[:, :, 1:, :] - image[:, :, :-1, :]).abs().mean(dim=1, keepdim=True)
    return (dx * torch.exp(-ix)).mean() + (dy * torch.exp(-iy)).mean()
