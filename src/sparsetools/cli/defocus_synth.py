"""``sparsetools defocus-synth``: depth-dependent defocus blur of images from their dense depth."""

from __future__ import annotations

from pathlib import Path

import click

from ..ops.defocus import DEFOCUS_CAMERAS, KERNELS, MISSING_MODES
from .noise_options import (
    color_bias_option,
    depth_option,
    noise_option,
    noise_profile_option,
    ratio_option,
)
from .options import (
    batch_options,
    calib_option,
    deprecated,
    emit_summary,
    output_dir_option,
    pair,
    positive,
    seed_option,
)


@click.command("defocus-synth")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@output_dir_option
@depth_option(
    required=True,
    help="Dense depth of the images: a KITTI uint16 PNG or .npy (metres) for one image, or a "
    "folder matched by frame. Holes (0) are refused unless --missing-depth far.",
)
@calib_option(
    help="Calibration (or folder of per-frame .txt/.json) whose K[0,0] is the focal length in "
    "pixels: f = K[0,0] x pixel pitch (instead of --focal-length-mm)."
)
@click.option(
    "--lens",
    type=click.Choice(list(DEFOCUS_CAMERAS)),
    default="dfd-nyu",
    show_default=True,
    help="Lens and sensor preset (focal length, f-number, pixel pitch); dfd-nyu is the paper's.",
)
@click.option(
    "--focal-length-mm",
    type=float,
    callback=positive,
    help="Focal length f in millimetres (replaces the preset's).",
)
@click.option(
    "--f-number",
    callback=pair(single=True, low=0, strict=True),
    metavar="F|LOW,HIGH",
    help="f-number F_n (A = f / F_n), or a range sampled log-uniformly per image "
    "[default: the preset's].",
)
@click.option(
    "--pixel-pitch-um",
    type=float,
    callback=positive,
    help="Pixel pitch of the images blurred, micrometres (replaces the preset's).",
)
@click.option(
    "--focus-distance",
    callback=pair(single=True, low=0, strict=True),
    default="0.7",
    show_default=True,
    metavar="D|LOW,HIGH",
    help="In-focus distance D_fp in metres, or a range sampled log-uniformly per image.",
)
@click.option(
    "--blur-kernel",
    type=click.Choice(KERNELS),
    default="disk",
    show_default=True,
    help="r(d) as a disk radius, or as the standard deviation of a Gaussian.",
)
@click.option(
    "--layer-step",
    type=float,
    default=0.5,
    show_default=True,
    callback=positive,
    help="Step of the signed radius between depth layers, pixels.",
)
@click.option(
    "--max-radius",
    type=float,
    default=64.0,
    show_default=True,
    callback=positive,
    help="Larger blur radii are clipped to this, pixels.",
)
@click.option(
    "--missing-depth",
    type=click.Choice(MISSING_MODES),
    default="error",
    show_default=True,
    help="Pixels without depth: refuse the image, or render them as infinitely far (sky).",
)
@noise_option(default="none")
@noise_profile_option
@ratio_option(default="1,8")
@click.option(
    "--noise-gamma",
    type=float,
    default=2.2,
    show_default=True,
    callback=positive,
    help="The blurred image is linearised with this exponent for the noise, then re-encoded.",
)
@color_bias_option
@click.option(
    "--radius-format",
    type=click.Choice(["npy", "png"]),
    default="npy",
    show_default=True,
    help="Radius maps as float32 .npy (pixels), or uint16 PNG holding round(radius x 256).",
)
@seed_option(help="Global seed; each image uses frame_rng(seed, '<frame id>').")
@deprecated("--sensor", "--lens", command="defocus-synth", dest="lens")
@deprecated("--camera", "--noise-profile", command="defocus-synth", dest="noise_profile")
@batch_options
def defocus_synth(
    images,
    out_dir,
    depth,
    calib,
    lens,
    focal_length_mm,
    f_number,
    pixel_pitch_um,
    focus_distance,
    blur_kernel,
    layer_step,
    max_radius,
    missing_depth,
    noise,
    noise_profile,
    ratio,
    noise_gamma,
    color_bias,
    radius_format,
    seed,
    batch,
    as_json,
):
    """Blur images as a thin lens focused at D_fp would, from their dense depth.

    Blur radius in pixels r(d) = (1 / (sqrt(2) p_x)) (A f / (D_fp - f)) |d - D_fp| / d,
    A = f / F_n, rendered in depth layers composited near over far (no sharp background
    through a blurred near edge), optionally with ELD sensor noise afterwards. Writes
    OUT/<sequence>/<frame>.png, the radius map OUT/radius/<sequence>/<frame>.npy (or .png),
    a JSON record of every value used in OUT/records/ and OUT/manifest.parquet (one row per
    image). The same seed gives the same bytes whatever --workers is.

    \b
    Examples:
      sparsetools defocus-synth sample_data/synthetic/image_2 \\
          --depth sample_data/synthetic/depth_gt -o out/defocus --missing-depth far \\
          --focal-length-mm 50 --f-number 2 --pixel-pitch-um 4.65 --focus-distance 15
      sparsetools defocus-synth images/ --depth depth/ -o out/defocus_sampled \\
          --lens rpi-v2 --focus-distance 0.3,3 --f-number 1.4,4 --noise eld --seed 0
      sparsetools defocus-synth images/ --depth depth/ -o out/defocus_calib \\
          --calib calib/ --pixel-pitch-um 4.65 --f-number 2 --focus-distance 10
    """
    from ..io.sources import images_with_depth
    from ..pipeline import run_job
    from ..pipeline.defocus import DefocusJob, DefocusSettings

    if calib is not None and focal_length_mm is not None:
        raise click.UsageError("give --focal-length-mm or --calib, not both")
    settings = DefocusSettings(
        seed=seed,
        sensor=lens,
        focal_length_mm=focal_length_mm,
        f_number=f_number,
        pixel_pitch_um=pixel_pitch_um,
        calib=calib is not None,
        focus_distance=focus_distance,
        blur_kernel=blur_kernel,
        layer_step=layer_step,
        max_radius=max_radius,
        missing_depth=missing_depth,
        noise=noise,
        camera=noise_profile,
        ratio=ratio,
        noise_gamma=noise_gamma,
        color_bias=color_bias,
        radius_format=radius_format,
    )
    frames = images_with_depth(images, depth=depth, calib=calib)
    summary = run_job(DefocusJob(settings), frames, out_dir, batch=batch,
                      inputs=[*images, depth, calib], desc="defocus")  # fmt: skip
    emit_summary(summary, as_json=as_json, title=f"defocused images written to {out_dir}")
