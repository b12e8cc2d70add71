"""Plots as an output format: panels of line, bar and histogram series drawn with matplotlib.

A command that plots its report first turns the report into :class:`Panel` records (the numbers
it reports, never recomputed), then :func:`render_panels` draws them into an RGB array or
:func:`write_plot` into a PNG (atomically). matplotlib is optional (the ``viz`` extra): it is
imported here only, inside the functions, with the Agg canvas (no display, no pyplot state);
:func:`require_matplotlib` turns its absence into one line naming the extra.
"""

from __future__ import annotations

import importlib
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import DependencyError, ParameterError

__all__ = [
    "INSTALL_HINT",
    "Panel",
    "Series",
    "render_panels",
    "require_matplotlib",
    "write_plot",
]

#: How to get matplotlib (the extra of pyproject.toml).
INSTALL_HINT = "pip install 'sparsetools[viz]'"

#: Series kinds :func:`render_panels` draws.
KINDS = ("line", "bar", "stacked-bar", "hist")

#: Colours of the series of a panel, in order (matplotlib's tab10).
COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2")


def require_matplotlib(what: str) -> None:
    """Import matplotlib, or raise :class:`DependencyError` saying ``what`` needs it.

    Parameters
    ----------
    what : str
        The command or option that plots, e.g. ``"beams --report --plot"``.

    Raises
    ------
    DependencyError
        matplotlib is not installed (``beams --report --plot needs matplotlib: pip install
        'sparsetools[viz]'``), or cannot be imported (its message added).
    """
    try:
        importlib.import_module("matplotlib")
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] != "matplotlib":
            raise DependencyError(
                f"{what} needs matplotlib, which cannot be imported (no module {exc.name!r}): "
                f"{INSTALL_HINT}"
            ) from exc
        raise DependencyError(f"{what} needs matplotlib: {INSTALL_HINT}") from exc
    except (ImportError, OSError) as exc:
        detail = " ".join(str(exc).split())[:200]
        raise DependencyError(
            f"{what} needs matplotlib, which cannot be imported ({detail}): {INSTALL_HINT}"
        ) from exc


@dataclass(frozen=True)
class Series:
    """One named series of a panel.

    Attributes
    ----------
    name : str
        Legend entry ("" for none).
    x : (N,) float
        Positions (line, bar) or, for ``hist``, ignored (the values are ``y``).
    y : (N,) float
        Values; NaN values are left out of a line.
    """

    name: str
    x: tuple[float, ...]
    y: tuple[float, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "x", tuple(float(v) for v in self.x))
        object.__setattr__(self, "y", tuple(float(v) for v in self.y))


@dataclass(frozen=True)
class Panel:
    """One plot: a title, axis labels and its series.

    Attributes
    ----------
    title, xlabel, ylabel : str
    series : tuple of Series
    kind : {'line', 'bar', 'stacked-bar', 'hist'}
        ``bar``: series side by side at each x; ``stacked-bar``: stacked; ``hist``: the ``y``
        values of each series binned (``bins`` bins).
    log : bool or None
        Logarithmic y axis; None: when the positive values span more than 10x (lines only).
    bins : int
        Histogram bins.
    xticklabels : tuple of str
        Labels of the x positions of bars (empty: numbers).
    """

    title: str
    xlabel: str
    ylabel: str
    series: tuple[Series, ...]
    kind: str = "line"
    log: bool | None = None
    bins: int = 20
    xticklabels: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ParameterError(f"unknown panel kind {self.kind!r}; choose one of {KINDS}")
        object.__setattr__(self, "series", tuple(self.series))
        object.__setattr__(self, "xticklabels", tuple(self.xticklabels))


def _log_axis(panel: Panel) -> bool:
    if panel.log is not None:
        return panel.log
    if panel.kind != "line":
        return False
    ys = np.array([v for s in panel.series for v in s.y], np.float64)
    ys = ys[np.isfinite(ys)]
    return bool(ys.size and ys.min() > 0 and ys.max() / ys.min() > 10)


def _draw(ax, panel: Panel) -> None:
    from matplotlib.ticker import MaxNLocator

    kind = panel.kind
    series = panel.series
    if kind == "line":
        for k, s in enumerate(series):
            x, y = np.asarray(s.x), np.asarray(s.y)
            keep = np.isfinite(y)
            ax.plot(x[keep], y[keep], "o-", color=COLOURS[k % len(COLOURS)], label=s.name or None,
                    markersize=4, linewidth=1.8)  # fmt: skip
        if all(float(v).is_integer() for s in series for v in s.x):
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    elif kind in ("bar", "stacked-bar"):
        n = max(len(series), 1)
        xs = [np.asarray(s.x) for s in series]
        step = min((np.min(np.diff(np.unique(x))) for x in xs if np.unique(x).size > 1), default=1)
        bottom = None
        for k, (s, x) in enumerate(zip(series, xs, strict=True)):
            y = np.nan_to_num(np.asarray(s.y))
            colour = COLOURS[k % len(COLOURS)]
            if kind == "bar":
                width = 0.8 * step / n
                ax.bar(x - 0.4 * step + (k + 0.5) * width, y, width=width, color=colour,
                       label=s.name or None)  # fmt: skip
            else:
                ax.bar(x, y, width=0.8 * step, bottom=bottom, color=colour, label=s.name or None)
                bottom = y if bottom is None else bottom + y
        # stacked bars make each top a sticky edge: a margin above the highest is set by hand
        ax.use_sticky_edges = False
        ax.margins(y=0.06)
        ax.set_ylim(bottom=0)
        if panel.xticklabels and xs:
            slanted = sum(len(t) for t in panel.xticklabels) > 60
            ax.set_xticks(xs[0], panel.xticklabels, rotation=30 if slanted else 0,
                          ha="right" if slanted else "center", fontsize=8)  # fmt: skip
    else:  # hist
        values = [np.asarray(s.y)[np.isfinite(s.y)] for s in series]
        if any(v.size for v in values):
            ax.hist([v for v in values], bins=panel.bins, label=[s.name for s in series],
                    color=list(COLOURS[: len(series)]))  # fmt: skip
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.xaxis.set_major_locator(MaxNLocator(5))
    if _log_axis(panel):
        from matplotlib.ticker import FormatStrFormatter, LogLocator

        ax.set_yscale("log")
        # plain numbers (0.5, 1, 2, 5, 10), not mathtext powers (2 x 10^0); minor ticks at
        # 2 and 5 only, so their labels never crowd
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_locator(LogLocator(base=10.0, subs=(2.0, 5.0)))
        ax.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
    ax.set_title(panel.title, fontsize=11)
    ax.set_xlabel(panel.xlabel)
    ax.set_ylabel(panel.ylabel)
    ax.grid(True, alpha=0.3)
    if any(s.name for s in series):
        ax.legend(fontsize=8)


def render_panels(
    panels: Sequence[Panel],
    *,
    columns: int = 2,
    panel_size: tuple[int, int] = (440, 300),
    title: str = "",
) -> np.ndarray:
    """Draw panels on a grid: ``columns`` per row, each ``panel_size`` pixels.

    Parameters
    ----------
    panels : sequence of Panel
    columns : int
        Panels per row (fewer when there are fewer panels).
    panel_size : (width, height) int, pixels
    title : str
        Title over the whole picture ("" for none).

    Returns
    -------
    (rows * height, columns * width, 3) uint8 RGB: the size is exactly the grid's.
    """
    require_matplotlib("plotting")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not panels:
        raise ParameterError("nothing to plot")
    columns = max(1, min(int(columns), len(panels)))
    rows = math.ceil(len(panels) / columns)
    w, h = (int(v) for v in panel_size)
    dpi = 100
    fig = Figure(figsize=(columns * w / dpi, rows * h / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(rows, columns, squeeze=False)
    for k, ax in enumerate(axes.ravel()):
        if k < len(panels):
            _draw(ax, panels[k])
        else:
            ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=12)
    fig.tight_layout()
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    out = np.ascontiguousarray(rgba[:, :, :3])
    fig.clear()
    return out


def write_plot(
    path: str | os.PathLike,
    panels: Sequence[Panel],
    *,
    columns: int = 2,
    panel_size: tuple[int, int] = (440, 300),
    title: str = "",
    overwrite: bool = True,
) -> np.ndarray:
    """:func:`render_panels` written as a PNG (atomically); returns the picture."""
    from .image import write_image

    rgb = render_panels(panels, columns=columns, panel_size=panel_size, title=title)
    write_image(path, rgb, overwrite=overwrite)
    return rgb
