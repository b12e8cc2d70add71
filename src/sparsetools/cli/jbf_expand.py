"""``sparsetools jbf-expand``: range-aware joint bilateral expansion of sparse radar depth."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
    calib_option,
    emit_summary,
    image_option,
    max_depth_option,
    output_dir_option,
    positive,
    resize_option,
)


def _window(ctx, param, value):
    """Parse ``WxH`` in metres (e.g. 2.35x2.35) into (w, h)."""
    if value is None:
        return None
    try:
        w, h = (float(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(
            f"expected WxH in metres such as 2.35x2.35, got {value!r}"
        ) from None
    if not (w > 0 and h > 0) or w == float("inf") or h == float("inf"):
        raise click.BadParameter(f"window sizes must be finite and > 0, got {value!r}")
    return w, h


_POSITIVE = click.FloatRange(min=0, min_open=True)


@click.command("jbf-expand")
@click.argument("radar", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@image_option(required=True, help="Camera image (one frame) or folder of images matched by frame.")
@calib_option(
    help="Calibration file or folder of per-frame .json|.txt (focal lengths; radar->camera "
    "transform for .pcd inputs)."
)
@click.option(
    "--fx", type=float, callback=positive, help="Focal length in pixels (instead of --calib)."
)
@click.option(
    "--fy", type=float, callback=positive, help="Focal length in pixels (instead of --calib)."
)
@output_dir_option
@click.option(
    "--method",
    type=click.Choice(["jbf", "height-extend"]),
    default="jbf",
    show_default=True,
    help="Joint bilateral expansion or the vertical-line baseline.",
)
@click.option(
    "--sigma-s",
    type=_POSITIVE,
    default=25.0,
    show_default=True,
    help="Spatial kernel sigma, pixels.",
)
@click.option(
    "--sigma-r",
    type=_POSITIVE,
    default=10.0,
    show_default=True,
    help="Range kernel sigma, intensity levels (0..255).",
)
@click.option(
    "--threshold",
    type=click.FloatRange(min=0, max=1, min_open=True),
    default=0.05,
    show_default=True,
    help="Expand pixels whose confidence is >= this.",
)
@click.option(
    "--window",
    "window_m",
    callback=_window,
    default="2.35x2.35",
    show_default=True,
    metavar="WxH",
    help="Real-world window in metres (authors' scripts: 1x2).",
)
@click.option(
    "--kernel",
    type=click.Choice(["jbf", "range", "spatial"]),
    default="jbf",
    show_default=True,
    help="Both kernels, or one alone (the paper's ablation).",
)
@click.option(
    "--range-metric",
    type=click.Choice(["gray", "rgb"]),
    default="gray",
    show_default=True,
    help="Intensity difference on luminance or Euclidean RGB.",
)
@click.option(
    "--conflict",
    type=click.Choice(["nearest", "max-confidence"]),
    default="nearest",
    show_default=True,
    help="Which seed wins a pixel reached by several windows.",
)
@resize_option(help="Scale image, radar and LiDAR maps and intrinsics by S (e.g. 0.5).")
@click.option(
    "--confidence/--no-confidence",
    default=True,
    show_default=True,
    help="Also write <frame>_conf.png (confidence * 65535) or .npy.",
)
@click.option(
    "--conf-format",
    type=click.Choice(["png", "npy"]),
    default="png",
    show_default=True,
    help="Confidence map as uint16 PNG or float32 .npy.",
)
@click.option(
    "--lidar",
    type=click.Path(exists=True, path_type=Path),
    help="LiDAR depth PNG or folder matched by frame: print the intrinsic-error table.",
)
@max_depth_option(default=80.0, help="LiDAR depth cap of the intrinsic error, metres.")
@batch_options
def jbf_expand(
    radar,
    image,
    calib,
    fx,
    fy,
    out_dir,
    method,
    sigma_s,
    sigma_r,
    threshold,
    window_m,
    kernel,
    range_metric,
    conflict,
    resize,
    confidence,
    conf_format,
    lidar,
    max_depth,
    batch,
    as_json,
):
    """Expand sparse radar depth with a range-aware joint bilateral filter.

    RADAR... are radar depth PNGs (KITTI uint16, e.g. from `sparsetools project`) or
    nuScenes radar .pcd files (projected with --calib), or folders of them (a `project`
    output folder, with its <sequence>/ sub-folders). Writes OUT/<sequence>/<frame>.png
    (expanded depth) and OUT/<sequence>/<frame>_conf.png (confidence); inputs are matched
    by frame.

    \b
    Example:
      sparsetools synth-scene out/scene --frames 2 --underwater-frames 0
      sparsetools jbf-expand out/scene/radar --calib out/scene/calib_radar \\
          --image out/scene/image_2 --lidar out/scene/depth_gt -o out/jbf
      sparsetools jbf-expand radar/000000.png --image 000000.png --fx 721.5 --fy 721.5 \\
          --kernel range -o out/range
    """
    from ..pipeline.jbf_expand import JbfSettings, format_intrinsic_table, run_jbf_expand

    if calib is None and (fx is None or fy is None):
        raise click.UsageError("give --calib, or both --fx and --fy")
    if calib is not None and (fx is not None or fy is not None):
        raise click.UsageError("give either --calib or --fx/--fy, not both")
    settings = JbfSettings(
        method=method,
        sigma_s=sigma_s,
        sigma_r=sigma_r,
        threshold=threshold,
        window_m=window_m,
        kernel=kernel,
        range_metric=range_metric,
        conflict=conflict,
        resize=resize,
        confidence=confidence,
        conf_format=conf_format,
        max_depth=max_depth,
    )
    summary = run_jbf_expand(
        list(radar),
        image=image,
        out_dir=out_dir,
        settings=settings,
        calib=calib,
        fx=fx,
        fy=fy,
        lidar=lidar,
        batch=batch,
    )
    result = summary.as_dict()
    table = result.pop("intrinsic_error", None)
    if table is not None:
        if as_json:
            result["intrinsic_error"] = table
        elif table["frames"]:
            click.echo(format_intrinsic_table(table, max_depth=max_depth))
    emit_summary(result, as_json=as_json, title=f"expanded radar written to {out_dir}")
