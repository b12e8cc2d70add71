"""``sparsetools densify``: dense depth from sparse LiDAR or radar maps (IP-Basic, baselines)."""

from __future__ import annotations

from pathlib import Path

import click

from .options import batch_options, emit_summary, max_depth_option, output_dir_option


@click.command("densify")
@click.argument(
    "sparse",
    nargs=-1,
    required=True,
    metavar="SPARSE...",
    type=click.Path(exists=True, path_type=Path),
)
@output_dir_option
@click.option(
    "--method",
    type=click.Choice(["ip-basic", "nearest", "linear"]),
    default="ip-basic",
    show_default=True,
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
@max_depth_option(
    default=100.0, help="IP-Basic's inversion offset, metres (depths >= this - 0.1 are ignored)."
)
@click.option(
    "--outside",
    type=click.Choice(["nearest", "zero"]),
    default="nearest",
    show_default=True,
    help="Linear fill outside the convex hull of the measurements: nearest one, or 0.",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["png", "npy"]),
    default="png",
    show_default=True,
    help="Dense maps as KITTI uint16 PNG (depth * 256) or float32 .npy metres.",
)
@batch_options
def densify(sparse, out_dir, method, variant, extrapolate, multiscale, max_depth, outside, fmt,
            batch, as_json):  # fmt: skip
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
    from ..ops.densify import DensifySettings
    from ..pipeline.densify import run_densify

    settings = DensifySettings(
        method=method,
        variant=variant,
        extrapolate=extrapolate,
        multiscale=multiscale,
        max_depth=max_depth,
        outside=outside,
    )
    summary = run_densify(list(sparse), out_dir, settings=settings, fmt=fmt, batch=batch)
    emit_summary(summary, as_json=as_json, title=f"dense depth maps in {out_dir}")
