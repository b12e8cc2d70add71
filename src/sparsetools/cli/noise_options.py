"""Options of the sensor-noise and depth-input commands (lowlight-synth, defocus-synth): each
declared once, as the shared ones in :mod:`.options`."""

from __future__ import annotations

from pathlib import Path

import click

from .parsing import pair

__all__ = [
    "color_bias_option",
    "depth_option",
    "noise_cameras",
    "noise_option",
    "noise_profile_option",
    "ratio_option",
]


def depth_option(f=None, *, help: str, required: bool = False):
    """``--depth``: a depth map (one image) or a folder of depth maps matched by frame."""

    def deco(fn):
        return click.option(
            "--depth", required=required, type=click.Path(exists=True, path_type=Path), help=help
        )(fn)

    return deco(f) if f is not None else deco


def noise_option(f=None, *, default: str = "eld"):
    """``--noise``: the ELD read-noise model, or none."""
    from ..ops.noise import NOISE_MODELS

    def deco(fn):
        return click.option(
            "--noise",
            type=click.Choice(NOISE_MODELS),
            default=default,
            show_default=True,
            help="Sensor noise: ELD (Tukey-lambda read noise), Gaussian read noise (ELD's "
            "separate Gaussian fit), or none.",
        )(fn)

    return deco(f) if f is not None else deco


def noise_cameras() -> tuple[str, ...]:
    """ELD noise tables shipped with the package, and ``random`` (one per image)."""
    from ..ops.noise import CAMERA_PROFILES

    return (*CAMERA_PROFILES, "random")


def noise_profile_option(f):
    """``--noise-profile``: the ELD noise table (a camera's measured noise)."""
    return click.option(
        "--noise-profile",
        type=click.Choice(noise_cameras()),
        default="SonyA7S2",
        show_default=True,
        help="ELD noise profile: the camera whose measured noise is added (random: one per image).",
    )(f)


def ratio_option(f=None, *, default: str = "2,32"):
    """``--ratio``: exposure ratio range of the noise."""

    def deco(fn):
        return click.option(
            "--ratio",
            callback=pair(low=0, strict=True),
            default=default,
            show_default=True,
            metavar="MIN,MAX",
            help="Exposure ratio ~ logU: higher = darker raw signal, more visible noise.",
        )(fn)

    return deco(f) if f is not None else deco


def color_bias_option(f):
    """``--color-bias``: add the noise table's per-channel black-level offsets."""
    return click.option(
        "--color-bias",
        is_flag=True,
        help="Add the ELD table's per-channel black-level offsets of the drawn calibration "
        "row (with the noise).",
    )(f)
