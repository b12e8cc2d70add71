"""Pictures of a training run: loss and metric curves, and prediction panels.

Drawn with OpenCV (no plotting library): :func:`draw_curves` returns the ``curves.png`` of a
run folder, :func:`prediction_picture` the ``predictions/epoch_NNN.png`` panels. Both return
(H, W, 3) uint8 RGB arrays; writing them is the caller's business.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ParameterError

__all__ = ["draw_curves", "prediction_picture"]


def _nice_ticks(
    lo: float, hi: float, n: int = 5, *, integer: bool = False
) -> tuple[float, float, list[float]]:
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = 0.0, 1.0
    if hi - lo < 1e-12:
        pad = 1.0 if integer else (abs(hi) * 0.1 or 1.0)
        lo, hi = lo - pad, hi + pad
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    steps = (1, 2, 5, 10) if integer else (1, 2, 2.5, 5, 10)
    step = next(m * mag for m in steps if m * mag >= raw)
    if integer:
        step = max(step, 1)
    lo_t = math.floor(lo / step) * step
    hi_t = math.ceil(hi / step) * step
    ticks = [lo_t + i * step for i in range(round((hi_t - lo_t) / step) + 1)]
    return lo_t, hi_t, ticks


def _log_ticks(lo: float, hi: float) -> tuple[float, float, list[float]]:
    """Axis range and ticks (1, 2, 5 x 10^k) of a logarithmic axis covering [lo, hi] > 0."""
    k0, k1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    ticks = [m * 10.0**k for k in range(k0, k1 + 1) for m in (1, 2, 5)]
    y0 = max(t for t in ticks if t <= lo * (1 + 1e-9))
    y1 = min(t for t in ticks if t >= hi * (1 - 1e-9))
    return y0, y1, [t for t in ticks if y0 <= t <= y1]


def _fmt(v: float) -> str:
    return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.2e}"


def _plot_panel(
    series: list[tuple[str, list[float], list[float], tuple[int, int, int]]],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    size: tuple[int, int] = (440, 300),
    log: bool | None = None,
) -> np.ndarray:
    """One line plot; ``log`` = logarithmic y axis (default: when positive values span > 10x)."""
    import cv2

    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 66, 14, 30, 44
    font = cv2.FONT_HERSHEY_SIMPLEX
    xs_all = [x for _, xs, _, _ in series for x in xs]
    ys_all = [y for _, _, ys, _ in series for y in ys if math.isfinite(y)]
    x0, x1, xt = _nice_ticks(min(xs_all, default=0), max(xs_all, default=1), integer=True)
    lo, hi = min(ys_all, default=0.0), max(ys_all, default=1.0)
    if log is None:
        log = lo > 0 and hi / lo > 10
    if log and lo > 0:
        y0, y1, yt = _log_ticks(lo, hi)
        fy = math.log10
        ylabel = f"{ylabel}, log"
    else:
        y0, y1, yt = _nice_ticks(lo, hi)
        fy = float

    def px(x, y):
        u = left + (x - x0) / (x1 - x0) * (w - left - right)
        v = h - bottom - (fy(y) - fy(y0)) / (fy(y1) - fy(y0)) * (h - top - bottom)
        return round(u), round(v)

    grey, black = (225, 225, 225), (0, 0, 0)
    for t in yt:
        _, v = px(x0, t)
        cv2.line(img, (left, v), (w - right, v), grey, 1)
        label = _fmt(t)
        (tw, _), _ = cv2.getTextSize(label, font, 0.38, 1)
        cv2.putText(img, label, (left - 5 - tw, v + 4), font, 0.38, black, 1, cv2.LINE_AA)
    for t in xt:
        u, _ = px(t, y0)
        cv2.line(img, (u, top), (u, h - bottom), grey, 1)
        label = _fmt(t)
        (tw, _), _ = cv2.getTextSize(label, font, 0.38, 1)
        cv2.putText(img, label, (u - tw // 2, h - bottom + 16), font, 0.38, black, 1, cv2.LINE_AA)
    cv2.line(img, (left, top), (left, h - bottom), black, 1)
    cv2.line(img, (left, h - bottom), (w - right, h - bottom), black, 1)
    cv2.putText(img, title, (left, 20), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, (w // 2 - 4 * len(xlabel), h - 8), font, 0.42, black, 1, cv2.LINE_AA)
    # y label written horizontally then rotated
    lab = np.full((18, 8 * len(ylabel) + 8, 3), 255, np.uint8)
    cv2.putText(lab, ylabel, (2, 13), font, 0.42, black, 1, cv2.LINE_AA)
    lab = np.rot90(lab)
    y_start = max(top, (h - lab.shape[0]) // 2)
    if y_start + lab.shape[0] <= h and lab.shape[1] <= left:
        img[y_start : y_start + lab.shape[0], 0 : lab.shape[1]] = np.minimum(
            img[y_start : y_start + lab.shape[0], 0 : lab.shape[1]], lab
        )
    for k, (name, xs, ys, colour) in enumerate(series):
        pts = [px(x, y) for x, y in zip(xs, ys, strict=True) if math.isfinite(y)]
        bgr = colour[::-1]
        if len(pts) > 1:
            cv2.polylines(img, [np.array(pts, np.int32)], False, bgr, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 3, bgr, -1, cv2.LINE_AA)
        ly = top + 14 + 16 * k
        cv2.line(img, (w - right - 110, ly - 4), (w - right - 90, ly - 4), bgr, 2)
        cv2.putText(img, name, (w - right - 86, ly), font, 0.4, black, 1, cv2.LINE_AA)
    return img[:, :, ::-1].copy()


#: Panel title and axis label of the validation metrics a run may select ``best.pt`` by.
METRIC_LABELS = {
    "rmse": ("validation RMSE", "RMSE (m)"),
    "abs_rel": ("validation AbsRel", "AbsRel"),
    "photometric": ("validation photometric error", "pe"),
}


def draw_curves(
    history: list[dict], *, loss_name: str = "loss", metric: str = "rmse"
) -> np.ndarray:
    """Loss (train, validation) and a validation metric per epoch, as (H, W, 3) uint8 RGB.

    Parameters
    ----------
    history : list of dict
        One row per epoch with ``epoch``, ``train_loss``, ``val_loss`` and ``metric``
        (missing or NaN values are left out of the lines).
    loss_name : str
        Name of the loss in the left panel's title.
    metric : str
        Row key of the right panel (``rmse``, ``abs_rel``, ``photometric`` or any other).
    """
    from ..ops.colormap import side_by_side

    def values(key):
        return [float(r[key]) if r.get(key) not in (None, "") else math.nan for r in history]

    ep = [float(r["epoch"]) for r in history]
    loss_panel = _plot_panel(
        [
            ("train", ep, values("train_loss"), (31, 119, 180)),
            ("validation", ep, values("val_loss"), (255, 127, 14)),
        ],
        title=f"{loss_name} loss",
        xlabel="epoch",
        ylabel="loss",
    )
    title, ylabel = METRIC_LABELS.get(metric, (f"validation {metric}", metric))
    metric_panel = _plot_panel(
        [("validation", ep, values(metric), (44, 160, 44))],
        title=title,
        xlabel="epoch",
        ylabel=ylabel,
    )
    return side_by_side([loss_panel, metric_panel], vertical=False, gap=6)


def prediction_picture(
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    *,
    max_depth: float = 80.0,
    min_panel_width: int = 240,
) -> np.ndarray:
    """One row per sample: rgb | sparse over rgb | prediction | gt, depth coloured 0-max m.

    Parameters
    ----------
    rows : list of (rgb (H, W, 3) uint8, sparse (H, W), prediction (H, W), gt (H, W))
    max_depth : float, metres
        Depth of the red end of the colour map (blue = 0 m).
    min_panel_width : int
        Small images are enlarged (nearest neighbour, integer factor) to at least this width.

    Returns
    -------
    (H', W', 3) uint8 RGB, with a header naming the columns.
    """
    import cv2

    from ..ops.colormap import colorize_depth, overlay_depth, side_by_side

    if not rows:
        raise ParameterError("no samples to draw")
    factor = max(1, math.ceil(min_panel_width / rows[0][0].shape[1]))

    def big(img):
        if factor == 1:
            return img
        return cv2.resize(img, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)

    out = []
    for rgb, sparse, pred, gt in rows:
        panels = [
            rgb,
            overlay_depth(rgb, sparse, max_depth=max_depth, dilate=1),
            colorize_depth(pred, max_depth=max_depth),
            colorize_depth(gt, max_depth=max_depth),
        ]
        out.append(side_by_side([big(p) for p in panels], vertical=False, gap=4))
    body = side_by_side(out, vertical=True, gap=4)
    header = np.full((20, body.shape[1], 3), 255, np.uint8)
    panel_w = rows[0][0].shape[1] * factor
    names = ("rgb", "sparse depth", "prediction", f"ground truth (0-{max_depth:g} m)")
    for k, name in enumerate(names):
        cv2.putText(
            header,
            name,
            (k * (panel_w + 4) + 4, 14),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return np.concatenate([header, body], axis=0)
