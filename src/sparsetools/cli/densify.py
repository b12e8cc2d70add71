"""``sparsetools densify``: dense depth from sparse LiDAR or radar maps (IP-Basic, baselines)."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
    densifier_option,
    deprecated,
    emit_summary,
    format_option,
    method_option,
    output_dir_option,
    positive,
)


@click.command("densify")
@click.argument(
    "sparse",
    nargs=-1,
    required=True,
    metavar="SPARSE...",
    type=click.Path(exists=True, path_type=Path),
)
@output_dir_option
@method_option(
    ["ip-basic", "nearest", "linear", "learned"],
    default="ip-basic",
    help="IP-Basic (Ku et al. 2018), nearest measurement, linear on the Delaunay triangles, "
    "or the learned densifier of train-densifier (with --densifier; SpaDe-style, with "
    "uncertainty).",
)
@click.option(
    "--variant",
    type=click.Choice(["gaussian", "bilateral"]),
    default="gaussian",
    show_default=True,
    help="IP-Basic's last blur: the paper's 5x5 Gaussian, or the bilateral filter.",
)
@click.option(
    "--extrapolate/--no-extrapolate",
    default=True,
    show_default=True,
    help="IP-Basic: extend each column's top value to row 0 and fill the large holes (31x31).",
)
@click.option(
    "--multiscale",
    is_flag=True,
    help="IP-Basic's multi-scale version with noise removal (instead of the fast one).",
)
@click.option(
    "--inversion-offset",
    type=float,
    default=100.0,
    show_default=True,
    callback=positive,
    help="IP-Basic's depth inversion d' = OFFSET - d, metres (depths >= OFFSET - 0.1 are "
    "ignored; the paper: 100).",
)
@click.option(
    "--outside",
    type=click.Choice(["nearest", "zero"]),
    default="nearest",
    show_default=True,
    help="Linear fill outside the convex hull of the measurements: nearest one, or 0.",
)
@densifier_option(
    help="--method learned: the densifier checkpoint (densifier.pt of train-densifier, or its "
    "run folder)."
)
@click.option(
    "--uncertainty",
    is_flag=True,
    help="--method learned: also write OUT/uncertainty/<sequence>/<frame>.npy, float32 "
    "U = log sigma^2 per pixel (sigma in metres: sigma = exp(U / 2); no scale, no offset).",
)
@format_option(
    ["png", "npy"],
    default="png",
    help="Dense maps as KITTI uint16 PNG (depth * 256) or float32 .npy metres.",
)
@deprecated("--max-depth", "--inversion-offset", command="densify", dest="inversion_offset")
@batch_options
def densify(sparse, out_dir, method, variant, extrapolate, multiscale, inversion_offset, outside,
            densifier, uncertainty, fmt, batch, as_json):  # fmt: skip
    """Complete sparse depth maps: IP-Basic (as published), the nearest / linear baselines, or
    the learned densifier.

    SPARSE: depth maps (KITTI uint16 PNG or .npy metres), folders of them, the output of
    project / beams / jbf-expand / accumulate, or a KITTI depth-completion tree
    (proj_depth/velodyne_raw). Radar maps work too. Writes the dense map as
    OUT/<sequence>/<frame>.png (or .npy) and OUT/mask/<sequence>/<frame>.png (uint8: 255 =
    measured in the input, 0 = filled in or no estimate). A rerun skips frames that are up
    to date, recomputes those whose input changed and refuses other settings.

    --method learned --densifier CHECKPOINT runs a densifier trained by `train-densifier` (one
    torch thread per worker; every pixel gets a depth) and with --uncertainty writes its
    log-variance map U beside the depth (docs/densify.md: how far to trust each pixel).

    \b
    Examples:
      sparsetools project sample_data/synthetic/velodyne --calib sample_data/synthetic/calib \\
          --image-size 1242x375 -o out/depth
      sparsetools densify out/depth -o out/dense                    # the paper's version
      sparsetools densify out/depth -o out/dense_ms --multiscale --variant bilateral
      sparsetools densify out/radar -o out/radar_nearest --method nearest
      sparsetools train-densifier -o out/densifier --threads 1
      sparsetools densify out/depth -o out/dense_learned --method learned \\
          --densifier out/densifier/densifier.pt --uncertainty
    """
    from ..io.sources import depth_frames
    from ..ops.densify import DensifySettings
    from ..pipeline import run_job
    from ..pipeline.densify import DensifyJob, LearnedSettings

    learned, model = _learned_method(method, densifier, uncertainty)
    settings = DensifySettings(
        method="ip-basic" if learned else method,
        variant=variant,
        extrapolate=extrapolate,
        multiscale=multiscale,
        max_depth=inversion_offset,
        outside=outside,
    )
    if learned:
        learned = LearnedSettings(str(model.path.resolve()), uncertainty)
    job = DensifyJob(settings, fmt, learned=learned or None, model=model)
    summary = run_job(job, depth_frames(sparse), out_dir, batch=batch, inputs=sparse)
    emit_summary(summary, as_json=as_json, title=f"dense depth maps in {out_dir}")


#: Options of the classical methods (refused with --method learned when given).
_CLASSICAL = ("variant", "extrapolate", "multiscale", "inversion_offset", "outside")


def _learned_method(method, densifier, uncertainty):
    """(True, the loaded model) for --method learned, else (False, None); options that do not
    go with the method are usage errors."""
    from click.core import ParameterSource

    ctx = click.get_current_context()

    def given(name):
        return ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT)

    if method != "learned":
        for name in ("densifier", "uncertainty"):
            if given(name):
                raise click.UsageError(f"--{name} belongs to --method learned")
        return False, None
    if densifier is None:
        raise click.UsageError("--method learned needs --densifier CHECKPOINT (train-densifier "
                               "writes one)")  # fmt: skip
    for name in _CLASSICAL:
        if given(name):
            flag = "--" + name.replace("_", "-")
            raise click.UsageError(f"{flag} is an option of the classical methods, not of "
                                   "--method learned")  # fmt: skip
    from ..train._torch_required import require_torch

    require_torch("densify --method learned")
    from ..train.densifier import LearnedDensifier

    return True, LearnedDensifier(densifier, threads=1)
