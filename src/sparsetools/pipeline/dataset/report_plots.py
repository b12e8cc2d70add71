"""The plots of ``dataset report``: histograms per split, drawn with matplotlib into PNG bytes.

matplotlib is an optional dependency (the ``viz`` extra: ``pip install 'sparsetools[viz]'``)
imported only here and only when a plot is drawn. The figures are made with its object API
(``Figure`` + the Agg canvas), never ``pyplot``: no global backend is switched, no window
opens, and nothing is shared between two reports made in one process.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ...io.plots import COLOURS, INSTALL_HINT, require_matplotlib

__all__ = ["INSTALL_HINT", "HistogramPanel", "histogram_png", "require_matplotlib"]

#: One colour per split, the same in every plot of a report (the colours of io.plots).
SPLIT_COLOURS = COLOURS


@dataclass(frozen=True)
class HistogramPanel:
    """One panel of a histogram figure: a distribution per split.

    Attributes
    ----------
    title, xlabel : str
    series : mapping of split name -> (N,) float array
        The values of each split (an empty array draws nothing for that split, but keeps its
        colour and its legend entry, marked "none").
    """

    title: str
    xlabel: str
    series: Mapping[str, np.ndarray]


#: Values above this percentile (of all splits together) are counted in the last bin, so that a
#: few far outliers do not squeeze every curve into the first bins.
CLIP_PERCENTILE = 99.5


def _bins(panel: HistogramPanel, n_bins: int) -> tuple[np.ndarray, float]:
    """Bin edges over the values of every split, and the share of values above the last edge.

    ``n_bins`` bins, fewer for few values (about 2 sqrt(N) for the largest split, at least 8)
    so that a handful of frames is not a row of spikes; the range ends at the
    :data:`CLIP_PERCENTILE` percentile of all values when the largest value is past 1.5 times
    that span (a long tail), else at the largest value.
    """
    values = [np.asarray(v, dtype=np.float64) for v in panel.series.values()]
    values = [v[np.isfinite(v)] for v in values]
    values = [v for v in values if v.size]
    if not values:
        return np.linspace(0.0, 1.0, n_bins + 1), 0.0
    largest = max(v.size for v in values)
    n_bins = int(min(n_bins, max(8, np.ceil(2 * np.sqrt(largest)))))
    every = np.concatenate(values)
    lo = float(every.min())
    hi = float(np.percentile(every, CLIP_PERCENTILE))
    top = float(every.max())
    if top - lo <= 1.5 * (hi - lo):  # no long tail: the whole range
        hi = top
    if hi <= lo:  # one value: a narrow bin around it
        pad = max(abs(lo) * 0.05, 1e-3)
        lo, hi = lo - pad, hi + pad
    return np.linspace(lo, hi, n_bins + 1), float(np.mean(every > hi))


def histogram_png(
    panels: Sequence[HistogramPanel],
    *,
    splits: Sequence[str],
    n_bins: int = 40,
    width_px: int = 1100,
    height_px: int = 330,
    dpi: int = 100,
) -> bytes:
    """Panels side by side, one outlined histogram per split in each, as PNG bytes.

    Each split's counts are shown as the share of its own values (splits of very different
    sizes stay comparable); the legend gives the number of values behind each curve.

    Parameters
    ----------
    panels : sequence of HistogramPanel
    splits : sequence of str
        All split names of the dataset, in order: fixes each split's colour.
    n_bins : int
        Bins per panel, spanning the values of all splits.
    width_px, height_px, dpi : int
        Size of the picture in pixels, and its resolution.

    Returns
    -------
    bytes
        A PNG image of ``width_px`` x ``height_px`` pixels.
    """
    require_matplotlib("dataset report")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_px / dpi, height_px / dpi), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    colours = {name: SPLIT_COLOURS[i % len(SPLIT_COLOURS)] for i, name in enumerate(splits)}
    for ax, panel in zip(axes, panels, strict=True):
        edges, above = _bins(panel, n_bins)
        for name in splits:
            v = np.asarray(panel.series.get(name, np.zeros(0)), dtype=np.float64)
            v = v[np.isfinite(v)]
            label = f"{name} ({v.size:,})" if v.size else f"{name} (none)"
            if not v.size:
                ax.plot([], [], color=colours[name], label=label)
                continue
            counts, _ = np.histogram(np.minimum(v, edges[-1]), bins=edges)
            ax.stairs(100.0 * counts / v.size, edges, color=colours[name], linewidth=1.6,
                      label=label)  # fmt: skip
        ax.set_title(panel.title, fontsize=10)
        clipped = f"; {100 * above:.2g} % above {edges[-1]:.3g} in the last bin" if above else ""
        ax.set_xlabel(panel.xlabel + clipped, fontsize=9)
        ax.set_ylabel("% of the split's values", fontsize=9)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, frameon=False)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()
