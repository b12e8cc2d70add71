"""``sparsetools dark-channel``: dark channel, LDDCV map and validity mask of images."""

from __future__ import annotations

from pathlib import Path

import click

from ..ops.dark_channel import COMBINE_MODES, INTENSITY_MODES
from .options import (
    batch_options,
    deprecated,
    emit_summary,
    non_negative,
    odd,
    output_dir_option,
)


@click.command("dark-channel")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@output_dir_option
@click.option(
    "--patch-size",
    type=int,
    default=15,
    show_default=True,
    callback=odd,
    metavar="N",
    help="Side N of the dark channel's square patch around each pixel, pixels (odd; the "
    "paper: 15).",
)
@click.option(
    "--mask-threshold",
    type=float,
    default=0.05,
    show_default=True,
    callback=non_negative,
    help="Threshold T of the mask |LDDCV| > T, in units of an image in [0, 1].",
)
@click.option(
    "--mask-mode",
    type=click.Choice(COMBINE_MODES),
    default="norm",
    show_default=True,
    help="norm: Euclidean norm of the two LDDCV channels (one mask); any: either channel; "
    "separate: one mask per channel.",
)
@click.option(
    "--intensity",
    type=click.Choice(INTENSITY_MODES),
    default="mean",
    show_default=True,
    help="Image intensity of the LDDCV's first channel: mean of R, G, B, or BT.601 luma.",
)
@click.option(
    "--lddcv-format",
    type=click.Choice(["npy", "png"]),
    default="npy",
    show_default=True,
    help="LDDCV as one (H, W, 2) float32 .npy, or two 16-bit PNGs <frame>_y / <frame>_dc "
    "holding round(v x 65535).",
)
@click.option(
    "--save-pictures",
    is_flag=True,
    help="Also write OUT/pictures/<sequence>/<frame>.png: image, dark channel, LDDCV "
    "channels and mask, labelled.",
)
@deprecated("--window", "--patch-size", command="dark-channel", dest="patch_size")
@batch_options
def dark_channel(
    images, out_dir, patch_size, mask_threshold, mask_mode, intensity, lddcv_format, save_pictures,
    batch,
    as_json,
):  # fmt: skip
    """Dark channel DC, LDDCV map and its mask M = 1[|LDDCV| > T] of every image.

    DC(p) is the minimum over R, G, B and over the N x N patch around p; LDDCV(i) holds the
    largest absolute difference to the 3 x 3 neighbours of the image intensity and of DC.
    IMAGES are PNG/JPEG files or folders (a defocus-synth output folder gives its defocused
    images). Writes OUT/dark/<sequence>/<frame>.png (8-bit), OUT/lddcv/<sequence>/<frame>.npy
    ((H, W, 2) float32) and OUT/mask/<sequence>/<frame>.png (0/255).

    \b
    Examples:
      sparsetools dark-channel out/defocus -o out/dc
      sparsetools dark-channel out/defocus -o out/dc_luma --intensity luma \\
          --mask-mode separate --lddcv-format png --save-pictures
    """
    from ..io.sources import image_frames
    from ..pipeline import run_job
    from ..pipeline.dark_channel import DarkChannelJob, DarkChannelSettings

    settings = DarkChannelSettings(
        window=patch_size,
        threshold=mask_threshold,
        intensity=intensity,
        mask_mode=mask_mode,
        lddcv_format=lddcv_format,
        pictures=save_pictures,
    )
    summary = run_job(DarkChannelJob(settings), image_frames(images), out_dir, batch=batch,
                      inputs=images)  # fmt: skip
    emit_summary(summary, as_json=as_json, title=f"dark-channel maps written to {out_dir}")
