"""``sparsetools dataset``: build, inspect and verify Parquet/PNG training datasets."""

from __future__ import annotations

import json
from pathlib import Path

import click

from .dataset_options import (
    params_callback,
    root_option,
    sequence_callback,
    split_file_option,
    splits_option,
    store_option,
)
from .options import (
    batch_options,
    calib_option,
    camera_option,
    cameras_option,
    crop_option,
    deprecated,
    emit_summary,
    filter_occluded_option,
    gt_option,
    icp_min_range_option,
    json_option,
    layout_option,
    nuscenes_version_option,
    output_dir_option,
    overwrite_option,
    quiet_debug_options,
    resize_option,
    resize_to_option,
    seed_option,
    sensor_option,
    split_option,
    store_geometry_option,
    store_points_option,
    sweeps_option,
    threads_option,
)


@click.group("dataset")
def dataset():
    """Build, inspect and verify training datasets (Parquet manifest + PNG/Parquet files).

    \b
    Example:
      sparsetools synth-scene -o out/scene --frames 4 --underwater-frames 0
      sparsetools dataset build -o out/ds --rgb out/scene/image_2 \\
          --sparse out/scene/depth_gt --calib out/scene/calib
      sparsetools dataset info out/ds
      sparsetools dataset verify out/ds
    See docs/dataset.md for the on-disk format.
    """


@dataset.command("build")
@output_dir_option(help="Dataset folder (created, or extended when it holds a dataset).")
@click.option(
    "--rgb",
    required=True,
    type=click.Path(exists=True, path_type=Path),
    help="Camera images: a folder tree (<sequence>/<frame>.png), a KITTI raw drive, date "
    "folder or root, or a val_selection_cropped folder.",
)
@click.option(
    "--sparse",
    required=True,
    type=click.Path(exists=True, path_type=Path),
    help="Sparse depth maps (KITTI uint16 PNG or .npy metres): a folder tree, a project / "
    "beams / jbf-expand output, a KITTI depth-completion tree, or a Parquet points table.",
)
@gt_option(help="Ground-truth depth maps (PNG or .npy), e.g. a KITTI depth-completion tree.")
@click.option(
    "--confidence",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="Folder of confidence maps (PNG uint16/65535 or .npy; <frame>_conf matches).",
)
@calib_option(
    help="One calibration (file or KITTI raw calib folder) or a folder of per-frame "
    "calibrations: gives fx, fy, cx, cy (a KITTI raw --rgb tree brings its own)."
)
@click.option(
    "--sequence-from",
    default="parent",
    show_default=True,
    callback=sequence_callback,
    metavar="parent|regex:PATTERN",
    help="Sequence of a frame: its folder, or a regex on its relative path "
    "(group 'sequence' or group 1).",
)
@splits_option(dataset="kitti", tree=True)
@split_file_option(
    help="Split list (KITTI Eigen form, or one id or sequence per line); repeat per split. "
    "The split name comes from NAME= or the file name (train/val/test)."
)
@seed_option(help="Seed of the split assignment.")
@click.option(
    "--sparse-format",
    type=click.Choice(["png", "parquet", "both"]),
    default="both",
    show_default=True,
    help="Store sparse depth as KITTI PNGs, Parquet points, or both.",
)
@store_option
@deprecated(
    "--link", "--store link", command="dataset build", dest="store", value="link", is_flag=True
)
@deprecated(
    "--copy", "--store copy", command="dataset build", dest="store", value="copy", is_flag=True
)
@click.option(
    "--source",
    default="lidar",
    show_default=True,
    help="Sensor of the sparse depth, stored per sample (lidar, lidar-4beam, radar...).",
)
@click.option(
    "--params",
    callback=params_callback,
    metavar="JSON|FILE",
    help="Generation parameters (JSON object) stored in every new row.",
)
@store_geometry_option
@batch_options
def build(
    out_dir,
    rgb,
    sparse,
    gt,
    confidence,
    calib,
    sequence_from,
    official_split,
    splits,
    split_files,
    seed,
    sparse_format,
    store,
    source,
    params,
    store_geometry,
    batch,
    as_json,
):
    """Build a dataset, or add frames to one, from per-frame files matched by frame.

    Frames are matched by their key <sequence>/<frame> (the sequence folder, or the KITTI
    drive, and the file name), or by a frame name unique on both sides. Splits go by
    sequence, never by frame. A rerun skips frames that are up to date, rebuilds frames
    whose inputs changed and refuses other settings (--overwrite rebuilds everything).

    \b
    Examples:
      sparsetools beams out/scene/velodyne --n 4 -o out/beams4
      sparsetools project out/beams4 --calib out/scene/calib --image out/scene/image_2 \\
          -o out/depth4
      sparsetools dataset build -o out/ds4 --rgb out/scene/image_2 --sparse out/depth4 \\
          --gt out/scene/depth_gt --calib out/depth4/calib --source lidar-4beam
      sparsetools dataset build -o out/kitti --rgb raw --sparse velodyne_raw --split eigen
      sparsetools dataset build -o out/kitti --rgb raw --sparse velodyne_raw \\
          --split-file train=my_train_files.txt --split-file test=my_test_files.txt
      sparsetools dataset build -o out/ds4_ref --rgb out/scene/image_2 --sparse out/depth4 \\
          --store reference
    """
    from ..pipeline.core import run_job
    from ..pipeline.dataset import BuildSettings, DatasetJob, find_build_inputs

    settings = BuildSettings.with_splits(
        splits, split_files, official_split=official_split, sequence_from=sequence_from, seed=seed,
        sparse_format=sparse_format, store=store, source=source, params=params,
        geometry=store_geometry,
    )  # fmt: skip
    found = find_build_inputs(
        settings, rgb=rgb, sparse=sparse, gt=gt, confidence=confidence, calib=calib
    )
    job = DatasetJob.for_inputs(settings, found)
    summary = run_job(job, found.frames, out_dir, batch=batch, inputs=found.roots, desc="dataset")
    _summary(summary, as_json, out_dir)


def _summary(summary, as_json, out_dir) -> None:
    """A build's summary; its stage timings (``stage_seconds``) and what each split list
    matched, drive by drive (``split_lists``), with ``--json`` only."""
    emit_summary(summary, as_json=as_json, title=f"dataset written to {out_dir}",
                 details=("stage_seconds", "split_lists", "gt.methods", "gt.removed", "gt.icp"))  # fmt: skip


@dataset.command("nuscenes")
@click.argument("root", type=click.Path(exists=True, file_okay=False, path_type=Path))
@output_dir_option(help="Dataset folder (stages in DATASET/.sources/).")
@nuscenes_version_option
@camera_option(default="CAM_FRONT", help="Camera channel.")
@sensor_option(help="Sparse input: RADAR_* or LIDAR_TOP.")
@sweeps_option(default=5, help="Sweeps of --sensor merged per sample.")
@resize_option
@crop_option(help="Then crop to W x H pixels at (LEFT, TOP), e.g. 800x350+0+100.")
@click.option(
    "--gt-sensor", default="LIDAR_TOP", show_default=True, metavar="CHANNEL|none",
    help="Ground truth: the projection of this sensor (none: no ground truth).",
)  # fmt: skip
@click.option(
    "--gt-sweeps", type=click.IntRange(min=1), default=1, show_default=True,
    help="Sweeps of the ground-truth sensor merged.",
)  # fmt: skip
@filter_occluded_option
@click.option("--jbf", is_flag=True, help="Expand the radar with jbf-expand (confidence stored).")
@click.option("--scenes", default=None, metavar="A,B,...", help="Only these scene names.")
@click.option(
    "--night", type=click.Choice(["any", "only", "exclude"]), default="any", show_default=True,
    help="Scenes by their description: all, only night ones, or only day ones.",
)  # fmt: skip
@splits_option(dataset="nuscenes")
@split_file_option(help="Scene list (one scene name per line); repeat per split. The split "
                    "name comes from NAME= or the file name (train/val/test).")  # fmt: skip
@seed_option(help="Seed of the split assignment.")
@cameras_option(help="Several cameras, one sample per key frame and camera, ids "
                "<scene>/<channel>/<token>: all, or channels (CAM_FRONT,CAM_BACK,...).")  # fmt: skip
@store_geometry_option
@store_points_option
@batch_options
def nuscenes(root, out_dir, nuscenes_version, camera, sensor, sweeps, resize, crop, gt_sensor,
             gt_sweeps, filter_occluded, jbf, scenes, night, official_split, splits, split_files,
             seed, cameras, store_geometry, store_points, batch,
             as_json):  # fmt: skip
    """nuScenes samples to a dataset: camera image, radar (or LiDAR) input, LiDAR truth.

    Per sample: the camera image, resized and cropped with its intrinsics adjusted, the
    sensor's sweeps projected into it (devkit filters; radar with its own ego pose), optionally
    expanded by the joint bilateral filter, and LIDAR_TOP projected as ground truth
    (--gt-sweeps N merged, --filter-occluded: without the points the camera cannot see; each
    row records its gt_method). Samples are frames of their scene, and splits go by scene:
    fractions over scenes (--splits), the official scene lists (--split official, --split
    mini) or your own (--split-file).

    \b
    Example (the radar paper's setting: 800x450, top 100 rows cut):
      sparsetools dataset nuscenes /data/nuscenes -o out/nus_radar --sweeps 5 \\
          --resize 0.5 --crop 800x350+0+100 --jbf --split official
    """
    from ..pipeline.dataset.cameras import parse_cameras
    from ..pipeline.dataset.roots import NUSCENES_CAMERAS, build_nuscenes_dataset

    if cameras is not None and camera != "CAM_FRONT":
        raise click.UsageError("give --camera or --cameras, not both")
    rig = parse_cameras(cameras, NUSCENES_CAMERAS, option="--cameras") or None
    summary = build_nuscenes_dataset(
        root, out_dir, version=nuscenes_version, camera=camera, sensor=sensor, sweeps=sweeps,
        resize=resize, crop=crop, gt_sensor=None if gt_sensor.lower() == "none" else gt_sensor,
        gt_sweeps=gt_sweeps, filter_occluded=filter_occluded, jbf=jbf,
        scenes=tuple(s.strip() for s in scenes.split(",")) if scenes else None,
        night=night, split=splits, split_files=split_files or None,
        official_split=official_split, seed=seed, cameras=rig, geometry=store_geometry,
        store_points=store_points, batch=batch,
    )  # fmt: skip
    _summary(summary, as_json, out_dir)


@dataset.command("kitti-raw")
@click.argument("root", type=click.Path(exists=True, file_okay=False, path_type=Path))
@output_dir_option(help="Dataset folder (stages in DATASET/.sources/).")
@click.option(
    "--beams", type=click.IntRange(min=1, max=64), default=4, show_default=True,
    help="Beams of the input (the full scan is the ground truth); 64: the full scan.",
)  # fmt: skip
@click.option(
    "--gt-method", "gt_method", type=click.Choice(["scan", "accumulated"]), default="scan",
    show_default=True,
    help="Ground truth: the frame's scan projected, or KITTI's recipe: frames t-K..t+K merged "
    "(oxts poses, else ICP), occlusion and moving-object tests, stereo check.",
)  # fmt: skip
@filter_occluded_option
@click.option(
    "--gt-neighbours", type=int, default=5, show_default=True, metavar="K",
    help="--gt-method accumulated: merge frames t-K..t+K of the drive (0..100; KITTI: 5).",
)  # fmt: skip
@click.option(
    "--stereo-check/--no-stereo-check", default=None,
    help="--gt-method accumulated: drop points that disagree with SGBM stereo of image_02/image_03 "
    "by more than 3 px and 5 % of disparity [default: on for frames whose image_03 exists].",
)  # fmt: skip
@icp_min_range_option
@resize_to_option
@splits_option(dataset="kitti")
@split_file_option(
    help="Your own split lists, Eigen form (<date>/<drive> <frame> <l|r>); repeat per split."
)
@seed_option(help="Seed of the split assignment.")
@cameras_option(help="Several cameras, one sample per frame and camera, ids "
                "<drive>/<camera>/<frame>: e.g. image_02,image_03 (default: image_02 alone, "
                "ids <drive>/<frame>).")  # fmt: skip
@store_geometry_option
@store_points_option
@store_option
@batch_options
def kitti_raw(root, out_dir, beams, gt_method, filter_occluded, gt_neighbours, stereo_check,
              icp_min_range, resize_to, official_split, splits, split_files, seed, cameras,
              store_geometry, store_points, store, batch, as_json):  # fmt: skip
    """KITTI raw drives to a dataset: image, N-beam projected LiDAR, LiDAR ground truth.

    ROOT is a drive, a date folder (all its drives) or a root of dates. Frames are keyed by
    drive, so frame names that repeat across drives stay distinct; splits go by drive, by the
    official lists (--split eigen: Eigen-Zhou train / val, Eigen test) or by your own lists
    (--split-file). The summary reports the listed frames the tree lacks, drive by drive.
    Ground truth: the full scan (--gt-method scan; --filter-occluded: without its see-through
    points), or accumulated as KITTI's annotated maps (--gt-method accumulated, which always
    filters occluded points); each row records its gt_method. --resize-to WxH: every image
    resized to exactly that size (intrinsics scaled per axis), the maps projected at it.

    \b
    Examples:
      sparsetools dataset kitti-raw /data/kitti_raw -o out/kitti4 --beams 4 --split eigen
      sparsetools dataset kitti-raw /data/kitti_raw -o out/kitti4 --beams 4 \\
          --split-file train=my_train_files.txt --split-file test=my_test_files.txt
      sparsetools dataset kitti-raw /data/kitti_raw/2011_09_26 -o out/kitti_acc \\
          --gt-method accumulated --icp-min-range 20
      sparsetools dataset kitti-raw /data/kitti_raw -o out/effis4 --beams 4 --split eigen \\
          --resize-to 640x192
      sparsetools dataset kitti-raw /data/kitti_raw -o out/kitti16 --beams 16 --store reference
    """
    from ..pipeline.dataset.cameras import parse_cameras
    from ..pipeline.dataset.roots import build_kitti_raw_dataset

    names = ("image_00", "image_01", "image_02", "image_03")
    rig = tuple(int(c[-1]) for c in parse_cameras(cameras, names, option="--cameras"))
    summary = build_kitti_raw_dataset(
        root, out_dir, beams=None if beams == 64 else beams, gt=gt_method,
        filter_occluded=filter_occluded, gt_neighbours=gt_neighbours, stereo_check=stereo_check,
        icp_min_range=icp_min_range, resize_to=resize_to, split=splits,
        split_files=split_files or None, official_split=official_split, seed=seed,
        cameras=rig or None, geometry=store_geometry, store_points=store_points, store=store,
        batch=batch,
    )  # fmt: skip
    _summary(summary, as_json, out_dir)


@dataset.command("kitti-dc")
@click.argument("root", type=click.Path(exists=True, file_okay=False, path_type=Path))
@output_dir_option(help="Dataset folder.")
@click.option(
    "--raw", type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="KITTI raw tree holding the images (<date>/<drive>/image_02/data/).",
)  # fmt: skip
@click.option(
    "--sparse-name", default=None, metavar="NAME",
    help="proj_depth map set of the input [default: velodyne_raw].",
)  # fmt: skip
@click.option(
    "--gt-name", default=None, metavar="NAME",
    help="proj_depth map set of the ground truth [default: groundtruth].",
)  # fmt: skip
@click.option(
    "--selection", is_flag=True,
    help="Build the 1,000-frame depth_selection/val_selection_cropped set instead (its own "
    "images and intrinsics).",
)  # fmt: skip
@store_option
@batch_options
def kitti_dc(root, out_dir, raw, sparse_name, gt_name, selection, store, batch, as_json):
    """A KITTI depth-completion root to a dataset, split as the tree splits it (train / val).

    ROOT holds data_depth_velodyne/ and data_depth_annotated/ ({train,val}/<drive>/proj_depth/
    <name>/image_02/). Frames without ground truth (the first and last 5 of each drive) are
    counted in the summary's unmatched line.

    \b
    Examples:
      sparsetools dataset kitti-dc /data/kitti_dc --raw /data/kitti_raw -o out/dc
      sparsetools dataset kitti-dc /data/kitti_dc --raw /data/kitti_raw -o out/dc4 \\
          --sparse-name velodyne_raw_4beam
      sparsetools dataset kitti-dc /data/kitti_dc --selection -o out/dc_selection
    """
    from ..pipeline.dataset.roots import build_kitti_dc_dataset

    if not selection and raw is None:
        raise click.UsageError("--raw (the KITTI raw images) is needed, or use --selection")
    summary = build_kitti_dc_dataset(
        root, out_dir, raw=raw, sparse_name=sparse_name, gt_name=gt_name, selection=selection,
        store=store, batch=batch,
    )  # fmt: skip
    _summary(summary, as_json, out_dir)


@dataset.command("export")
@click.argument("maps", type=click.Path(exists=True, file_okay=False, path_type=Path))
@output_dir_option(help="Root of the layout written.")
@layout_option(
    ("kitti-dc", "kitti-selection", "monodepth2-gt"),
    default="kitti-dc",
    help="kitti-dc: {train,val}/<drive>/proj_depth/<name>/image_02/<frame>.png; kitti-selection:"
    " <name>/<drive>_<name>_<frame>_image_02.png (val_selection_cropped naming); monodepth2-gt:"
    " OUT/gt_depths.npz for the lines of --split-file, MAPS being a KITTI raw tree.",
)
@click.option(
    "--name",
    default="velodyne_raw",
    show_default=True,
    help="Map set name (e.g. velodyne_raw_4beam).",
)
@click.option(
    "--split-from", type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="A depth-completion tree whose train/val folders give each drive's split.",
)  # fmt: skip
@split_option("default_split", help="Split of drives --split-from lacks.")
@split_file_option(
    help="--layout monodepth2-gt: the split's test_files.txt (<date>/<drive> <frame> [l|r] "
    "lines); one map per line, in its order."
)
@click.option(
    "--depth-value", type=click.Choice(["velodyne-x", "camera-z"]), default="velodyne-x",
    show_default=True,
    help="--layout monodepth2-gt: what a pixel holds: the point's Velodyne x (monodepth2's "
    "Eigen ground truth, generate_depth_map(vel_depth=True)) or its camera z.",
)  # fmt: skip
@batch_options
def export(maps, out_dir, layout, name, split_from, default_split, split_files, depth_value,
           batch, as_json):  # fmt: skip
    """Write depth maps of KITTI drives in the official depth-completion layout, or the
    ground truth monodepth2 evaluates with.

    MAPS holds maps per drive (<drive>/<frame>.png: a project, beams+project, jbf-expand or
    densify output for a KITTI raw root); they are copied byte for byte, so a 4-beam or radar
    variant of the benchmark drops into code that reads only the official layout.

    With --layout monodepth2-gt, MAPS is a KITTI raw tree and OUT/gt_depths.npz holds one
    float32 depth map (metres, 0 = none) per line of --split-file, as monodepth2's
    export_gt_depth.py --split eigen writes it: the Velodyne scan projected into image_02
    (x < 0 dropped, -1 px offset, nearest value per pixel), storing the Velodyne x. A line
    whose scan is missing is refused (monodepth2 pairs maps with predictions by line).

    \b
    Examples:
      sparsetools dataset export out/depth4 -o out/kitti_dc4 --name velodyne_raw_4beam \\
          --split-from /data/kitti_dc/data_depth_velodyne
      sparsetools dataset export /data/kitti_raw -o out/eigen --layout monodepth2-gt \\
          --split-file eigen:test
    """
    if layout == "monodepth2-gt":
        _export_monodepth2_gt(maps, out_dir, split_files, split_from, depth_value, batch, as_json)
        return
    if split_files:
        raise click.UsageError("--split-file is for --layout monodepth2-gt")
    from ..io.sources import depth_frames
    from ..io.sources.kitti import drive_splits
    from ..pipeline import run_job
    from ..pipeline.export import ExportJob, ExportSettings

    splits = drive_splits(split_from) if split_from is not None else {}
    job = ExportJob(ExportSettings(layout=layout, name=name, splits=splits), default_split)
    frames = depth_frames([maps], role="depth", option="MAPS")
    summary = run_job(job, frames, out_dir, batch=batch, inputs=[maps])
    emit_summary(summary, as_json=as_json, title=f"maps exported to {out_dir}")


def _export_monodepth2_gt(root, out_dir, split_files, split_from, depth_value, batch, as_json):
    """``export --layout monodepth2-gt``: one archive, not per-frame work (no run_job)."""
    from ..pipeline.monodepth2_gt import export_monodepth2_gt

    if len(split_files) != 1:
        raise click.UsageError("--layout monodepth2-gt needs one --split-file FILE (or eigen:test)")
    split_file = split_files[0][1] if isinstance(split_files[0], tuple) else split_files[0]
    if split_from is not None:
        raise click.UsageError("--split-from is for --layout kitti-dc")
    result = export_monodepth2_gt(
        root, split_file, out_dir, value=depth_value, overwrite=batch.overwrite,
        progress=batch.show_progress,
    )  # fmt: skip
    emit_summary(result, as_json=as_json, title=f"monodepth2 ground truth written to {out_dir}")


@dataset.command("info")
@click.argument("dataset_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@root_option
@json_option(help="Print the information as JSON.")
@quiet_debug_options
def info(dataset_dir, roots, as_json):
    """Counts per split, image sizes, density statistics, file sizes, schema version.

    Sizes count what is on disk in the dataset folder (staged sources in .sources/ too) and,
    apart, the images a --store reference dataset keeps in place.

    \b
    Example:
      sparsetools dataset info out/ds --json
    """
    from ..pipeline.dataset import dataset_info

    d = dataset_info(dataset_dir, roots=roots)
    click.echo(json.dumps(d.to_dict(), indent=1) if as_json else d.format())


@dataset.command("verify")
@click.argument("dataset_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--no-hash", is_flag=True, help="Skip the SHA-256 comparison (faster).")
@threads_option(help="Threads reading and decoding files.")
@deprecated("--workers", "--threads", command="dataset verify", dest="threads", metavar="N")
@root_option
@json_option(help="Print the report as JSON.")
@quiet_debug_options
def verify(dataset_dir, no_hash, threads, roots, as_json):
    """Check every file: present, decodable, sizes consistent, SHA-256 matching the manifest.

    A --store reference dataset's images are checked where they are (--root NAME=PATH when
    the tree moved): missing, or changed since the build (size, modification time, hash).
    Exits with status 1 and lists the problems when any is found.

    \b
    Examples:
      sparsetools dataset verify out/ds --threads 4
      sparsetools dataset verify out/kitti4_ref --root kitti=/mnt/new/kitti_raw
    """
    from ..pipeline.dataset import verify_dataset

    report = verify_dataset(dataset_dir, check_hashes=not no_hash, threads=threads, roots=roots)
    click.echo(json.dumps(report.to_dict(), indent=1) if as_json else report.format())
    if not report.ok:
        raise click.ClickException(f"{len(report.problems)} problem(s) found in {dataset_dir}")


@dataset.command("pack")
@click.argument("dataset_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@output_dir_option(
    help="The packed dataset (created; refused if it holds what pack did not write)."
)
@root_option
@batch_options
def pack(dataset_dir, out_dir, roots, batch, as_json):
    """Make a self-contained copy of a dataset whose images are referenced in place.

    Every referenced image is copied in (checked against the size and SHA-256 the manifest
    recorded; a changed one is refused), with the sample's other files and the Parquet parts;
    the manifest is rewritten as --store copy writes it. --root NAME=PATH when a tree moved.

    \b
    Examples:
      sparsetools dataset kitti-raw /data/kitti_raw -o out/kitti4 --beams 4 --store reference
      sparsetools dataset pack out/kitti4 -o out/kitti4_packed
      sparsetools dataset pack out/kitti4 -o out/kitti4_packed --root kitti=/mnt/kitti_raw
    """
    from ..pipeline.core import run_job
    from ..pipeline.dataset.pack import pack_plan

    job, frames, inputs = pack_plan(dataset_dir, roots=roots)
    summary = run_job(job, frames, out_dir, batch=batch, inputs=inputs, desc="pack")
    emit_summary(summary, as_json=as_json, title=f"packed dataset written to {out_dir}")


@dataset.command("report")
@click.argument("dataset_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@output_dir_option(
    file=True,
    help="The page (.html), one self-contained file: pictures embedded, no link outside it. "
    "Refused if it exists and was not written by dataset report, unless --overwrite.",
)
@click.option(
    "--eval", "eval_path", type=click.Path(exists=True, path_type=Path), metavar="RUN|FILE",
    help="Per-image metrics of a trained model, worst first: a train run folder (its "
    "eval_*.json of this dataset) or a results file of `sparsetools eval`.",
)  # fmt: skip
@click.option(
    "--thumbnails", type=click.IntRange(min=0), default=4, show_default=True, metavar="N",
    help="Thumbnails per group and split: the N frames of lowest density, the N of highest, "
    "N spread over the split (0: none).",
)  # fmt: skip
@threads_option(help="Threads of the verify run.")
@overwrite_option(help="Replace a page that dataset report did not write, or wrote otherwise.")
@json_option(help="Print the summary as JSON.")
@quiet_debug_options
def report(dataset_dir, out_dir, eval_path, thumbnails, threads, overwrite, as_json):
    """One HTML page showing the whole dataset: counts, histograms, thumbnails, checks.

    Per split: the counts of `dataset info`, sequences, sources and the recorded generation
    parameters; histograms of density and depth (matplotlib: pip install 'sparsetools[viz]');
    thumbnails of the frames of lowest and highest density (sparse depth over the image); the
    checks of `dataset verify` and their outcome; with --eval, a model's per-image metrics,
    worst frames first. The page is rewritten only when the manifest or the eval results
    change.

    \b
    Examples:
      sparsetools dataset report out/ds -o out/ds_report.html
      sparsetools dataset report out/ds -o out/ds_report.html --eval out/run --thumbnails 6
    """
    import dataclasses

    from ..pipeline.dataset.report import write_dataset_report

    s = write_dataset_report(dataset_dir, out_dir, thumbnails=thumbnails, eval_path=eval_path,
                             threads=threads, overwrite=overwrite)  # fmt: skip
    if as_json:
        click.echo(json.dumps(dataclasses.asdict(s), indent=1))
    elif s.status == "up to date":
        click.echo(f"{s.path} is up to date")
    else:
        verdict = "no problem" if not s.problems else f"{s.problems} problem(s) (listed in it)"
        click.echo(
            f"{s.path} written: {s.samples} sample(s) in {s.splits} split(s), {s.thumbnails} "
            f"thumbnail(s), {s.eval_images} evaluated image(s); verify: {verdict} "
            f"({s.bytes / 1024:.0f} KB)"
        )
