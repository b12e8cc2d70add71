"""``sparsetools underwater``: remove co-moving lighting and backscatter from seafloor images."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
    checked,
    deprecated,
    emit_summary,
    odd,
    output_dir_option,
    positive,
)


def _a_ref(ctx, param, value):
    """``A`` or ``R,G,B`` grey levels -> a tuple of floats > 0."""
    from ..validate import check_positive

    if value is None:
        return None
    try:
        parts = [float(v) for v in value.split(",")]
    except ValueError:
        raise click.BadParameter(f"expected one number or R,G,B, got {value!r}") from None
    if len(parts) not in (1, 3):
        raise click.BadParameter(f"expected one number or three (R,G,B), got {value!r}")
    return checked(lambda v: tuple(check_positive(p, "a_ref") for p in v))(ctx, param, parts)


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
    "--median-window",
    type=int,
    default=31,
    show_default=True,
    callback=odd,
    metavar="N",
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
@deprecated("--window", "--median-window", command="underwater", dest="median_window")
@batch_options
def underwater(
    seafloor_dir,
    water_dir,
    out_dir,
    median_window,
    white_balance,
    eps,
    a_ref,
    batch,
    as_json,
):
    """Compensate deep-sea lighting by pixel-wise medians (no light or water model).

    Per channel I = A F + B: B is the median of the water-only frames, F the median of a
    centred window of N seafloor frames minus B (shifted to stay full at the ends) divided by
    A_ref, and the output is A = (I - B) / F. SEAFLOOR_DIR frames are taken in name order;
    each sub-folder is a sequence of its own. Writes OUT/<sequence>/<frame>.png (albedo in
    grey levels), OUT/mask/<sequence>/<frame>.png (255 = valid), OUT/backscatter.npy and
    OUT/underwater.json. Each worker holds N frames.

    \b
    Examples:
      sparsetools underwater out/scene/underwater/seafloor \\
          --water out/scene/underwater/water -o out/uw --median-window 31
      sparsetools underwater dive/seafloor --water dive/water -o out/uw --white-balance --workers 4
    """
    from ..errors import FormatError, ParameterError
    from ..io.sources import image_frames
    from ..pipeline import run_job
    from ..pipeline.underwater import UnderwaterJob, UnderwaterSettings

    settings = UnderwaterSettings(window=median_window, eps=eps, white_balance=white_balance,
                                  a_ref=a_ref)  # fmt: skip
    try:
        water = image_frames([water_dir], option="--water")
    except (FormatError, ParameterError) as exc:
        raise FormatError(f"no water-only frames: {exc}") from exc
    frames = image_frames([seafloor_dir], option="SEAFLOOR")
    job = UnderwaterJob(settings, water=tuple(f.image for f in water))
    summary = run_job(job, frames, out_dir, batch=batch, inputs=[seafloor_dir, water_dir])
    # The counts every batch command prints count tasks, here segments of frames: the text
    # says which (frames_*, segments_*); --json keeps them too, for scripts that read every
    # command's summary alike.
    emit_summary(summary, as_json=as_json, title=f"compensated frames written to {out_dir}",
                 details=("processed", "skipped_existing", "recomputed", "failed"))  # fmt: skip
