"""Depth colouring for pictures: blue (near) to red (far), sparse points over an image."""

from __future__ import annotations

import numpy as np

from ..validate import (
    check_dtype,
    check_finite,
    check_int_range,
    check_nonempty,
    check_range,
    check_same_shape,
    check_shape,
)

__all__ = ["colorize_depth", "overlay_depth", "side_by_side"]


def colorize_depth(
    depth: np.ndarray, *, max_depth: float = 80.0, min_depth: float = 0.0
) -> np.ndarray:
    """Colour a depth map with the turbo colormap.

    Parameters
    ----------
    depth : (H, W) float, metres; 0 or non-finite = no measurement.
    max_depth, min_depth : float, metres
        Depths map linearly from blue (``min_depth``) to red (``max_depth``), clipped.

    Returns
    -------
    rgb : (H, W, 3) uint8
        Black where there is no measurement.
    """
    import cv2

    d = np.asarray(depth, dtype=np.float32)
    check_shape(d, "(H, W)", "depth")
    check_finite(max_depth, "max_depth")
    check_finite(min_depth, "min_depth")
    valid = np.isfinite(d) & (d > 0)
    t = np.clip((np.where(valid, d, 0) - min_depth) / max(max_depth - min_depth, 1e-6), 0, 1)
    idx = np.round(t * 255).astype(np.uint8)
    bgr = cv2.applyColorMap(idx, cv2.COLORMAP_TURBO)
    rgb = bgr[:, :, ::-1].copy()
    rgb[~valid] = 0
    return rgb


def overlay_depth(
    image: np.ndarray,
    depth: np.ndarray,
    *,
    max_depth: float = 80.0,
    dilate: int = 2,
    dim: float = 0.6,
) -> np.ndarray:
    """Sparse depth coloured 0..``max_depth`` m over a dimmed copy of ``image``.

    Parameters
    ----------
    image : (H, W, 3) uint8 RGB
    depth : (H, W) float, metres, 0 = empty
    dilate : int
        Grow every valid pixel to a (2*dilate+1)^2 square so single points are visible;
        nearer points stay on top.
    dim : float
        Factor applied to the image under the points (0..1).
    """
    import cv2

    image = np.asarray(image)
    depth = np.asarray(depth)
    check_shape(image, "(H, W, 3)", "image")
    check_dtype(image, "image", (np.uint8,))
    check_shape(depth, "(H, W)", "depth")
    check_same_shape(depth, image, "depth", "image", dims=2)
    check_int_range(dilate, "dilate", low=0)
    check_range(dim, "dim", low=0.0, high=1.0)
    d = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    if dilate > 0:
        # Grey erosion of inverted depth keeps the NEAREST point where squares overlap.
        inv = np.where(d > 0, 1.0 / np.maximum(d, 1e-6), 0).astype(np.float32)
        kernel = np.ones((2 * dilate + 1, 2 * dilate + 1), np.uint8)
        inv = cv2.dilate(inv, kernel)
        d = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), 0).astype(np.float32)
    colours = colorize_depth(d, max_depth=max_depth)
    out = (image.astype(np.float32) * dim).astype(np.uint8)
    mask = d > 0
    out[mask] = colours[mask]
    return out


def side_by_side(panels: list[np.ndarray], *, vertical: bool = True, gap: int = 4) -> np.ndarray:
    """Stack (H, W, 3) uint8 panels with a white gap; widths (or heights) are padded to match."""
    check_nonempty(panels, "panels")
    for i, p in enumerate(panels):
        check_shape(p, "(H, W, 3)", f"panels[{i}]")
    check_int_range(gap, "gap", low=0)
    axis = 0 if vertical else 1
    other = 1 - axis
    size = max(p.shape[other] for p in panels)
    out = []
    for i, p in enumerate(panels):
        pad = [(0, 0), (0, 0), (0, 0)]
        pad[other] = (0, size - p.shape[other])
        out.append(np.pad(p, pad, constant_values=255))
        if i < len(panels) - 1:
            shape = [0, 0, 3]
            shape[axis] = gap
            shape[other] = size
            out.append(np.full(shape, 255, np.uint8))
    return np.concatenate(out, axis=axis)
