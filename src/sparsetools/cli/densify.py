"""``sparsetools densify``: dense depth from sparse LiDAR or radar maps (IP-Basic, baselines)."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
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
    ["ip-basic", "nearest", "linear"],
    default="ip-basic",
    help="IP-Basic (Ku et al. 2018), nearest measurement, or linear on the Delaunay triangles.",
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
@format_option(
    ["png", "npy"],
    default="png",
    help="Dense maps as KITTI uint16 PNG (depth * 256) or float32 .npy metres.",
)
@deprecated("--max-depth", "--inversion-offset", command="densify", dest="inversion_offset")
@batch_options
def densify(sparse, out_dir, method, variant, extrapolate, multiscale, inversion_offset, outside,
            fmt, batch, as_json):  # fmt: skip
    """Complete sparse depth maps: IP-Basic (as published) or the nearest / linear baselines.

    SPARSE: depth maps (KITTI uint16 PNG or .npy metres), folders of them, the output of
    project / beams / jbf-expand / accumulate, or a KITTI depth-completion tree
    (proj_depth/velodyne_raw). Radar maps work too. Writes the dense map as
    OUT/<sequence>/<frame>.png (or .npy) and OUT/mask/<sequence>/<frame>.png (uint8: 255 =
    measured in the input, 0 = filled in or no estimate). A rerun skips frames that are up
    to date, recomputes those whose input changed and refuses other settings.

    \b
    Examples:
      sparsetools project sample_data/synthetic/velodyne --calib sample_data/synthetic/calib \\
          --image-size 1242x375 -o out/depth
      sparsetools densify out/depth -o out/dense                    # the paper's version
      sparsetools densify out/depth -o out/dense_ms --multiscale --variant bilateral
      sparsetools densify out/radar -o out/radar_nearest --method nearest
    """
    from ..io.sources import depth_frames
    from ..ops.densify import DensifySettings
    from ..pipeline import run_job
    from ..pipeline.densify import DensifyJob

    settings = DensifySettings(
        method=method,
        variant=variant,
        extrapolate=extrapolate,
        multiscale=multiscale,
        max_depth=inversion_offset,
        outside=outside,
    )
    summary = run_job(DensifyJob(settings, fmt), depth_frames(sparse), out_dir, batch=batch,
                      inputs=sparse)  # fmt: skip
    emit_summary(summary, as_json=as_json, title=f"dense depth maps in {out_dir}")
