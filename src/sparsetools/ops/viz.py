"""Pictures of depth maps: labelled overlays, side-by-side comparisons and a colour bar.

Built on :mod:`sparsetools.ops.colormap` (turbo, blue = near, red = far); this module only
adds text labels (OpenCV's Hershey font) and the layout. Arrays in, arrays out: reading and
writing files is the caller's job (``sparsetools viz``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..validate import (
    check_choice,
    check_dtype,
    check_finite,
    check_int_range,
    check_nonempty,
    check_ordered,
    check_positive,
    check_same_length,
    check_same_shape,
    check_shape,
)
from .colormap import colorize_depth, overlay_depth, side_by_side
from .text import put_outlined_text

__all__ = ["colorbar", "contact_sheet", "depth_panels", "fit_picture", "label_panel"]

#: Where :func:`label_panel` writes its text.
CORNERS = ("top-left", "bottom-left")


def _font_scale(height: int) -> float:
    return float(np.clip(height / 450.0, 0.35, 1.2))


def label_panel(
    rgb: np.ndarray, text: str, *, scale: float | None = None, corner: str = "top-left"
) -> np.ndarray:
    """Copy of ``rgb`` with ``text`` written once in a corner (white on a dark outline).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    text : str
        ASCII text (OpenCV's Hershey fonts have no other glyphs; others become ``?``).
    scale : float, optional
        Font scale; default grows with the image height. A text wider than the picture is
        written smaller (down to 0.3).
    corner : {"top-left", "bottom-left"}

    Notes
    -----
    The letters are drawn once, white, with a black outline taken from those same letters
    (:func:`sparsetools.ops.text.put_outlined_text`), so the label reads on any background.
    """
    import cv2

    check_shape(np.asarray(rgb), "(H, W, 3)", "rgb")
    check_positive(scale, "scale", allow_none=True)
    check_choice(corner, "corner", CORNERS)
    out = np.ascontiguousarray(rgb, dtype=np.uint8).copy()
    if not text:
        return out
    text = text.encode("ascii", "replace").decode("ascii")
    scale = _font_scale(out.shape[0]) if scale is None else float(scale)
    thick = max(1, round(2 * scale))
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    room = out.shape[1] - 2 * max(2, round(6 * scale))
    if tw > room > 0:  # a long label in a narrow picture: a smaller font
        scale = max(0.3, scale * room / tw)
        thick = max(1, round(2 * scale))
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    org = (max(2, round(6 * scale)), max(th + 2, round(6 * scale) + th))
    if corner == "bottom-left":
        org = (org[0], max(th + 2, out.shape[0] - max(2, round(6 * scale)) - base))
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
    panel_width: int | None = None,
    caption: str | None = None,
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
    panel_width : int, optional
        Shrink (or grow) each overlaid panel to this width, pixels, keeping its aspect ratio,
        before the labels are written: labels stay legible in small pictures (contact-sheet
        tiles). Points are drawn (``dilate``) at full resolution first.
    caption : str, optional
        Text written once in the bottom-left corner of the panels (a frame key).

    Returns
    -------
    (H', W', 3) uint8
    """
    check_nonempty(depths, "depths")
    if labels is not None:
        check_same_length(labels, depths, "labels", "depth maps")
    check_positive(max_depth, "max_depth")
    check_int_range(dilate, "dilate", low=0)
    if panel_width is not None:
        panel_width = check_int_range(panel_width, "panel_width", low=8)
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
        if panel_width is not None and panel_width != panel.shape[1]:
            panel = _resize(
                panel, panel_width, max(1, round(panel.shape[0] * panel_width / panel.shape[1]))
            )
        if labels is not None:
            # small panels (a sheet's tile): the labels as large as the tile's caption
            scale = None
            if panel_width is not None:
                scale = _font_scale(panel.shape[0] * (len(depths) if vertical else 1))
            panel = label_panel(panel, labels[i], scale=scale)
        panels.append(panel)
    out = side_by_side(panels, vertical=vertical) if len(panels) > 1 else panels[0]
    if caption:
        out = label_panel(out, caption, corner="bottom-left")
    if with_colorbar and out.shape[1] >= 64:
        out = side_by_side([out, colorbar(out.shape[1], max_depth=max_depth)], vertical=True)
    return out


def _resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    if (rgb.shape[1], rgb.shape[0]) == (width, height):
        return rgb
    shrink = width <= rgb.shape[1] and height <= rgb.shape[0]
    return cv2.resize(
        rgb, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    )


def fit_picture(rgb: np.ndarray, size: tuple[int, int], *, background: int = 255) -> np.ndarray:
    """``rgb`` scaled to fit inside ``size`` (aspect ratio kept) and centred on a plain
    background.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    size : (width, height), pixels
    background : int
        Grey level of the uncovered border (0..255).

    Returns
    -------
    (height, width, 3) uint8
        ``rgb`` itself (a copy) when it already has this size.
    """
    check_shape(np.asarray(rgb), "(H, W, 3)", "rgb", nonempty=True)
    check_dtype(np.asarray(rgb), "rgb", (np.uint8,))
    w = check_int_range(size[0], "width", low=1)
    h = check_int_range(size[1], "height", low=1)
    check_int_range(background, "background", low=0, high=255)
    src = np.asarray(rgb)
    if (src.shape[1], src.shape[0]) == (w, h):
        return src.copy()
    f = min(w / src.shape[1], h / src.shape[0])
    nw = min(w, max(1, round(src.shape[1] * f)))
    nh = min(h, max(1, round(src.shape[0] * f)))
    out = np.full((h, w, 3), background, np.uint8)
    y0, x0 = (h - nh) // 2, (w - nw) // 2
    out[y0 : y0 + nh, x0 : x0 + nw] = _resize(src, nw, nh)
    return out


def contact_sheet(
    tiles: Sequence[np.ndarray],
    labels: Sequence[str] | None = None,
    *,
    grid: tuple[int, int] = (4, 3),
    tile_size: tuple[int, int] | None = None,
    margin: int = 2,
    background: int = 255,
) -> np.ndarray:
    """One page of a contact sheet: ``tiles`` in a ``grid`` of equal cells, row by row, each
    with its label written once (bottom-left corner of the cell).

    Parameters
    ----------
    tiles : sequence of (h, w, 3) uint8
        At most ``cols * rows`` pictures (fewer: the remaining cells stay blank). Each is
        fitted into its cell less ``margin`` on every side (:func:`fit_picture`, aspect
        ratio kept).
    labels : sequence of str, optional
        One per tile (a frame key); ``""`` for none.
    grid : (cols, rows)
        Cells across and down.
    tile_size : (width, height), optional
        Size of one cell, pixels (default: the largest tile plus the margins).
    margin : int, pixels
        Background around each tile inside its cell (separates neighbours).
    background : int
        Grey level of margins and blank cells.

    Returns
    -------
    (rows * height, cols * width, 3) uint8
    """
    check_nonempty(tiles, "tiles")
    cols = check_int_range(grid[0], "grid columns", low=1)
    rows = check_int_range(grid[1], "grid rows", low=1)
    check_int_range(len(tiles), f"tiles of a {cols}x{rows} grid", high=cols * rows)
    if labels is not None:
        check_same_length(labels, tiles, "labels", "tiles")
    margin = check_int_range(margin, "margin", low=0)
    check_int_range(background, "background", low=0, high=255)
    for i, tile in enumerate(tiles):
        check_shape(np.asarray(tile), "(H, W, 3)", f"tiles[{i}]", nonempty=True)
        check_dtype(np.asarray(tile), f"tiles[{i}]", (np.uint8,))
    if tile_size is None:
        tw = max(np.asarray(t).shape[1] for t in tiles) + 2 * margin
        th = max(np.asarray(t).shape[0] for t in tiles) + 2 * margin
    else:
        tw = check_int_range(tile_size[0], "tile width", low=2 * margin + 1)
        th = check_int_range(tile_size[1], "tile height", low=2 * margin + 1)
    page = np.full((rows * th, cols * tw, 3), background, np.uint8)
    inner = (tw - 2 * margin, th - 2 * margin)
    for i, tile in enumerate(tiles):
        cell = fit_picture(np.asarray(tile), inner, background=background)
        if labels is not None and labels[i]:
            cell = label_panel(cell, labels[i], corner="bottom-left")
        r, c = divmod(i, cols)
        y, x = r * th + margin, c * tw + margin
        page[y : y + inner[1], x : x + inner[0]] = cell
    return page
