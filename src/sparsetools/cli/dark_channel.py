"""``sparsetools dark-channel``: dark channel, LDDCV map and validity mask of images."""

from __future__ import annotations

from pathlib import Path

import click

from ..ops.dark_channel import COMBINE_MODES, INTENSITY_MODES
from .options import batch_options, emit_summary, non_negative, output_dir_option


def _odd_window(ctx, param, value):
    if value is not None and value % 2 == 0:
        raise click.BadParameter(f"must be odd (a window centred on the pixel), got {value}")
    return value


@click.command("dark-channel")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@output_dir_option
@click.option(
    "--window",
    type=click.IntRange(min=1),
    default=15,
    show_default=True,
    callback=_odd_window,
    help="Side N of the dark channel's square window, pixels (odd).",
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
@batch_options
def dark_channel(
    images, out_dir, window, mask_threshold, mask_mode, intensity, lddcv_format, save_pictures,
    batch,
    as_json,
):  # fmt: skip
    """Dark channel DC, LDDCV map and its mask M = 1[|LDDCV| > T] of every image.

    DC(p) is the minimum over R, G, B and over the N x N window around p; LDDCV(i) holds the
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
    from ..pipeline.dark_channel import DarkChannelSettings, run_dark_channel

    settings = DarkChannelSettings(
        window=window,
        threshold=mask_threshold,
        intensity=intensity,
        mask_mode=mask_mode,
        lddcv_format=lddcv_format,
        pictures=save_pictures,
    )
    summary = run_dark_channel(images, out_dir, settings=settings, batch=batch)
    emit_summary(summary, as_json=as_json, title=f"dark-channel maps written to {out_dir}")
