"""Depth-like files of a dataset or a folder: depth maps (KITTI uint16 PNG, metres x 256, or
``.npy`` float metres) and confidence maps (PNG 0-255 or 16-bit, or ``.npy`` in [0, 1]), decoded
from bytes or read from a path, their values checked."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .image import decode_depth_png, read_depth_png

__all__ = [
    "decode_confidence_bytes",
    "decode_depth_bytes",
    "read_confidence_file",
    "read_depth_file",
]


def _load_npy(data: bytes, source: str) -> np.ndarray:
    from .npy import load_npy

    arr = load_npy(data, source=source, invalid="not a readable .npy array")
    if not isinstance(arr, np.ndarray):
        raise FormatError(f"{source}: expected one array in the .npy file")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim != 2:
        raise FormatError(f"{source}: expected an (H, W) array, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise FormatError(f"{source}: expected a numeric array, got {arr.dtype}")
    return arr


def decode_depth_bytes(data: bytes, suffix: str, *, source: str = "depth") -> np.ndarray:
    """Decode a depth file's bytes: KITTI uint16 PNG or ``.npy`` (metres) by ``suffix``.

    Returns (H, W) float32 metres. Values of a ``.npy`` that are not valid depths
    (non-finite or <= 0) become 0 (no measurement).
    """
    suffix = suffix.lower()
    if suffix == ".png":
        return decode_depth_png(data, source=source)
    if suffix == ".npy":
        with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: Inf, invalid
            arr = _load_npy(data, source).astype(np.float32, copy=False)
        with np.errstate(invalid="ignore"):
            bad = ~(np.isfinite(arr) & (arr > 0))
        if bad.any():
            arr = np.where(bad, np.float32(0), arr)
        return arr
    raise FormatError(f"{source}: unknown depth format '{suffix}' (expected .png or .npy)")


def read_depth_file(path: str | os.PathLike) -> np.ndarray:
    """Read a depth map: KITTI uint16 PNG (value / 256) or ``.npy`` float metres.

    Returns
    -------
    (H, W) float32
        Metres, 0 = no measurement.
    """
    path = Path(path)
    if path.suffix.lower() == ".png":
        return read_depth_png(path)
    from .npy import read_map_bytes

    data = read_map_bytes(path, what="depth map")
    return decode_depth_bytes(data, path.suffix, source=str(path))


def decode_confidence_bytes(data: bytes, suffix: str, *, source: str = "confidence") -> np.ndarray:
    """Decode a confidence map: PNG (uint16 / 65535 or uint8 / 255) or ``.npy`` as float32."""
    suffix = suffix.lower()
    if suffix == ".npy":
        with np.errstate(over="ignore", invalid="ignore"):
            return _load_npy(data, source).astype(np.float32, copy=False)
    if suffix == ".png":
        from .image import decode_image_bytes

        img = decode_image_bytes(data, source=source, what="confidence PNG")
        if img.ndim != 2:
            raise FormatError(f"{source}: a confidence PNG must be single-channel")
        scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype)
        if scale is None:
            raise FormatError(f"{source}: {img.dtype} PNG, expected uint8 or uint16 confidence")
        return img.astype(np.float32) / np.float32(scale)
    raise FormatError(f"{source}: unknown confidence format '{suffix}' (expected .png or .npy)")


def read_confidence_file(path: str | os.PathLike) -> np.ndarray:
    """Read a confidence map (see :func:`decode_confidence_bytes`): (H, W) float32 in [0, 1]."""
    from .npy import read_map_bytes

    path = Path(path)
    data = read_map_bytes(path, what="confidence map")
    return decode_confidence_bytes(data, path.suffix, source=str(path))
