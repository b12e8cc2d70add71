"""Torch-free writers shared by training and evaluation: JSON, CSV and the progress bar.

Both writers are atomic (a temporary name, then rename): a crash leaves the old file or the
new one, whole.
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_path

__all__ = ["progress_bar", "write_csv", "write_json"]


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json(path: str | os.PathLike, obj) -> None:
    """``obj`` as indented JSON, atomically (numpy scalars and paths allowed)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, default=_json_default) + "\n")


def _csv_value(v):
    if isinstance(v, float):
        return repr(v)  # round-trips exactly
    return "" if v is None else v


def write_csv(path: str | os.PathLike, rows: list[dict], columns: list[str]) -> None:
    """Rows as CSV with the given columns (floats written exactly, None as empty), atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: _csv_value(r.get(k)) for k in columns})
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())


def progress_bar(total: int, desc: str, enabled: bool, *, unit: str = "batch"):
    """A tqdm bar on stderr (a no-op when not ``enabled``)."""
    from tqdm import tqdm

    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        file=sys.stderr,
        disable=not enabled,
        leave=False,
        dynamic_ncols=True,
    )
