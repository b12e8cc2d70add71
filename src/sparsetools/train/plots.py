"""Pictures of a training run: loss and metric curves, and prediction panels.

:func:`draw_curves` returns the ``curves.png`` of a run folder (matplotlib, through
:mod:`sparsetools.io.plots`; :func:`curve_panels` holds its numbers), :func:`prediction_picture`
the ``predictions/epoch_NNN.png`` panels (OpenCV). Both return (H, W, 3) uint8 RGB arrays;
writing them is the caller's business. :func:`eval_panels` are the plots of ``eval --plot``.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from ..errors import ParameterError
from ..io.plots import Panel, Series, render_panels

__all__ = [
    "CURVES_PANEL",
    "EVAL_HISTOGRAMS",
    "curve_panels",
    "draw_curves",
    "eval_panels",
    "eval_plot_path",
    "prediction_picture",
]

#: Per-image metrics whose histograms ``eval --plot`` draws (name, axis label).
EVAL_HISTOGRAMS = (("rmse", "RMSE per image (m)"), ("abs_rel", "AbsRel per image"))

#: Size of each of the two panels of ``curves.png`` (width, height), pixels.
CURVES_PANEL = (440, 300)


#: Panel title and axis label of the validation metrics a run may select ``best.pt`` by.
METRIC_LABELS = {
    "rmse": ("validation RMSE", "RMSE (m)"),
    "abs_rel": ("validation AbsRel", "AbsRel"),
    "photometric": ("validation photometric error", "pe"),
}


def curve_panels(
    history: list[dict], *, loss_name: str = "loss", metric: str = "rmse"
) -> list[Panel]:
    """The two panels of ``curves.png``: loss (train, validation) and a validation metric per
    epoch, the values of the metrics rows (``metrics.csv``) as they are.

    Parameters
    ----------
    history : list of dict
        One row per epoch with ``epoch``, ``train_loss``, ``val_loss`` and ``metric``
        (missing values become NaN and are left out of the lines).
    loss_name : str
        Name of the loss in the left panel's title.
    metric : str
        Row key of the right panel (``rmse``, ``abs_rel``, ``photometric`` or any other).
    """

    def values(key):
        return [float(r[key]) if r.get(key) not in (None, "") else math.nan for r in history]

    ep = [float(r["epoch"]) for r in history]
    title, ylabel = METRIC_LABELS.get(metric, (f"validation {metric}", metric))
    return [
        Panel(
            f"{loss_name} loss",
            "epoch",
            "loss",
            (
                Series("train", ep, values("train_loss")),
                Series("validation", ep, values("val_loss")),
            ),
        ),
        Panel(title, "epoch", ylabel, (Series("validation", ep, values(metric)),)),
    ]


def draw_curves(
    history: list[dict], *, loss_name: str = "loss", metric: str = "rmse"
) -> np.ndarray:
    """``curves.png`` of a run: :func:`curve_panels` drawn with matplotlib, as (300, 880, 3)
    uint8 RGB (a logarithmic y axis where positive values span more than 10x)."""
    return render_panels(curve_panels(history, loss_name=loss_name, metric=metric),
                         columns=2, panel_size=CURVES_PANEL)  # fmt: skip


def _none_nan(values) -> list[float]:
    return [math.nan if v is None else float(v) for v in values]


def eval_panels(result: dict) -> list[Panel]:
    """The panels of ``eval --plot``: MAE and RMSE by ground-truth depth bin, and histograms
    of per-image metrics (:data:`EVAL_HISTOGRAMS`), from the result as written to the JSON.

    Parameters
    ----------
    result : dict
        ``EvalResult.to_dict()``: ``depth_bins`` (``edges_m``, ``mae``, ``rmse``, ``pixels``)
        and ``per_image`` rows.
    """
    bins = result.get("depth_bins")
    if not bins:
        raise ParameterError("no errors by depth bin in this result (evaluated without --plot)")
    edges = bins["edges_m"]
    centres = list(range(len(edges) - 1))  # one slot per bin, the bins named below
    labels = [f"{a:g}-{b:g}" for a, b in itertools.pairwise(edges)]
    panels = [
        Panel(
            "error by ground-truth depth (all pixels)",
            "ground-truth depth (m)",
            "error (m)",
            (Series("MAE", centres, _none_nan(bins["mae"])),
             Series("RMSE", centres, _none_nan(bins["rmse"]))),
            kind="bar",
            xticklabels=tuple(labels),
        )
    ]  # fmt: skip
    rows = [r for r in result.get("per_image", []) if r.get("n_pixels", 0) > 0]
    for name, label in EVAL_HISTOGRAMS:
        values = [float(r[name]) for r in rows]
        panels.append(
            Panel(
                f"{label.split(' per')[0]} of {len(values)} images",
                label,
                "images",
                (Series("", range(len(values)), values),),
                kind="hist",
            )
        )
    return panels


def eval_plot_path(json_path) -> Path:
    """``eval --plot``'s PNG: beside the results, ``<results stem>.png``."""
    return Path(json_path).with_suffix(".png")


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
