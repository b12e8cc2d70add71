"""Mapping-consistent image enhancement (MCIE) of RNW (arXiv 2108.03830), METHODS.md section 4.

A global, per-channel clipped histogram equalisation: the 256-bin histogram of the
reference (target) frame is clipped at ``clip * pixel count``, the overflow is spread
uniformly over all bins (once, not iteratively as CLAHE does), and

    lut(b) = round((cdf(b) - cdf_min) / (cdf_max - cdf_min) * 255)

with ``cdf_min`` the smallest non-zero value of the cumulative histogram. The same table is
applied to every frame of the sequence (``cv2.LUT``), so brightness stays consistent between
target and source frames and the photometric loss remains valid.

``rounding="rnw"`` reproduces the integer arithmetic of RNW's released implementation instead
(issue 17): the clip limit truncated to an integer, the excess spread as
``round(excess / 256)`` whole pixels per bin, and the table values truncated (not rounded) to
uint8. It differs from the default by at most one level per entry.
"""

from __future__ import annotations

import numpy as np

from ..errors import ParameterError
from ..validate import check_array, check_choice, check_dtype, check_positive, check_shape

__all__ = ["ROUNDINGS", "apply_lut", "mcie_lut"]

#: Table arithmetic: exact with rounding to nearest (default), or RNW's integer version.
ROUNDINGS = ("nearest", "rnw")


def _check_rgb8(image: np.ndarray, name: str) -> np.ndarray:
    """``image`` as (H, W, C) uint8, C = 1 or 3."""
    check_array(image, name)
    check_dtype(image, name, (np.uint8,))
    check_shape(image, "(H, W) | (H, W, 1) | (H, W, 3)", name, nonempty=True)
    return image[:, :, None] if image.ndim == 2 else image


def mcie_lut(
    reference: np.ndarray, *, clip: float = 0.004, bins: int = 256, rounding: str = "nearest"
) -> np.ndarray:
    """Per-channel MCIE lookup table built from one reference frame.

    Parameters
    ----------
    reference : (H, W, 3) or (H, W) uint8
        The target frame.
    clip : float
        Clip limit as a fraction of the pixel count (RNW: 0.004; 0.008 for RobotCar);
        1 or more disables clipping (plain histogram equalisation).
    bins : int
        Must be 256 (8-bit images); kept as a parameter to say so explicitly.
    rounding : {"nearest", "rnw"}
        "nearest": limit ``clip * N`` and excess ``E / 256`` per bin as real numbers, table
        values rounded to nearest (half to even). "rnw": RNW's released implementation's
        integer arithmetic: limit ``int(clip * N)``, ``round(E / 256)`` whole pixels added to
        every bin (half to even, as Python's ``round``), table values truncated, i.e.
        ``floor((cdf - cdf_min) * 255 / (cdf_max - cdf_min))`` computed exactly in integers.

    Returns
    -------
    lut : (256, C) uint8
        ``lut[b, c]`` is the new value of level ``b`` in channel ``c``. A channel whose
        cumulative histogram is flat after clipping (one level only and no clipping) keeps
        the identity mapping.
    """
    if bins != 256:
        raise ParameterError(
            f"MCIE works on 8-bit images with 256 bins, got bins={bins}", param="bins"
        )
    check_positive(clip, "clip")
    check_choice(rounding, "rounding", ROUNDINGS)
    ref = _check_rgb8(reference, "reference")
    n_pix = ref.shape[0] * ref.shape[1]
    lut = np.empty((256, ref.shape[2]), np.uint8)
    for c in range(ref.shape[2]):
        counts = np.bincount(ref[:, :, c].ravel(), minlength=256)
        if rounding == "rnw":
            lut[:, c] = _rnw_table(counts, int(min(clip, 1.0) * n_pix))  # >= 1: no clipping
        else:
            lut[:, c] = _nearest_table(counts, min(clip, 1.0) * n_pix)
    return lut


def _nearest_table(counts: np.ndarray, limit: float) -> np.ndarray:
    hist = counts.astype(np.float64)
    excess = np.maximum(hist - limit, 0.0).sum()
    hist = np.minimum(hist, limit) + excess / 256.0
    cdf = np.cumsum(hist)
    nonzero = cdf[cdf > 0]
    cdf_min, cdf_max = nonzero[0], cdf[-1]
    if cdf_max - cdf_min <= 0:
        return np.arange(256, dtype=np.uint8)
    mapped = (cdf - cdf_min) / (cdf_max - cdf_min) * 255.0
    return np.rint(np.clip(mapped, 0, 255)).astype(np.uint8)


def _rnw_table(counts: np.ndarray, limit: int) -> np.ndarray:
    # Integers throughout: with at most 2^31 pixels, cdf * 255 fits int64 exactly.
    hist = counts.astype(np.int64)
    excess = int(np.maximum(hist - limit, 0).sum())
    hist = np.minimum(hist, limit) + round(excess / 256)
    cdf = np.cumsum(hist)
    nonzero = cdf[cdf > 0]
    if nonzero.size == 0:  # clip limit 0 (fewer than 1 / clip pixels): nothing to map
        return np.arange(256, dtype=np.uint8)
    cdf_min, cdf_max = int(nonzero[0]), int(cdf[-1])
    if cdf_max == cdf_min:
        return np.arange(256, dtype=np.uint8)
    mapped = np.maximum(cdf - cdf_min, 0) * 255 // (cdf_max - cdf_min)
    return mapped.astype(np.uint8)


def apply_lut(image: np.ndarray, lut: np.ndarray) -> np.ndarray:
    """Map ``image`` through a per-channel table with ``cv2.LUT``.

    Parameters
    ----------
    image : (H, W, C) or (H, W) uint8
    lut : (256, C) or (256,) uint8
        From :func:`mcie_lut`; a single-channel table is applied to every channel.

    Returns
    -------
    uint8 array of the shape of ``image``.
    """
    import cv2

    img = _check_rgb8(image, "image")
    lut = np.asarray(lut)
    check_shape(lut, "(256) | (256, C)", "lut")
    check_dtype(lut, "lut", (np.uint8,))
    if lut.ndim == 2 and lut.shape[1] == 1:
        lut = lut[:, 0]
    channels = img.shape[2]
    if lut.ndim == 2:
        check_shape(lut, f"(256, {channels})", "lut")  # one table per channel of the image
    if lut.ndim == 1:
        table = np.ascontiguousarray(lut.reshape(1, 256))
        out = cv2.LUT(np.ascontiguousarray(img), table)
    else:
        # cv2.LUT maps channel c of the image through channel c of a (1, 256, C) table.
        table = np.ascontiguousarray(lut.reshape(1, 256, channels))
        out = cv2.LUT(np.ascontiguousarray(img), table)
    return out.reshape(np.asarray(image).shape)
