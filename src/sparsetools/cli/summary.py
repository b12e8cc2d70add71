"""How a command prints its summary: ``key  value`` lines, or JSON with ``--json``.

The text summary has a fixed number of lines whatever the number of frames: one line per
total (a nested group of totals, such as ``removed``, on one line; a list of lines, such as
the report of each split list, one line per item). What grows with the batch
(per-frame tables) or describes the run's inner workings (stage timings) is named in
``details`` and printed with ``--json`` only. ``-q`` changes stderr only, never stdout.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import click

__all__ = ["emit_summary"]


def emit_summary(summary, *, as_json: bool, title: str = "", details: Iterable[str] = ()) -> None:
    """Print a run summary (a RunSummary or a dict) on stdout (key: value lines, or JSON);
    exit 1 if frames failed.

    Parameters
    ----------
    summary : RunSummary or dict
    as_json : bool
        Print everything as JSON (``--json``).
    title : str
        First line of the text summary.
    details : iterable of str
        Entries printed with ``--json`` only: ``name``, or ``group.name`` inside a nested
        group (per-frame tables, stage timings).
    """
    if hasattr(summary, "as_dict"):
        summary = summary.as_dict()
    if as_json:
        click.echo(json.dumps(summary, indent=1, default=_json_default))
    else:
        if title:
            click.echo(title)
        rows = _text_rows(summary, details=details)
        width = max((len(k) for k, _ in rows), default=0)
        for k, v in rows:
            click.echo(f"{k:<{width}}  {v}")
        for fid, err in (summary.get("failures") or {}).items():
            click.echo(f"  failed {fid}: {err}")
    if summary.get("failed"):
        ctx = click.get_current_context()
        click.echo(f"Error: {summary['failed']} frame(s) failed (listed above)", err=True)
        ctx.exit(1)


def _text_rows(summary: dict, *, details: Iterable[str] = ()) -> list[tuple[str, str]]:
    """The ``(name, value)`` lines of a text summary: the summary's own names with spaces for
    underscores, one line per entry (a nested group's entries joined on it: their names are
    data, such as split names, and are kept as they are); ``details`` and ``failures`` left
    out, and empty groups too."""
    hidden: dict[str, set[str]] = {}
    for name in details:
        group, _, inner = name.partition(".")
        hidden.setdefault(group, set()).add(inner)
    rows = []
    for k, v in summary.items():
        drop = hidden.get(k, set())
        if k == "failures" or "" in drop:
            continue
        if isinstance(v, dict):
            v = {kk: vv for kk, vv in v.items() if kk not in drop}
            if not v:
                continue
        if isinstance(v, (list, tuple)) and v and all(isinstance(x, str) for x in v):
            rows.append((str(k).replace("_", " "), v[0]))
            rows.extend(("", x) for x in v[1:])
            continue
        rows.append((str(k).replace("_", " "), _inline(v)))
    return rows


def _inline(v, nested: bool = False) -> str:
    if isinstance(v, dict):
        text = ", ".join(f"{k} {_inline(x, nested=True)}" for k, x in v.items())
        return f"({text})" if nested else text
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
