"""``sparsetools jbf-expand``: range-aware joint bilateral expansion of sparse radar depth."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
    calib_option,
    deprecated,
    emit_summary,
    image_option,
    max_depth_option,
    method_option,
    output_dir_option,
    positive,
    resize_option,
    size_metres,
)


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
@method_option(
    ["jbf", "height-extend"],
    default="jbf",
    help="Joint bilateral expansion or the vertical-line baseline.",
)
@click.option(
    "--sigma-s",
    type=float,
    callback=positive,
    default=25.0,
    show_default=True,
    help="Spatial kernel sigma, pixels.",
)
@click.option(
    "--sigma-r",
    type=float,
    callback=positive,
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
    "--window-m",
    "window_m",
    callback=size_metres,
    default="2.35x2.35",
    show_default=True,
    metavar="WxH",
    help="Real-world window, width x height in metres (authors' scripts: 1x2).",
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
    "--conf-format",
    type=click.Choice(["png", "npy", "none"]),
    default="png",
    show_default=True,
    help="Confidence map <frame>_conf.png (uint16, confidence * 65535), <frame>_conf.npy "
    "(float32), or none.",
)
@click.option(
    "--lidar",
    type=click.Path(exists=True, path_type=Path),
    help="LiDAR depth PNG or folder matched by frame: print the intrinsic-error table.",
)
@max_depth_option(default=80.0, help="LiDAR depth cap of the intrinsic error, metres.")
@deprecated("--window", "--window-m", command="jbf-expand", dest="window_m", metavar="WxH")
@deprecated("--no-confidence", "--conf-format none", command="jbf-expand", dest="conf_format",
            value="none", is_flag=True)  # fmt: skip
@deprecated("--confidence", "--conf-format png", command="jbf-expand", dest="conf_format",
            value="png", is_flag=True)  # fmt: skip
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
      sparsetools synth-scene -o out/scene --frames 2 --underwater-frames 0
      sparsetools jbf-expand out/scene/radar --calib out/scene/calib_radar \\
          --image out/scene/image_2 --lidar out/scene/depth_gt -o out/jbf
      sparsetools jbf-expand radar/000000.png --image 000000.png --fx 721.5 --fy 721.5 \\
          --kernel range -o out/range
      sparsetools jbf-expand out/scene/radar --calib out/scene/calib_radar \\
          --image out/scene/image_2 --window-m 1x2 --conf-format none -o out/jbf12
    """
    from ..io.sources import radar_frames
    from ..pipeline import run_job
    from ..pipeline.jbf_expand import JbfJob, JbfSettings, format_intrinsic_table

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
        confidence=conf_format != "none",
        conf_format="png" if conf_format == "none" else conf_format,
        max_depth=max_depth,
    )
    frames = radar_frames(radar, image=image, calib=calib, lidar=lidar)
    summary = run_job(JbfJob(settings, fx, fy), frames, out_dir, batch=batch,
                      inputs=[*radar, image, calib, lidar])  # fmt: skip
    result = summary.as_dict()
    table = result.pop("intrinsic_error", None)
    if table is not None:
        if as_json:
            result["intrinsic_error"] = table
        elif table["frames"]:
            click.echo(format_intrinsic_table(table, max_depth=max_depth))
    emit_summary(result, as_json=as_json, title=f"expanded radar written to {out_dir}")
