"""``sparsetools lowlight-synth``: day images to synthetic night images (flares + sensor noise).

The options of the ELD sensor noise and of the depth input (``--depth``, ``--noise``,
``--camera``, ``--ratio``, ``--color-bias``) are shared with ``defocus-synth`` (cli/options.py).
"""

from __future__ import annotations

import logging
from pathlib import Path

import click

from .noise_options import (
    color_bias_option,
    depth_option,
    noise_cameras,
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

#: ELD noise tables shipped with the package, and "random" (one per image).
CAMERAS = noise_cameras()


log = logging.getLogger(__name__)


@click.command("lowlight-synth")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@output_dir_option
@depth_option(
    help="Depth PNG (KITTI uint16) for one image, or a folder matched by frame: flare "
    "sources are placed only at pixels with depth in (0, --flare-max-depth] m."
)
@calib_option(
    help="Calibration (or folder of per-frame .txt/.json) giving K, to record each "
    "light source's 3-D point."
)
@seed_option(help="Global seed; each output uses frame_rng(seed, '<frame id>:<variant>').")
@click.option(
    "--variants",
    type=click.IntRange(min=1, max=1000),
    default=1,
    show_default=True,
    help="Night versions per image, 1-1000 (OUT/<frame>_v<k>.png when > 1).",
)
@click.option("--flare/--no-flare", default=True, show_default=True, help="Add lens flares.")
@noise_option(default="eld")
@noise_profile_option
@color_bias_option
@click.option(
    "--brightness",
    callback=pair(low=0, strict=True),
    default="0.4,1.0",
    show_default=True,
    metavar="MIN,MAX",
    help="Brightness scale s_b ~ U(MIN, MAX).",
)
@click.option(
    "--gamma",
    callback=pair(low=0, strict=True),
    default="1.8,2.2",
    show_default=True,
    metavar="MIN,MAX",
    help="Linearisation gamma g ~ U(MIN, MAX).",
)
@click.option(
    "--flare-count",
    callback=pair(integer=True, single=True, low=1),
    default="1,20",
    show_default=True,
    metavar="N|MIN,MAX",
    help="Clip range of the flare count N_F (N: exactly N).",
)
@click.option(
    "--flare-scale",
    callback=pair(low=0, strict=True),
    default="0.2,1.0",
    show_default=True,
    metavar="MIN,MAX",
    help="s_F ~ logU: flare size as a fraction of the shorter side.",
)
@click.option(
    "--flare-amount",
    callback=pair(low=0, strict=True),
    default="0.3,3.0",
    show_default=True,
    metavar="MIN,MAX",
    help="F ~ logU; N_F = max(floor(F / s_F + 0.5), 1).",
)
@click.option(
    "--flare-max-depth",
    type=float,
    default=20.0,
    show_default=True,
    callback=positive,
    help="Farthest light source, metres (with --depth).",
)
@ratio_option(default="2,32")
@click.option(
    "--bank-seed",
    type=int,
    default=0,
    show_default=True,
    help="Seed of the procedural flare-pattern bank.",
)
@deprecated("--camera", "--noise-profile", command="lowlight-synth", dest="noise_profile")
@batch_options
def lowlight_synth(
    images,
    out_dir,
    depth,
    calib,
    seed,
    variants,
    flare,
    noise,
    noise_profile,
    color_bias,
    brightness,
    gamma,
    flare_count,
    flare_scale,
    flare_amount,
    flare_max_depth,
    ratio,
    bank_seed,
    batch,
    as_json,
):
    """Turn day images into night images (DepthDark's low-light data generation).

    IMAGES are PNG/JPEG files or folders. Each output is (s_b I)^g plus procedural lens
    flares, with ELD sensor noise in linear light, returned with exponent 1/g. Writes
    OUT/<sequence>/<frame>.png (<frame>_v<k>.png with --variants > 1), a JSON record per
    output in OUT/records/, and OUT/manifest.parquet (one row per output: source, variant, seed and
    every sampled parameter). The same seed gives the same bytes whatever --workers is.

    \b
    Examples:
      sparsetools lowlight-synth out/scene/image_2 --depth out/scene/depth_gt \\
          --calib out/scene/calib -o out/night
      sparsetools lowlight-synth day.png -o out/night --variants 4 --noise gaussian
      sparsetools lowlight-synth day.png -o out/night --noise-profile CanonEOS5D4 --color-bias
    """
    from ..io.sources import images_with_depth
    from ..ops.lowlight import LowLightParams
    from ..pipeline import run_job
    from ..pipeline.lowlight import LowLightJob, LowLightSettings

    params = LowLightParams(
        brightness=brightness,
        gamma=gamma,
        flare=flare,
        flare_scale=flare_scale,
        flare_amount=flare_amount,
        flare_count=flare_count,
        flare_max_depth=flare_max_depth,
        noise=noise,
        camera=noise_profile,
        color_bias=color_bias,
        ratio=ratio,
        bank_seed=bank_seed,
    )
    settings = LowLightSettings(seed=seed, variants=variants, params=params)
    frames = images_with_depth(images, depth=depth, calib=calib, depth_required=False)
    if calib is not None and depth is None:
        log.warning("--calib without --depth: the calibration is only used to place flares in 3-D")
    summary = run_job(LowLightJob(settings), frames, out_dir, batch=batch,
                      inputs=[*images, depth, calib], desc="lowlight")  # fmt: skip
    emit_summary(summary, as_json=as_json, title=f"night images written to {out_dir}")
