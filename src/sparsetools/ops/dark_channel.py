"""Dark channel, LDDCV map and its validity mask (DepthDark survey section 5, METHODS.md 11).

After "Dark Channel-Assisted Depth-from-Defocus from a Single Image" (arXiv 2506.06643), for an
RGB image ``I`` with values in [0, 1]:

    DC(p)    = min over c in {R, G, B} of min over the N x N window around p of I_c(q)   N = 15
    LDDCV(i) = [max over q in N3(i) |Y(i) - Y(q)|,  max over q in N3(i) |DC(i) - DC(q)|]
    M(i)     = 1[ |LDDCV(i)| > T ]                                                     T = 0.05

with ``N3(i)`` the 3 x 3 neighbourhood and ``Y`` the image intensity, here the plain mean of
R, G and B (``intensity="luma"`` uses the BT.601 grey of ``cv2.cvtColor`` instead).

Choices the paper leaves open, made here:

- **Borders.** Windows are clipped to the image (pixels outside are ignored). For the minimum
  and the maximum this is the same as any reflecting border, since reflected pixels are pixels
  of the window anyway; a constant border would bias the result, so none is used.
- **The mask.** ``|LDDCV(i)|`` is the Euclidean norm of the two-channel vector, giving one
  mask, as the survey's "the two-channel LDDCV map and its mask" has it (``combine="norm"``).
  ``combine="any"`` marks a pixel when either channel exceeds T, ``combine="separate"`` returns
  one mask per channel.

The window minimum is ``cv2.erode`` with a rectangular kernel (min over RGB first: the two
minima commute), the 3 x 3 variation is ``max(dilate(X) - X, X - erode(X))``, which equals
the maximum absolute difference to the neighbours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..validate import (
    check_all_finite,
    check_array,
    check_choice,
    check_dtype,
    check_non_negative,
    check_odd,
    check_same_shape,
    check_shape,
    check_values,
)

__all__ = [
    "COMBINE_MODES",
    "INTENSITY_MODES",
    "DarkChannelFeatures",
    "dark_channel",
    "dark_channel_features",
    "image_intensity",
    "lddcv",
    "lddcv_mask",
]

INTENSITY_MODES = ("mean", "luma")
COMBINE_MODES = ("norm", "any", "separate")


@dataclass(frozen=True)
class DarkChannelFeatures:
    """The dark-channel cues of one image.

    Attributes
    ----------
    dark : (H, W) float32, [0, 1]
        Dark channel ``DC``.
    lddcv : (H, W, 2) float32, [0, 1]
        Channel 0: intensity variation, channel 1: dark-channel variation.
    mask : (H, W) bool, or (H, W, 2) bool with ``combine="separate"``
        ``|LDDCV| > threshold``.
    window, threshold, intensity, combine
        The settings used.
    """

    dark: np.ndarray
    lddcv: np.ndarray
    mask: np.ndarray
    window: int
    threshold: float
    intensity: str
    combine: str


def _as_unit_rgb(image: np.ndarray) -> np.ndarray:
    """An (H, W, 3) RGB image, uint8 or float in [0, 1], as float32 in [0, 1]."""
    check_array(image, "image")
    check_shape(image, "(H, W, 3)", "image", nonempty=True)
    check_dtype(image, "image", (np.uint8, np.float32, np.float64))
    if image.dtype == np.uint8:
        return image.astype(np.float32) / np.float32(255.0)
    img = image.astype(np.float32)
    check_all_finite(img, "image")
    check_values(img, "image", low=0.0, high=1.0)
    return img


def _bounded(size: int, shape: tuple[int, ...]) -> int:
    """The window's side clipped to the image: a window of 2 max(H, W) - 1 pixels already
    covers the whole image from every pixel, so any larger one gives the same result (and
    ``--patch-size 30001`` on a small image builds no 900 MB kernel)."""
    return min(size, 2 * max(shape[:2]) - 1)


def _window_min(x: np.ndarray, size: int) -> np.ndarray:
    import cv2

    size = _bounded(size, x.shape)
    # erode's default border value is "+infinity" for a minimum: out-of-image pixels are ignored.
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (size, size))
    return cv2.erode(np.ascontiguousarray(x), kernel, borderType=cv2.BORDER_CONSTANT)


def _window_max(x: np.ndarray, size: int) -> np.ndarray:
    import cv2

    size = _bounded(size, x.shape)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (size, size))
    return cv2.dilate(np.ascontiguousarray(x), kernel, borderType=cv2.BORDER_CONSTANT)


def dark_channel(image: np.ndarray, *, window: int = 15) -> np.ndarray:
    """Dark channel: the minimum over R, G, B and over a ``window`` x ``window`` square.

    Parameters
    ----------
    image : (H, W, 3) uint8, or float in [0, 1]
        RGB image (uint8 is divided by 255).
    window : int
        Odd side of the square window, pixels (the paper's N = 15). The window is clipped at
        the image border.

    Returns
    -------
    (H, W) float32, [0, 1]
    """
    window = check_odd(window, "window", low=1)
    img = _as_unit_rgb(image)
    return _window_min(img.min(axis=2), window)


def image_intensity(image: np.ndarray, *, intensity: str = "mean") -> np.ndarray:
    """Image intensity used by LDDCV: mean of R, G, B, or BT.601 luma (``"luma"``).

    Returns
    -------
    (H, W) float32, [0, 1]
    """
    check_choice(intensity, "intensity", INTENSITY_MODES)
    img = _as_unit_rgb(image)
    if intensity == "mean":
        return img.mean(axis=2, dtype=np.float32)
    import cv2

    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def _variation(x: np.ndarray) -> np.ndarray:
    # max_q |x_i - x_q| = max(max_q x_q - x_i, x_i - min_q x_q) over the 3x3 neighbourhood.
    return np.maximum(_window_max(x, 3) - x, x - _window_min(x, 3))


def lddcv(
    image: np.ndarray, *, window: int = 15, intensity: str = "mean", dark: np.ndarray | None = None
) -> np.ndarray:
    """Local Defocus and Dark-Channel Variation map.

    Parameters
    ----------
    image : (H, W, 3) uint8, or float in [0, 1]
    window : int
        Dark-channel window (ignored when ``dark`` is given).
    intensity : {"mean", "luma"}
        See :func:`image_intensity`.
    dark : (H, W) float32, optional
        A dark channel already computed by :func:`dark_channel`.

    Returns
    -------
    (H, W, 2) float32, [0, 1]
        Maximum absolute difference to the 3 x 3 neighbours (border pixels have fewer) of the
        intensity (channel 0) and of the dark channel (channel 1).
    """
    y = image_intensity(image, intensity=intensity)
    dc = dark_channel(image, window=window) if dark is None else np.asarray(dark, np.float32)
    check_same_shape(dc, y, "dark", "image")
    return np.stack([_variation(y), _variation(dc)], axis=2)


def lddcv_mask(
    variation: np.ndarray, *, threshold: float = 0.05, combine: str = "norm"
) -> np.ndarray:
    """Validity mask ``|LDDCV| > threshold``.

    Parameters
    ----------
    variation : (H, W, 2) float
        From :func:`lddcv`.
    threshold : float
        ``T`` in the units of an image in [0, 1] (paper: 0.05).
    combine : {"norm", "any", "separate"}
        "norm": Euclidean norm of the two channels; "any": either channel; "separate": one
        mask per channel.

    Returns
    -------
    (H, W) bool, or (H, W, 2) bool for "separate"
    """
    check_choice(combine, "combine", COMBINE_MODES)
    check_non_negative(threshold, "threshold")
    v = np.asarray(variation)
    check_shape(v, "(H, W, 2)", "variation")
    if combine == "separate":
        return np.abs(v) > threshold
    if combine == "any":
        return (np.abs(v) > threshold).any(axis=2)
    v64 = v.astype(np.float64)
    return np.hypot(v64[..., 0], v64[..., 1]) > threshold


def dark_channel_features(
    image: np.ndarray,
    *,
    window: int = 15,
    threshold: float = 0.05,
    intensity: str = "mean",
    combine: str = "norm",
) -> DarkChannelFeatures:
    """Dark channel, two-channel LDDCV map and mask of one image (the per-frame job).

    Parameters
    ----------
    image : (H, W, 3) uint8, or float in [0, 1]
    window, threshold, intensity, combine
        See :func:`dark_channel`, :func:`lddcv` and :func:`lddcv_mask`.

    Returns
    -------
    DarkChannelFeatures
    """
    dark = dark_channel(image, window=window)
    var = lddcv(image, intensity=intensity, dark=dark)
    mask = lddcv_mask(var, threshold=threshold, combine=combine)
    return DarkChannelFeatures(dark, var, mask, int(window), float(threshold), intensity, combine)
