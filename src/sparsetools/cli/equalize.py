"""``sparsetools equalize``: mapping-consistent image enhancement (MCIE) of a sequence."""

from __future__ import annotations

from pathlib import Path

import click

from ..ops.enhance import ROUNDINGS
from .options import (
    batch_options,
    build,
    deprecated,
    emit_summary,
    output_dir_option,
    positive,
)


@click.command("equalize")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@output_dir_option
@click.option(
    "--clip",
    type=float,
    default=0.004,
    show_default=True,
    callback=positive,
    help="Histogram clip limit as a fraction of the pixel count, in (0, 1] (RobotCar: 0.008; "
    "1: no clipping).",
)
@click.option(
    "--reference-frame",
    metavar="FRAME",
    help="Frame whose histogram makes the table: a path or the name of an input "
    "[default: the first image].",
)
@click.option(
    "--rounding",
    type=click.Choice(ROUNDINGS),
    default="nearest",
    show_default=True,
    help="Table arithmetic: real-valued and rounded to nearest, or rnw: RNW's released "
    "integer version (limit and spread excess truncated to whole pixels, values truncated; "
    "at most one level lower).",
)
@deprecated("--reference", "--reference-frame", command="equalize", dest="reference_frame")
@batch_options
def equalize(
    images,
    out_dir,
    clip,
    reference_frame,
    rounding,
    batch,
    as_json,
):
    """Equalise images with ONE clipped-histogram table per channel (RNW's MCIE).

    The table comes from the reference frame (256 bins, clip limit = CLIP x pixel count,
    overflow spread uniformly) and maps every frame with cv2.LUT, so the same grey level
    becomes the same output level in all frames (photometric losses stay valid). Writes
    OUT/<sequence>/<frame>.png and the table as OUT/mcie_lut.json (reference, clip,
    rounding, table).

    \b
    Examples:
      sparsetools equalize out/night -o out/night_mcie
      sparsetools equalize seq/ -o out/eq --reference-frame 000010 --clip 0.008
      sparsetools equalize out/night -o out/night_rnw --rounding rnw
    """
    from ..io.sources import image_frames
    from ..pipeline import run_job
    from ..pipeline.equalize import EqualizeJob, EqualizeSettings

    settings = build(EqualizeSettings, clip=clip, reference=reference_frame or "",
                     rounding=rounding)  # fmt: skip
    ref_file = reference_frame if reference_frame and Path(reference_frame).is_file() else None
    summary = run_job(EqualizeJob(settings), image_frames(images), out_dir, batch=batch,
                      inputs=[*images, ref_file])  # fmt: skip
    emit_summary(summary, as_json=as_json, title=f"equalised frames written to {out_dir}")
