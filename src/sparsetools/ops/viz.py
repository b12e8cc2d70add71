"""Pictures of depth maps: labelled overlays, side-by-side comparisons and a colour bar.

Built on :mod:`sparsetools.ops.colormap` (turbo, blue = near, red = far); this module only
adds text labels (OpenCV's Hershey font) and the layout. Arrays in, arrays out: reading and
writing files is the caller's job (``sparsetools viz``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import ParameterError
from ..validate import (
    check_dtype,
    check_finite,
    check_int_range,
    check_nonempty,
    check_ordered,
    check_positive,
    check_same_shape,
    check_shape,
)
from .colormap import colorize_depth, overlay_depth, side_by_side
from .text import put_outlined_text

__all__ = ["colorbar", "depth_panels", "label_panel"]


def _font_scale(height: int) -> float:
    return float(np.clip(height / 450.0, 0.35, 1.2))


def label_panel(rgb: np.ndarray, text: str, *, scale: float | None = None) -> np.ndarray:
    """Copy of ``rgb`` with ``text`` written in its top-left corner (white on a dark outline).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    text : str
        ASCII text (OpenCV's Hershey fonts have no other glyphs; others become ``?``).
    scale : float, optional
        Font scale; default grows with the image height.
    """
    import cv2

    check_shape(np.asarray(rgb), "(H, W, 3)", "rgb")
    check_positive(scale, "scale", allow_none=True)
    out = np.ascontiguousarray(rgb, dtype=np.uint8).copy()
    if not text:
        return out
    text = text.encode("ascii", "replace").decode("ascii")
    scale = _font_scale(out.shape[0]) if scale is None else float(scale)
    thick = max(1, round(2 * scale))
    (_, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    org = (max(2, round(6 * scale)), max(th + 2, round(6 * scale) + th))
    # one drawing of the letters, the outline taken from it (ops/text.py says why)
    return put_outlined_text(out, text, org, scale=scale, thickness=thick, outline=1)


def colorbar(
    width: int,
    *,
    max_depth: float = 80.0,
    min_depth: float = 0.0,
    height: int | None = None,
    ticks: int = 5,
) -> np.ndarray:
    """A horizontal colour bar ``min_depth`` .. ``max_depth`` with metre labels.

    Returns
    -------
    (h, width, 3) uint8
        The same colours as :func:`sparsetools.ops.colormap.colorize_depth`; white background
        under the labels.
    """
    import cv2

    width = check_int_range(width, "width", low=16)
    check_finite(min_depth, "min_depth")
    check_finite(max_depth, "max_depth")
    check_ordered(min_depth, max_depth, "min_depth", "max_depth")
    if height is not None:
        check_int_range(height, "height", low=1)
    check_int_range(ticks, "ticks", low=0)
    scale = _font_scale(width // 3)
    bar_h = height or max(10, round(18 * scale))
    text_h = round(30 * scale) + 6
    margin = max(8, round(30 * scale))
    inner = width - 2 * margin
    # Depth ramp over the inner width; tiny offset keeps 0 m coloured (0 = "no data").
    ramp = np.linspace(min_depth, max_depth, inner, dtype=np.float64)
    ramp = np.where(ramp <= 0, 1e-6, ramp)
    row = colorize_depth(ramp[None, :].astype(np.float32), max_depth=max_depth, min_depth=min_depth)
    out = np.full((bar_h + text_h, width, 3), 255, np.uint8)
    out[:bar_h, margin : margin + inner] = row
    thick = max(1, round(scale))
    for i in range(ticks):
        value = min_depth + (max_depth - min_depth) * i / max(ticks - 1, 1)
        x = margin + round((inner - 1) * i / max(ticks - 1, 1))
        label = f"{value:g} m"
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale * 0.8, thick)
        x0 = int(np.clip(x - tw // 2, 0, width - tw))
        cv2.line(out, (x, bar_h), (x, bar_h + 3), (0, 0, 0), 1)
        cv2.putText(
            out,
            label,
            (x0, bar_h + 4 + th),
            cv2.FONT_HERSHEY_SIMPLEX,
            scale * 0.8,
            (0, 0, 0),
            thick,
            cv2.LINE_AA,
        )
    return out


def depth_panels(
    image: np.ndarray | None,
    depths: Sequence[np.ndarray],
    *,
    labels: Sequence[str] | None = None,
    max_depth: float = 80.0,
    dilate: int = 2,
    vertical: bool = True,
    with_colorbar: bool = True,
) -> np.ndarray:
    """Overlay one or more depth maps on the same image, label them and stack the panels.

    Parameters
    ----------
    image : (H, W, 3) uint8 RGB or None
        Background; None draws the points on black.
    depths : sequence of (H, W) float, metres
        0 = empty. Each becomes one panel (``overlay_depth``, nearest point on top).
    labels : sequence of str, optional
        One per depth map, written in the panel's corner.
    max_depth : float, metres
        Red end of the colour scale (blue = 0 m).
    dilate : int
        Each point drawn as a (2 * dilate + 1)^2 square.
    vertical : bool
        Stack panels top to bottom (default) or left to right.
    with_colorbar : bool
        Add a labelled colour bar below.

    Returns
    -------
    (H', W', 3) uint8
    """
    check_nonempty(depths, "depths")
    if labels is not None and len(labels) != len(depths):
        raise ParameterError(f"{len(labels)} label(s) for {len(depths)} depth map(s)")
    check_positive(max_depth, "max_depth")
    check_int_range(dilate, "dilate", low=0)
    first = np.asarray(depths[0])
    check_shape(first, "(H, W)", "depths[0]")
    for i, d in enumerate(depths[1:], start=1):
        check_same_shape(np.asarray(d), first, f"depths[{i}]", "depths[0]")
    shape = first.shape
    if image is None:
        image = np.zeros((*shape, 3), np.uint8)
        dim = 1.0
    else:
        image = np.asarray(image)
        dim = 0.6
        check_shape(image, "(H, W, 3)", "image")
        check_dtype(image, "image", (np.uint8,))
        check_same_shape(image, first, "image", "depths[0]", dims=2)
    panels = []
    for i, d in enumerate(depths):
        panel = overlay_depth(
            image, np.asarray(d, dtype=np.float32), max_depth=max_depth, dilate=int(dilate), dim=dim
        )
        if labels is not None:
            panel = label_panel(panel, labels[i])
        panels.append(panel)
    out = side_by_side(panels, vertical=vertical) if len(panels) > 1 else panels[0]
    if with_colorbar and out.shape[1] >= 64:
        out = side_by_side([out, colorbar(out.shape[1], max_depth=max_depth)], vertical=True)
    return out
