"""How a command prints its summary: ``key  value`` lines, or JSON with ``--json``."""

from __future__ import annotations

import json
from pathlib import Path

import click

__all__ = ["emit_summary"]


def emit_summary(summary, *, as_json: bool, title: str = "") -> None:
    """Print a run summary (a RunSummary or a dict) on stdout (key: value lines, or JSON);
    exit 1 if frames failed."""
    if hasattr(summary, "as_dict"):
        summary = summary.as_dict()
    if as_json:
        click.echo(json.dumps(summary, indent=1, default=_json_default))
    else:
        if title:
            click.echo(title)
        rows = _flatten({k: v for k, v in summary.items() if k != "failures"})
        width = max((len(k) for k, _ in rows), default=0)
        for k, v in rows:
            if isinstance(v, float):
                v = f"{v:.4g}"
            click.echo(f"{k:<{width}}  {v}")
        for fid, err in (summary.get("failures") or {}).items():
            click.echo(f"  failed {fid}: {err}")
    if summary.get("failed"):
        ctx = click.get_current_context()
        click.echo(f"Error: {summary['failed']} frame(s) failed (listed above)", err=True)
        ctx.exit(1)


def _flatten(d: dict, prefix: str = "") -> list[tuple[str, object]]:
    """Nested dicts become ``parent.child`` rows; underscores of the summary's own names read
    as spaces (nested keys are data, frame ids say: kept as they are)."""
    rows = []
    for k, v in d.items():
        key = f"{prefix}{k!s}" if prefix else str(k).replace("_", " ")
        if isinstance(v, dict):
            rows.extend(_flatten(v, key + "."))
        else:
            rows.append((key, v))
    return rows


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
