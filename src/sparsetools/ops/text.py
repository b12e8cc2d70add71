"""Text on pictures: white letters with a black outline, drawn once.

OpenCV 5 draws ``FONT_HERSHEY_*`` with a proportional font whose letters widen with the stroke
thickness, so the usual outline trick (the text in black with a thick stroke, then in white with
a thin one) puts two differently spaced copies of the text on the picture, which read as
garbled text. :func:`put_outlined_text` draws the letters once (one thickness) into a mask and
takes the outline from that mask (a dilation), so the outline follows the very letters shown.
"""

from __future__ import annotations

import numpy as np

from ..validate import check_int_range, check_positive, check_shape

__all__ = ["put_outlined_text", "text_size"]

_FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX, without importing cv2 at module import


def text_size(text: str, scale: float, thickness: int) -> tuple[int, int, int]:
    """Width, height above the baseline and depth below it (pixels) of ``text`` as drawn."""
    import cv2

    (w, h), base = cv2.getTextSize(text, _FONT, float(scale), int(thickness))
    return int(w), int(h), int(base)


def put_outlined_text(
    rgb: np.ndarray,
    text: str,
    org: tuple[int, int],
    *,
    scale: float,
    thickness: int = 1,
    outline: int = 1,
    colour: tuple[int, int, int] = (255, 255, 255),
    outline_colour: tuple[int, int, int] = (0, 0, 0),
) -> np.ndarray:
    """Draw ``text`` at ``org`` (left end of its baseline) in ``colour`` with an outline, in place.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        Picture drawn on (modified and returned).
    text : str
        ASCII text (other characters become ``?``).
    org : (x, y) int, pixels
        Left end of the baseline, as ``cv2.putText``.
    scale : float
        Font scale of ``cv2.putText``.
    thickness : int
        Stroke of the letters, pixels (>= 1).
    outline : int
        Width of the outline around the letters, pixels (0: none).
    colour, outline_colour : (3,) int
        RGB (or whatever channel order ``rgb`` has) of the letters and of their outline.

    Returns
    -------
    (H, W, 3) uint8, ``rgb`` itself.
    """
    import cv2

    check_shape(rgb, "(H, W, 3)", "rgb")
    check_positive(scale, "scale")
    check_int_range(thickness, "thickness", low=1)
    check_int_range(outline, "outline", low=0)
    text = text.encode("ascii", "replace").decode("ascii")
    if not text:
        return rgb
    h_img, w_img = rgb.shape[:2]
    w, h, base = text_size(text, scale, thickness)
    pad = outline + thickness + 2
    # The region the letters and their outline can touch, clipped to the picture.
    x0, y0 = int(org[0]) - pad, int(org[1]) - h - pad
    x1, y1 = int(org[0]) + w + pad, int(org[1]) + base + pad
    cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, w_img), min(y1, h_img)
    if cx0 >= cx1 or cy0 >= cy1:
        return rgb
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.putText(mask, text, (int(org[0]) - x0, int(org[1]) - y0), _FONT, float(scale), 255,
                int(thickness), cv2.LINE_AA)  # fmt: skip
    alpha = mask.astype(np.float32) / 255.0
    roi = rgb[cy0:cy1, cx0:cx1].astype(np.float32)
    crop = (slice(cy0 - y0, cy1 - y0), slice(cx0 - x0, cx1 - x0))
    if outline:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * outline + 1, 2 * outline + 1))
        ring = cv2.dilate(mask, kernel).astype(np.float32)[crop][..., None] / 255.0
        roi = roi * (1.0 - ring) + np.asarray(outline_colour, np.float32) * ring
    a = alpha[crop][..., None]
    roi = roi * (1.0 - a) + np.asarray(colour, np.float32) * a
    rgb[cy0:cy1, cx0:cx1] = np.clip(np.rint(roi), 0, 255).astype(np.uint8)
    return rgb
