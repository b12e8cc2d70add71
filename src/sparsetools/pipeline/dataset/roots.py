"""From a dataset root to a training dataset in one command: nuScenes, KITTI raw, KITTI depth
completion.

Each route prepares what the dataset needs in ``DATASET/.sources/<stage>/`` (camera images at
the maps' resolution, projected radar / LiDAR maps, beams, a JBF expansion), every stage an
ordinary sparsetools output folder with its own record, so a rerun redoes only what changed,
then calls :func:`~sparsetools.pipeline.dataset.build.build_dataset` on them. Splits go by
sequence: the nuScenes scene, the KITTI drive (or the tree's own train/val).
"""

from __future__ import annotations

import logging
import os
from dataclasses import replace
from pathlib import Path

from ...errors import FormatError, ParameterError, UsageError
from ..batch import Batch, RunSummary
from ..core import run_job
from .build import SOURCES_DIR, BuildSettings, DatasetJob, build_dataset, find_build_inputs
from .official_splits import check_scene_list
from .splits import split_list_of

__all__ = [
    "build_kitti_dc_dataset",
    "build_kitti_raw_dataset",
    "build_nuscenes_dataset",
    "sweeps_summary",
]

log = logging.getLogger(__name__)


#: How messages name what each route records in the dataset's ``params``: the route's own
#: options (a refusal says ``--sweeps 5, not 3``, not ``--params sweeps 5, not 3``).
NUSCENES_OPTIONS = {
    "route": "dataset", "version": "--nuscenes-version", "camera": "--camera",
    "sensor": "--sensor", "sweeps": "--sweeps", "resize": "--resize", "crop": "--crop",
    "gt": "--gt-sensor", "jbf": "--jbf",
}  # fmt: skip
KITTI_RAW_OPTIONS = {"route": "dataset", "beams": "--beams"}
KITTI_DC_OPTIONS = {"route": "dataset", "sparse": "--sparse-name", "selection": "--selection"}


def _stage(out: Path, name: str) -> Path:
    return Path(out) / SOURCES_DIR / name


def build_nuscenes_dataset(
    root: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    version: str = "v1.0-mini",
    camera: str = "CAM_FRONT",
    sensor: str = "RADAR_FRONT",
    sweeps: int = 5,
    resize: float | None = None,
    crop: tuple[int, int, int, int] | None = None,
    gt_sensor: str | None = "LIDAR_TOP",
    gt_sweeps: int = 1,
    jbf: bool = False,
    scenes: tuple[str, ...] | None = None,
    night: str = "any",
    split: str | None = None,
    split_files=None,
    official_split: str | None = None,
    seed: int = 0,
    sparse_format: str = "both",
    batch: Batch | None = None,
) -> RunSummary:
    """nuScenes samples -> dataset: one camera's image (resized / cropped, with its adjusted
    intrinsics), the sparse input from ``sensor`` (radar: ``sweeps`` merged, devkit filters;
    optionally expanded by the JBF, whose confidence map is stored too), ground truth from
    ``gt_sensor`` (``None``: none), splits by scene: fractions (``split``), scene lists
    (``split_files``, one scene name per line) or an ``official_split`` (``official``, ``mini``).

    The radar paper's setting: ``camera="CAM_FRONT", resize=0.5, crop=(100, 0, 350, 800)``
    (``--crop 800x350+0+100``: 1600x900 -> 800x450, the top 100 rows cut).

    ``sweeps`` is what is asked for; a sample whose chain of earlier sweeps is shorter merges
    fewer. Each manifest row records what its sample merged (``generation_params["sample"]``:
    ``sweeps_merged``, with ground truth ``gt_sweeps_merged``); the summary's ``sweeps`` gives
    the requested count and the merged minimum, maximum and mean.

    Raises
    ------
    UsageError
        ``sensor`` is also ``gt_sensor`` (the input would be the ground truth itself).
    """
    from ...io.sources import nuscenes_frames
    from ..camera_images import CameraImageJob, CameraImageSettings
    from ..project import ProjectJob, ProjectSettings

    batch = batch or Batch()
    for item in split_files or ():  # scene lists: refused before any work
        check_scene_list(split_list_of(item))
    if jbf and not sensor.upper().startswith("RADAR"):
        raise ParameterError("--jbf expands radar: give a RADAR_* --sensor", param="jbf")
    if gt_sensor is not None and sensor.upper() == gt_sensor.upper():
        raise UsageError(
            f"{sensor} is also the ground truth (--gt-sensor {gt_sensor}): the input would equal "
            "the truth; give another --sensor, or --gt-sensor another channel or none",
            param="sensor",
        )
    out = Path(out_dir)
    common = {"version": version, "camera": camera, "scenes": scenes, "night": night}
    frames = nuscenes_frames(root, sensor=sensor, sweeps=sweeps, **common)
    gt_merged = {}
    if gt_sensor is not None:
        gt_frames = nuscenes_frames(root, sensor=gt_sensor, sweeps=gt_sweeps, **common)
        have = {f.key for f in gt_frames}
        lost = [f for f in frames if f.key not in have]
        if lost:
            log.warning("%d sample(s) lack %s and are left out", len(lost), gt_sensor)
        frames = [f for f in frames if f.key in have]
        gt_frames = [f for f in gt_frames if f.key in {f.key for f in frames}]
        gt_merged = {str(f.key): 1 + len(f.sweeps) for f in gt_frames}
    # What was merged, per sample: a sample near the start of its chain has fewer sweeps.
    merged = {str(f.key): 1 + len(f.sweeps) for f in frames}
    sample_params = {
        k: (("sweeps_merged", n),) + ((("gt_sweeps_merged", gt_merged[k]),) if gt_merged else ())
        for k, n in merged.items()
    }
    images = CameraImageJob(CameraImageSettings(resize=resize, crop=crop))
    run_job(images, frames, _stage(out, "images"), batch=batch, desc="images")
    project = ProjectJob(ProjectSettings(resize=resize, crop=crop, camera=camera))
    run_job(project, frames, _stage(out, "sparse"), batch=batch, inputs=[root])
    gt = None
    if gt_sensor is not None:
        run_job(project, gt_frames, _stage(out, "gt"), batch=batch, inputs=[root])
        gt = _stage(out, "gt")
    sparse, confidence, source = _stage(out, "sparse"), None, sensor.lower()
    if jbf:
        from ...io.sources import radar_frames
        from ..jbf_expand import JbfJob

        radar = radar_frames([_stage(out, "sparse")], image=_stage(out, "images"),
                             calib=_stage(out, "images") / "calib")  # fmt: skip
        run_job(JbfJob(), radar, _stage(out, "jbf"), batch=batch)
        sparse = confidence = _stage(out, "jbf")
        source = f"{sensor.lower()}-jbf"
    settings = BuildSettings.with_splits(
        split, split_files, official_split=official_split, sparse_format=sparse_format,
        source=source, seed=seed,
        params={
            "route": "nuscenes", "version": version, "camera": camera, "sensor": sensor,
            "sweeps": sweeps, "resize": resize, "crop": list(crop) if crop else None,
            "gt": gt_sensor, "jbf": jbf,
        },
    )  # fmt: skip
    found = find_build_inputs(settings, rgb=_stage(out, "images"), sparse=sparse, gt=gt,
                              confidence=confidence, calib=_stage(out, "images") / "calib")  # fmt: skip
    found = replace(found, frames=[
        replace(x, sample_params=sample_params.get(x.id, ())) for x in found.frames
    ])  # fmt: skip
    job = DatasetJob.for_inputs(settings, found, param_options=NUSCENES_OPTIONS)
    summary = run_job(job, found.frames, out, batch=batch, inputs=found.roots, desc="dataset")
    return summary.with_totals({"sweeps": sweeps_summary(sweeps, merged.values())})


def sweeps_summary(requested: int, merged) -> dict:
    """``{"requested", "merged_min", "merged_max", "merged_mean"}`` over the samples; a
    warning when some samples merged fewer sweeps than requested (their chain is shorter)."""
    merged = list(merged)
    if not merged:
        return {"requested": requested}
    short = sum(1 for n in merged if n < requested)
    if short:
        log.warning(
            "%d of %d sample(s) merged fewer than %d sweeps (as few as %d): their chain of "
            "earlier sweeps is shorter; each row records its own (sweeps_merged)",
            short, len(merged), requested, min(merged),
        )  # fmt: skip
    return {
        "requested": requested,
        "merged_min": min(merged),
        "merged_max": max(merged),
        "merged_mean": round(sum(merged) / len(merged), 3),
    }


def build_kitti_raw_dataset(
    root: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    beams: int | None = 4,
    camera: int = 2,
    split: str | None = None,
    split_files=None,
    official_split: str | None = None,
    seed: int = 0,
    sparse_format: str = "both",
    batch: Batch | None = None,
) -> RunSummary:
    """KITTI raw drives (a drive, a date folder or a root of dates) -> dataset: the camera
    image, the projected scan kept at ``beams`` beams as input (``None``: the full scan), the
    full-scan projection as ground truth; splits by drive, by split files, or by an
    ``official_split`` (``eigen``, ``eigen_full``, ``eigen_benchmark``, ``odom``)."""
    from ...io.sources import Frame, cloud_frames, is_kitti_raw, kitti_raw_index
    from ..beams import BeamsJob, BeamsSettings
    from ..project import ProjectJob, ProjectSettings

    batch = batch or Batch()
    out = Path(out_dir)
    if not is_kitti_raw(root):
        raise FormatError(
            f"{root}: not a KITTI raw drive, date folder or root (no <drive>/velodyne_points/"
            "data/ or image_0N/data/ with the calibration pair)"
        )
    frames = cloud_frames([root], camera=camera)
    project = ProjectJob(ProjectSettings(camera=camera))
    run_job(project, frames, _stage(out, "gt"), batch=batch, inputs=[root])
    sparse = _stage(out, "gt")
    if beams is not None:
        run_job(BeamsJob(BeamsSettings(n=(beams,))), frames, _stage(out, f"beams{beams}"),
                batch=batch, inputs=[root])  # fmt: skip
        raw = kitti_raw_index(root, what="cloud", camera=camera)
        beam_frames = [
            Frame(key=f.key, cloud=f.key.path(_stage(out, f"beams{beams}"), ".bin"),
                  calib=raw.calib[f.key], image=f.image)
            for f in frames
        ]  # fmt: skip
        sparse = _stage(out, f"sparse{beams}")
        run_job(project, beam_frames, sparse, batch=batch)
    return build_dataset(
        out,
        rgb=root,
        sparse=sparse,
        gt=_stage(out, "gt"),
        split=split,
        split_files=split_files,
        official_split=official_split,
        seed=seed,
        sparse_format=sparse_format,
        source="lidar" if beams is None else f"lidar-{beams}beam",
        camera=camera,
        params={"route": "kitti-raw", "beams": beams},
        param_options=KITTI_RAW_OPTIONS,
        batch=batch,
    )


def build_kitti_dc_dataset(
    root: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    raw: str | os.PathLike | None = None,
    sparse_name: str | None = None,
    gt_name: str | None = None,
    selection: bool = False,
    camera: int = 2,
    sparse_format: str = "both",
    batch: Batch | None = None,
) -> RunSummary:
    """A KITTI depth-completion root -> dataset, split as the tree splits it.

    ``root`` holds ``data_depth_velodyne/`` and ``data_depth_annotated/`` (or is one of them
    with ``{train,val}/<drive>/proj_depth/``); images come from the KITTI raw tree ``raw``.
    ``selection``: the 1,000-frame ``depth_selection/val_selection_cropped`` set instead, with
    its own images and intrinsics (split ``val_selection``). Frames without ground truth (the
    first and last 5 of each drive) are counted in the summary's ``unmatched``.
    """
    root = Path(root)
    if selection:
        sel = root / "depth_selection" / "val_selection_cropped"
        sel = sel if sel.is_dir() else root
        return build_dataset(
            out_dir, rgb=sel, sparse=sel, gt=sel, calib=sel, split="tree",
            sparse_format=sparse_format, source="lidar", camera=camera,
            params={"route": "kitti-dc", "selection": True}, param_options=KITTI_DC_OPTIONS,
            batch=batch,
        )  # fmt: skip
    from ...io.sources.kitti import is_kitti_depth_completion

    if raw is None:
        raise ParameterError("give the KITTI raw tree holding the images", param="raw")
    sparse = root / "data_depth_velodyne" if (root / "data_depth_velodyne").is_dir() else root
    if not is_kitti_depth_completion(sparse):
        raise FormatError(
            f"{root}: not a KITTI depth-completion tree (no data_depth_velodyne/ nor "
            "{train,val}/<drive>/proj_depth/)"
        )
    gt = root / "data_depth_annotated" if (root / "data_depth_annotated").is_dir() else root
    return build_dataset(
        out_dir, rgb=raw, sparse=sparse, gt=gt, split="tree", sparse_name=sparse_name,
        gt_name=gt_name, sparse_format=sparse_format, camera=camera,
        source=f"lidar-{sparse_name}" if sparse_name else "lidar",
        params={"route": "kitti-dc", "sparse": sparse_name or "velodyne_raw"},
        param_options=KITTI_DC_OPTIONS, batch=batch,
    )  # fmt: skip
