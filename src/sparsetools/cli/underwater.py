"""``sparsetools underwater``: remove co-moving lighting and backscatter from seafloor images."""

from __future__ import annotations

import math
from pathlib import Path

import click

from .options import batch_options, emit_summary, output_dir_option, positive


def _odd_window(ctx, param, value):
    if value is not None and (value < 1 or value % 2 == 0):
        raise click.BadParameter(f"the median window must be a positive odd number, got {value}")
    return value


def _a_ref(ctx, param, value):
    if value is None:
        return None
    try:
        parts = [float(v) for v in value.split(",")]
    except ValueError:
        raise click.BadParameter(f"expected one number or R,G,B, got {value!r}") from None
    if len(parts) not in (1, 3) or not all(math.isfinite(p) and p > 0 for p in parts):
        raise click.BadParameter(f"expected one positive number or three (R,G,B), got {value!r}")
    return parts


@click.command("underwater")
@click.argument("seafloor_dir", type=click.Path(exists=True, path_type=Path))
@click.option(
    "--water",
    "water_dir",
    required=True,
    type=click.Path(exists=True, path_type=Path),
    help="Folder of water-only frames (no seafloor in view): the backscatter.",
)
@output_dir_option
@click.option(
    "--window",
    type=int,
    default=31,
    show_default=True,
    callback=_odd_window,
    help="Seafloor frames in each temporal median (odd).",
)
@click.option("--white-balance", is_flag=True, help="Gray-world white balance of every output.")
@click.option(
    "--eps",
    type=float,
    default=1e-3,
    show_default=True,
    callback=positive,
    help="Smallest factor F kept; pixels below are masked invalid.",
)
@click.option(
    "--a-ref",
    callback=_a_ref,
    metavar="A|R,G,B",
    help="Reference albedo in grey levels [default: per-channel median of M - B "
    "over the first window].",
)
@batch_options
def underwater(
    seafloor_dir,
    water_dir,
    out_dir,
    window,
    white_balance,
    eps,
    a_ref,
    batch,
    as_json,
):
    """Compensate deep-sea lighting by pixel-wise medians (no light or water model).

    Per channel I = A F + B: B is the median of the water-only frames, F the median of a
    centred WINDOW of seafloor frames minus B (shifted to stay full at the ends) divided by
    A_ref, and the output is A = (I - B) / F. SEAFLOOR_DIR frames are taken in name order;
    each sub-folder is a sequence of its own. Writes OUT/<sequence>/<frame>.png (albedo in
    grey levels), OUT/mask/<sequence>/<frame>.png (255 = valid), OUT/backscatter.npy and
    OUT/underwater.json. Each worker holds WINDOW frames.

    \b
    Examples:
      sparsetools underwater out/scene/underwater/seafloor \\
          --water out/scene/underwater/water -o out/uw --window 31
      sparsetools underwater dive/seafloor --water dive/water -o out/uw --white-balance --workers 4
    """
    from ..pipeline.underwater import run_underwater

    summary = run_underwater(
        seafloor_dir,
        water_dir,
        out_dir,
        window=window,
        eps=eps,
        a_ref=a_ref,
        white_balance=white_balance,
        batch=batch,
    )
    emit_summary(summary, as_json=as_json, title=f"compensated frames written to {out_dir}")
