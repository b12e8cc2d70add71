"""``sparsetools project``: point clouds to sparse depth maps (KITTI, KITTI raw, nuScenes)."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
    emit_summary,
    executor_from,
    image_size_option,
    output_dir_option,
    progress_enabled,
)


def _crop(ctx, param, value):
    if value is None:
        return None
    try:
        parts = tuple(int(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"expected TOP,LEFT,H,W as integers, got {value!r}") from None
    if len(parts) != 4:
        raise click.BadParameter(f"expected four integers TOP,LEFT,H,W, got {value!r}")
    top, left, h, w = parts
    if top < 0 or left < 0 or h <= 0 or w <= 0:
        raise click.BadParameter(f"TOP, LEFT must be >= 0 and H, W > 0, got {value!r}")
    return parts


def _positive(ctx, param, value):
    if value is not None and not value > 0:
        raise click.BadParameter(f"must be > 0, got {value}")
    return value


def _non_negative(ctx, param, value):
    if value is not None and not value >= 0:
        raise click.BadParameter(f"must be >= 0, got {value}")
    return value


@click.command("project")
@click.argument(
    "clouds", nargs=-1, metavar="[CLOUD]...", type=click.Path(exists=True, path_type=Path)
)
@click.option(
    "--calib",
    type=click.Path(exists=True, path_type=Path),
    help="KITTI object calib .txt, KITTI raw date folder, JSON calibration, or a folder "
    "of per-frame calib files matched by stem.",
)
@output_dir_option
@image_size_option
@click.option(
    "--image",
    type=click.Path(exists=True, path_type=Path),
    help="Image (or folder of images matched by stem) giving the map size.",
)
@click.option(
    "--camera",
    default=None,
    help="KITTI camera index (default 2) or nuScenes camera (default CAM_FRONT).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["png", "npy", "parquet"]),
    default="png",
    show_default=True,
    help="png: KITTI uint16 (depth*256); npy: float32 metres; parquet: "
    "OUT/sparse.parquet, one row per frame with lists u, v, depth.",
)
@click.option(
    "--min-depth",
    type=float,
    default=0.1,
    show_default=True,
    callback=_non_negative,
    help="Drop points with depth <= this (metres).",
)
@click.option(
    "--max-depth",
    type=float,
    default=None,
    callback=_positive,
    help="Drop points with depth > this (metres; default no limit).",
)
@click.option(
    "--resize",
    type=float,
    default=None,
    callback=_positive,
    metavar="S",
    help="Scale the image and intrinsics by S first (e.g. 0.5: 1600x900 -> 800x450).",
)
@click.option(
    "--crop",
    callback=_crop,
    metavar="TOP,LEFT,H,W",
    help="Then crop to H x W pixels at (TOP, LEFT), e.g. 100,0,350,800.",
)
@click.option(
    "--pixel-offset",
    type=click.Choice(["0", "-1"]),
    default="0",
    show_default=True,
    help="-1 shifts pixels by one as monodepth2 does (KITTI's 1-based code).",
)
@click.option(
    "--kitti-raw",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    metavar="DRIVE_DIR",
    help="KITTI raw drive (<date>_drive_XXXX_sync); calib from its date folder.",
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
    help="nuScenes root (tables in ROOT/<version>/).",
)
@click.option(
    "--version",
    "nuscenes_version",
    default="v1.0-mini",
    show_default=True,
    help="nuScenes table version.",
)
@click.option(
    "--sensor",
    default="RADAR_FRONT",
    show_default=True,
    help="nuScenes sensor channel to project (RADAR_FRONT, LIDAR_TOP, ...).",
)
@click.option(
    "--sweeps",
    type=click.IntRange(min=1),
    default=None,
    help="nuScenes sweeps accumulated per key frame [default: 5 for radar, 1 else].",
)
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
    kitti_raw,
    kitti_object,
    nuscenes,
    nuscenes_version,
    sensor,
    sweeps,
    workers,
    overwrite,
    on_error,
    executor,
    dask_scheduler,
    as_json,
):
    """Project point clouds to sparse depth maps (nearest point wins, order-free).

    CLOUD may be files or folders (.bin KITTI / .pcd.bin nuScenes / .pcd / .ply / .npy).
    Writes OUT/<stem>.png (or .npy, or OUT/sparse.parquet) and the calibration of every map,
    after --resize/--crop, as OUT/calib/<stem>.json.

    \b
    Examples:
      sparsetools project kitti/training/velodyne/000001.bin \\
          --calib kitti/training/calib/000001.txt --image-size 1242x375 -o out/depth
      sparsetools project --kitti-object kitti -o out/depth --pixel-offset -1
      sparsetools project --kitti-raw 2011_09_26/2011_09_26_drive_0001_sync -o out/raw
      sparsetools project --nuscenes nuscenes --sensor RADAR_FRONT --camera CAM_FRONT \\
          --sweeps 5 --resize 0.5 --crop 100,0,350,800 -o out/radar
    """
    from ..io.sources import frames_from_paths, kitti_object_frames, kitti_raw_frames
    from ..pipeline.project import ProjectSettings, nuscenes_tasks, run_project, tasks_from_frames

    given = [
        name
        for name, v in (
            ("CLOUD", clouds),
            ("--kitti-raw", kitti_raw),
            ("--kitti-object", kitti_object),
            ("--nuscenes", nuscenes),
        )
        if v
    ]
    if len(given) != 1:
        raise click.UsageError(
            "give exactly one source: CLOUD..., --kitti-raw, --kitti-object or --nuscenes"
            + (f" (got {', '.join(given)})" if given else "")
        )
    if clouds and calib is None:
        raise click.UsageError("CLOUD arguments need --calib")
    if calib is not None and not clouds:
        raise click.UsageError(f"--calib goes with CLOUD arguments ({given[0]} has its own)")
    if image is not None and not clouds:
        raise click.UsageError(f"--image goes with CLOUD arguments ({given[0]} has its own)")
    if nuscenes:
        cam = camera or "CAM_FRONT"
    elif camera is None:
        cam = 2
    elif camera.isdigit():
        cam = int(camera)
    elif clouds:
        cam = camera  # a camera name, for JSON calibrations holding several cameras
    else:
        raise click.BadParameter(
            f"KITTI camera is an index 0-3, got {camera!r}", param_hint="--camera"
        )
    settings = ProjectSettings(
        fmt=fmt,
        min_depth=min_depth,
        max_depth=max_depth,
        pixel_offset=int(pixel_offset),
        resize=resize,
        crop=crop,
        camera=cam,
        image_size=image_size,
    )
    if nuscenes:
        n = sweeps if sweeps is not None else (5 if sensor.upper().startswith("RADAR") else 1)
        tasks = nuscenes_tasks(
            nuscenes,
            out_dir,
            settings,
            version=nuscenes_version,
            sensor=sensor,
            camera=cam,
            sweeps=n,
        )
        inputs = [nuscenes]
    else:
        if clouds:
            frames = frames_from_paths(list(clouds), calib=calib, image=image)
            inputs = [*clouds, calib, *([image] if image else [])]
        elif kitti_raw:
            frames, inputs = kitti_raw_frames(kitti_raw), [kitti_raw]
        else:
            frames, inputs = kitti_object_frames(kitti_object, camera=cam), [kitti_object]
        tasks = tasks_from_frames(frames, out_dir, settings)
    params = click.get_current_context().params
    summary = run_project(
        tasks,
        out_dir,
        inputs=inputs,
        executor=executor_from(params),
        overwrite=overwrite,
        on_error=on_error,
        progress=progress_enabled(),
    )
    emit_summary(summary, as_json=as_json, title=f"sparse depth maps in {out_dir}")
