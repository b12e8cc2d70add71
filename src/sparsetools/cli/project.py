"""``sparsetools project``: point clouds to sparse depth maps (KITTI, KITTI raw, nuScenes)."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
    calib_option,
    camera_option,
    crop_option,
    emit_summary,
    filter_occluded_option,
    format_option,
    image_option,
    image_size_option,
    max_depth_option,
    min_depth_option,
    nuscenes_version_option,
    output_dir_option,
    pixel_offset_option,
    resize_option,
    sensor_option,
    sweeps_option,
)


@click.command("project")
@click.argument(
    "clouds", nargs=-1, metavar="[CLOUD]...", type=click.Path(exists=True, path_type=Path)
)
@calib_option
@output_dir_option
@image_size_option
@image_option
@camera_option(help="KITTI camera index (default 2) or nuScenes camera (default CAM_FRONT).")
@format_option(
    ["png", "npy", "parquet"],
    default="png",
    help="png: KITTI uint16 (depth*256); npy: float32 metres; parquet: "
    "OUT/sparse.parquet, one row per frame with lists u, v, depth.",
)
@min_depth_option
@max_depth_option
@resize_option
@crop_option
@pixel_offset_option
@filter_occluded_option
@click.option(
    "--kitti-raw",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    multiple=True,
    metavar="DIR",
    help="KITTI raw drive, date folder (all its drives) or root of dates; repeatable. "
    "Calibration from each drive's date folder.",
)
@click.option(
    "--kitti-object",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    metavar="ROOT",
    help="KITTI object root (training/velodyne, calib, image_2).",
)
@click.option(
    "--nuscenes",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    metavar="ROOT",
    help="nuScenes root (tables in ROOT/<nuscenes-version>/).",
)
@nuscenes_version_option
@sensor_option(help="nuScenes sensor channel to project (RADAR_FRONT, LIDAR_TOP, ...).")
@sweeps_option(help="nuScenes sweeps accumulated per key frame [default: 5 for radar, 1 else].")
@batch_options
def project(
    clouds,
    calib,
    out_dir,
    image_size,
    image,
    camera,
    fmt,
    min_depth,
    max_depth,
    resize,
    crop,
    pixel_offset,
    filter_occluded,
    kitti_raw,
    kitti_object,
    nuscenes,
    nuscenes_version,
    sensor,
    sweeps,
    batch,
    as_json,
):
    """Project point clouds to sparse depth maps (nearest point wins, order-free).

    CLOUD may be files or folders (.bin KITTI / .pcd.bin nuScenes / .pcd / .ply / .npy),
    KITTI raw drives or date folders, or a KITTI object root (their calibration and images
    are found in the tree). Writes OUT/<sequence>/<frame>.png (or .npy, or
    OUT/sparse.parquet) and the calibration of every map, after --resize/--crop, as
    OUT/calib/<sequence>/<frame>.json; a flat folder of clouds has no <sequence>/ level.
    A rerun skips frames that are up to date, recomputes frames whose inputs changed and
    refuses other settings (see --overwrite).

    \b
    Examples:
      sparsetools project kitti/training/velodyne/000001.bin \\
          --calib kitti/training/calib/000001.txt --image-size 1242x375 -o out/depth
      sparsetools project --kitti-object kitti -o out/depth --pixel-offset -1
      sparsetools project raw/2011_09_26 -o out/raw       # every drive of the date
      sparsetools project --nuscenes nuscenes --sensor RADAR_FRONT --camera CAM_FRONT \\
          --sweeps 5 --resize 0.5 --crop 800x350+0+100 -o out/radar
      sparsetools project raw/2011_09_26 -o out/gt --filter-occluded  # no see-through
    """
    from ..io.sources import cloud_source
    from ..pipeline import run_job
    from ..pipeline.project import ProjectJob, ProjectSettings

    source = cloud_source(
        clouds=clouds, kitti_raw=kitti_raw, kitti_object=kitti_object, nuscenes=nuscenes,
        calib=calib, image=image, camera=camera, nuscenes_version=nuscenes_version,
        sensor=sensor, sweeps=sweeps,
    )  # fmt: skip
    settings = ProjectSettings(
        fmt=fmt,
        min_depth=min_depth,
        max_depth=max_depth,
        pixel_offset=int(pixel_offset),
        resize=resize,
        crop=crop,
        camera=source.camera,
        image_size=image_size,
        filter_occluded=filter_occluded,
    )
    summary = run_job(ProjectJob(settings), source.frames, out_dir, batch=batch,
                      inputs=source.inputs)  # fmt: skip
    emit_summary(summary, as_json=as_json, title=f"sparse depth maps in {out_dir}")
