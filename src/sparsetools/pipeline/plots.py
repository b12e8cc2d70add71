"""Plots of batch commands' reports: the numbers a command reports, as panels of
:mod:`sparsetools.io.plots` (drawn only there, with matplotlib).

- :func:`ring_report_panels`: ``beams --report --plot`` (points and median elevations per ring,
  one line per cloud), written as ``OUT/ring_report.png``;
- :func:`removal_panels`: ``accumulate --plot`` (points removed per frame by reason), written as
  ``OUT/removals.png``.

Each takes what the command prints with ``--json`` (the report records, the summary dict), so a
plot never disagrees with the text.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from ..io.plots import Panel, Series

__all__ = [
    "REMOVALS_PLOT",
    "REMOVAL_REASONS",
    "RING_REPORT_PLOT",
    "removal_panels",
    "ring_report_panels",
    "write_command_plot",
]

#: File name of ``beams --report --plot`` in its ``-o`` folder.
RING_REPORT_PLOT = "ring_report.png"
#: File name of ``accumulate --plot`` in its ``-o`` folder.
REMOVALS_PLOT = "removals.png"
#: The per-frame removal reasons of accumulate's summary (``removed_per_frame``), plotted.
REMOVAL_REASONS = ("occluded", "inconsistent", "masked")
#: Above this many frames the removals are lines (bars would be thinner than a pixel).
MAX_BAR_FRAMES = 100
#: Clouds named in the legend of the ring report (the others are drawn unnamed).
MAX_LEGEND = 8


def _nan(v) -> float:
    return math.nan if v is None else float(v)


def ring_report_panels(reports: Sequence[Mapping]) -> list[Panel]:
    """Panels of ``beams --report``: points, far points, median elevation (all points) and
    median elevation of the far points per ring, one line per cloud (2 x 2).

    Parameters
    ----------
    reports : sequence of dict
        ``RingReport.to_dict()`` of each cloud (what ``beams --report --json`` prints): ``cloud``
        and ``table``, rows with ``ring``, ``points``, ``elevation_deg``, ``far_elevation_deg``
        (None: no far point) and ``far_points``; and ``far_range_m``.
    """
    pts, far_pts, el, far = [], [], [], []
    for k, r in enumerate(reports):
        name = Path(r["cloud"]).name if k < MAX_LEGEND else ""
        rows = r["table"]
        ring = [row["ring"] for row in rows]
        pts.append(Series(name, ring, [row["points"] for row in rows]))
        far_pts.append(Series(name, ring, [row["far_points"] for row in rows]))
        el.append(Series(name, ring, [row["elevation_deg"] for row in rows]))
        far.append(Series(name, ring, [_nan(row["far_elevation_deg"]) for row in rows]))
    far_range = reports[0]["far_range_m"] if reports else 0.0
    return [
        Panel("points per ring", "ring (0 = highest laser)", "points", tuple(pts), log=False),
        Panel(
            f"points beyond {far_range:g} m per ring",
            "ring (0 = highest laser)",
            "points",
            tuple(far_pts),
            log=False,
        ),
        Panel(
            "median elevation per ring",
            "ring (0 = highest laser)",
            "elevation (deg)",
            tuple(el),
            log=False,
        ),
        Panel(
            f"median elevation beyond {far_range:g} m",
            "ring (0 = highest laser)",
            "elevation (deg)",
            tuple(far),
            log=False,
        ),
    ]


def removal_panels(summary: Mapping) -> list[Panel]:
    """The panel of ``accumulate --plot``: points of the other scans removed per frame, by reason
    (``removed_per_frame`` of the summary), stacked bars (lines above
    :data:`MAX_BAR_FRAMES` frames), frames in the summary's order.

    Parameters
    ----------
    summary : dict
        accumulate's summary (what ``--json`` prints).
    """
    per_frame = summary.get("removed_per_frame") or {}
    ids = list(per_frame)
    x = list(range(len(ids)))
    series = tuple(
        Series(reason, x, [per_frame[f].get(reason, 0) for f in ids]) for reason in REMOVAL_REASONS
    )
    total = summary.get("removed") or {}
    title = "points removed per frame: " + ", ".join(
        f"{reason} {int(total.get(reason, 0))}" for reason in REMOVAL_REASONS
    )
    sequences = {f.rpartition("/")[0] for f in ids}
    xlabel, names = "frame", ids
    if len(sequences) == 1 and "" not in sequences:  # one sequence: named once, in the label
        xlabel = f"frame of {sequences.pop()}"
        names = [f.rpartition("/")[2] for f in ids]
    if len(ids) <= MAX_BAR_FRAMES:
        return [Panel(title, xlabel, "points removed", series, kind="stacked-bar",
                      xticklabels=tuple(names) if len(ids) <= 30 else ())]  # fmt: skip
    return [Panel(title, f"{xlabel} (in order)", "points removed", series, log=False)]


def write_command_plot(
    path: str | os.PathLike,
    panels: Sequence[Panel],
    *,
    command: str,
    overwrite: bool,
    columns: int = 2,
    panel_size: tuple[int, int] = (440, 320),
) -> Path:
    """Write a command's plot as ``path`` (PNG, atomically) with its record.

    The file is the command's own: an existing file it did not write is refused (one line
    naming ``--overwrite``); its own earlier plot is replaced.
    """
    from ..io.plots import write_plot
    from .output_file import OutputFile

    out = OutputFile(path, command, {}, [], overwrite=overwrite, noun="a plot")
    out.up_to_date()  # raises for a file the command did not write
    write_plot(path, panels, columns=columns, panel_size=panel_size)
    out.record()
    return Path(path)
