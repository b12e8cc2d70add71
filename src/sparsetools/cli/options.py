"""Options shared by several commands, and validation callbacks (click.BadParameter)."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import click

__all__ = [
    "batch_options",
    "emit_summary",
    "executor_from",
    "float_pair",
    "image_size_option",
    "int_list",
    "output_dir_option",
    "progress_enabled",
    "size_wxh",
]


def size_wxh(ctx, param, value):
    """Parse ``WxH`` (e.g. 1242x375) into (W, H)."""
    if value is None:
        return None
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WxH such as 1242x375, got {value!r}") from None
    if w <= 0 or h <= 0:
        raise click.BadParameter(f"width and height must be positive, got {value!r}")
    return w, h


def float_pair(sep: str = ","):
    """Callback parsing ``a<sep>b`` into a (low, high) float pair with low <= high."""

    def parse(ctx, param, value):
        if value is None:
            return None
        try:
            a, b = (float(v) for v in value.split(sep))
        except ValueError:
            raise click.BadParameter(f"expected two numbers as A{sep}B, got {value!r}") from None
        if a > b:
            raise click.BadParameter(f"range is inverted ({a} > {b})")
        return a, b

    return parse


def int_list(ctx, param, value):
    """Parse ``5,7,9,11`` (or several values) into a tuple of ints."""
    if value is None or value == ():
        return None
    items = value if isinstance(value, (tuple, list)) else (value,)
    out = []
    try:
        for item in items:
            out.extend(int(v) for v in str(item).replace(",", " ").split())
    except ValueError:
        raise click.BadParameter(f"expected integers, got {value!r}") from None
    return tuple(out)


def output_dir_option(f):
    return click.option(
        "-o",
        "--out",
        "out_dir",
        required=True,
        type=click.Path(path_type=Path),
        help="Output folder (created; existing complete outputs are skipped unless --overwrite).",
    )(f)


def image_size_option(f):
    return click.option(
        "--image-size",
        callback=size_wxh,
        metavar="WxH",
        help="Image size when the calibration does not hold it (e.g. 1242x375).",
    )(f)


def batch_options(f):
    """--workers, --overwrite, --on-error, --executor, --dask-scheduler, --json."""
    decorators = [
        click.option(
            "--workers",
            type=click.IntRange(min=1),
            default=1,
            show_default=True,
            help="Frames processed in parallel (local processes or Dask workers).",
        ),
        click.option(
            "--overwrite", is_flag=True, help="Recompute and replace outputs that already exist."
        ),
        click.option(
            "--on-error",
            type=click.Choice(["stop", "skip"]),
            default="stop",
            show_default=True,
            help="Stop at the first bad frame, or skip it, list it and go on (exit 1).",
        ),
        click.option(
            "--executor",
            type=click.Choice(["local", "dask"]),
            default="local",
            show_default=True,
            help="Run frames in local processes or on a Dask cluster.",
        ),
        click.option(
            "--dask-scheduler",
            metavar="ADDRESS",
            default=None,
            help="Dask scheduler address (default: start a local cluster).",
        ),
        click.option(
            "--json", "as_json", is_flag=True, help="Print the summary as JSON on stdout."
        ),
    ]
    return functools.reduce(lambda acc, d: d(acc), reversed(decorators), f)


def executor_from(params: dict):
    from ..pipeline import make_executor

    return make_executor(
        params.get("executor", "local"),
        workers=params.get("workers", 1),
        scheduler=params.get("dask_scheduler"),
    )


def progress_enabled() -> bool:
    ctx = click.get_current_context(silent=True)
    quiet = bool(ctx and ctx.find_root().obj and ctx.find_root().obj.get("quiet"))
    return (not quiet) and sys.stderr.isatty()


def emit_summary(summary: dict, *, as_json: bool, title: str = "") -> None:
    """Print a run summary on stdout (key: value lines, or JSON); exit 1 if frames failed."""
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
    """Nested dicts become ``parent.child`` rows; underscores read as spaces."""
    rows = []
    for k, v in d.items():
        key = f"{prefix}{str(k).replace('_', ' ')}"
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
