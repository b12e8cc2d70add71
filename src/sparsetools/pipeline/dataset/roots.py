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
from dataclasses import dataclass, replace
from pathlib import Path

from ...errors import FormatError, ParameterError, UsageError
from ..batch import Batch, RunSummary
from ..core import run_job
from .build import BuildSettings, DatasetJob, build_dataset, find_build_inputs
from .cameras import CameraInputs, camera_id, find_rig_inputs
from .kitti_raw_stages import (
    check_kitti_raw_gt,
    kitti_raw_stages,
    resized_images,
    stage_dir,
)
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
    "gt": "--gt-sensor", "jbf": "--jbf", "gt_filter_occluded": "--filter-occluded",
    "cameras": "--cameras",
}  # fmt: skip
KITTI_RAW_OPTIONS = {
    "route": "dataset", "beams": "--beams", "gt": "--gt-method", "gt_neighbours": "--gt-neighbours",
    "stereo_check": "--stereo-check/--no-stereo-check", "icp_min_range": "--icp-min-range",
    "gt_filter_occluded": "--filter-occluded", "resize_to": "--resize-to", "cameras": "--cameras",
}  # fmt: skip
#: nuScenes camera channels, in the devkit's order (``--cameras all``).
NUSCENES_CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK",
                    "CAM_BACK_LEFT", "CAM_BACK_RIGHT")  # fmt: skip
KITTI_DC_OPTIONS = {"route": "dataset", "sparse": "--sparse-name", "selection": "--selection"}


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
    filter_occluded: bool = False,
    jbf: bool = False,
    scenes: tuple[str, ...] | None = None,
    night: str = "any",
    split: str | None = None,
    split_files=None,
    official_split: str | None = None,
    seed: int = 0,
    sparse_format: str = "both",
    cameras: tuple[str, ...] | None = None,
    geometry: bool = False,
    store_points: bool = False,
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
    ``sweeps_merged``, with ground truth ``gt_sweeps_merged`` and ``gt_method``, e.g.
    ``sweeps(3)+occlusion``); the summary's ``sweeps`` gives the requested count and the
    merged minimum, maximum and mean. ``filter_occluded``: the ground truth without the points
    the camera cannot see (:func:`sparsetools.ops.occlusion.filter_occluded` on the merged
    sweeps' map).

    ``cameras``: several channels (``--cameras all`` or ``CAM_FRONT,CAM_BACK,...``), one
    sample per key frame and camera, ids ``<scene>/<channel>/<sample token>`` (:mod:`.cameras`);
    None or one: ``camera``, ids ``<scene>/<sample token>`` as before. ``geometry``: the
    geometry columns (``K``, ``T_cam_lidar``: the sensor's points to the camera at its time,
    ``T_ego_cam``, ``T_world_ego`` at the camera's time); ``store_points``: the sensor's
    points too, sweeps merged as the sparse input merges them (``points/part-*.parquet``).

    Raises
    ------
    UsageError
        ``sensor`` is also ``gt_sensor`` (the input would be the ground truth itself), or
        ``filter_occluded`` without ground truth.
    """
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
    if filter_occluded and gt_sensor is None:
        raise UsageError("--filter-occluded filters the ground truth: not with --gt-sensor none",
                         param="filter_occluded")  # fmt: skip
    out = Path(out_dir)
    cams = tuple(cameras) if cameras else (camera,)
    rig = len(cams) > 1
    staged = {
        cam: _nuscenes_stages(
            root, out, camera=cam, suffix=f"_{cam}" if rig else "", version=version,
            sensor=sensor, sweeps=sweeps, resize=resize, crop=crop, gt_sensor=gt_sensor,
            gt_sweeps=gt_sweeps, filter_occluded=filter_occluded, jbf=jbf, scenes=scenes,
            night=night, batch=batch,
        )
        for cam in cams
    }  # fmt: skip
    source = f"{sensor.lower()}-jbf" if jbf else sensor.lower()
    settings = BuildSettings.with_splits(
        split, split_files, official_split=official_split, sparse_format=sparse_format,
        source=source, seed=seed, geometry=geometry, store_points=store_points,
        params={
            "route": "nuscenes", "version": version, "camera": camera, "sensor": sensor,
            "sweeps": sweeps, "resize": resize, "crop": list(crop) if crop else None,
            "gt": gt_sensor, "jbf": jbf,
            # recorded only when set, so datasets of earlier versions resume
            **({"gt_filter_occluded": True} if filter_occluded else {}),
            **({"cameras": list(cams)} if rig else {}),
        },
    )  # fmt: skip
    poses = {}
    if settings.geometry:
        from ...io.sources.nuscenes import nuscenes_camera_poses

        poses = {cam: nuscenes_camera_poses(root, version=version, camera=cam) for cam in cams}

    def extra(cam) -> tuple:
        out = ()
        if poses:
            p = poses[cam]
            out += (("T_ego_cam", {k: v[0] for k, v in p.items()}),
                    ("T_world_ego", {k: v[1] for k, v in p.items()}))  # fmt: skip
        if store_points:
            out += (("cloud", staged[cam].clouds), ("sweeps", staged[cam].sweeps))
        return out

    inputs = [
        CameraInputs(cam, rgb=st.images, sparse=st.sparse, gt=st.gt, confidence=st.confidence,
                     calib=st.images / "calib", extra=extra(cam))
        for cam, st in staged.items()
    ]  # fmt: skip
    if rig:
        found = find_rig_inputs(settings, inputs)
        sample_params = {camera_id(k, cam): v for cam, st in staged.items()
                         for k, v in st.sample_params.items()}  # fmt: skip
    else:
        c = inputs[0]
        found = find_build_inputs(settings, rgb=c.rgb, sparse=c.sparse, gt=c.gt,
                                  confidence=c.confidence, calib=c.calib)  # fmt: skip
        fields = dict(c.extra)
        found = replace(found, frames=[
            replace(x, **{name: v[x.id] for name, v in fields.items() if x.id in v})
            for x in found.frames
        ])  # fmt: skip
        sample_params = staged[cams[0]].sample_params
    found = replace(found, frames=[
        replace(x, sample_params=sample_params.get(x.id, ())) for x in found.frames
    ])  # fmt: skip
    job = DatasetJob.for_inputs(settings, found, param_options=NUSCENES_OPTIONS)
    summary = run_job(job, found.frames, out, batch=batch, inputs=found.roots, desc="dataset")
    merged = [n for st in staged.values() for n in st.merged.values()]
    gt_totals = staged[cams[0]].gt_totals
    if rig and gt_totals:
        gt_totals = {"gt": {"methods": _count(dict(v)["gt_method"]
                                              for v in sample_params.values())}}  # fmt: skip
        if filter_occluded:
            gt_totals["gt"]["occluded_pixels"] = sum(
                st.gt_totals["gt"].get("occluded_pixels", 0) for st in staged.values()
            )
    return summary.with_totals({"sweeps": sweeps_summary(sweeps, merged), **gt_totals})


@dataclass(frozen=True)
class _NuscenesStages:
    """One camera's stages of ``dataset nuscenes``: its folders, per-sample parameters (by
    ``scene/token``), sweeps merged per sample, the ground truth's totals."""

    images: Path
    sparse: Path
    gt: Path | None
    confidence: Path | None
    sample_params: dict
    merged: dict
    gt_totals: dict
    clouds: dict
    sweeps: dict


def _nuscenes_stages(root, out: Path, *, camera, suffix, version, sensor, sweeps, resize, crop,
                     gt_sensor, gt_sweeps, filter_occluded, jbf, scenes, night,
                     batch) -> _NuscenesStages:  # fmt: skip
    from ...io.sources import nuscenes_frames
    from ..camera_images import CameraImageJob, CameraImageSettings
    from ..project import ProjectJob, ProjectSettings

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
    tag = "+occlusion" if filter_occluded else ""
    sample_params = {
        k: (("sweeps_merged", n),) + (
            (("gt_sweeps_merged", gt_merged[k]), ("gt_method", f"sweeps({gt_merged[k]}){tag}"))
            if gt_merged else ()
        )
        for k, n in merged.items()
    }  # fmt: skip
    images_dir = stage_dir(out, "images" + suffix)
    images = CameraImageJob(CameraImageSettings(resize=resize, crop=crop))
    run_job(images, frames, images_dir, batch=batch, desc="images")
    project = ProjectJob(ProjectSettings(resize=resize, crop=crop, camera=camera))
    run_job(project, frames, stage_dir(out, "sparse" + suffix), batch=batch, inputs=[root])
    gt, gt_totals = None, {}
    if gt_sensor is not None:
        gt = stage_dir(out, ("gt_occluded" if filter_occluded else "gt") + suffix)
        gt_job = ProjectJob(replace(project.settings, filter_occluded=filter_occluded))
        done = run_job(gt_job, gt_frames, gt, batch=batch, inputs=[root], desc="gt")
        gt_totals = {"gt": {"methods": _count(dict(sample_params[k])["gt_method"]
                                              for k in gt_merged)}}  # fmt: skip
        if filter_occluded:
            gt_totals["gt"]["occluded_pixels"] = done.totals.get("occluded_pixels", 0)
    sparse, confidence = stage_dir(out, "sparse" + suffix), None
    if jbf:
        from ...io.sources import radar_frames
        from ..jbf_expand import JbfJob

        radar = radar_frames([stage_dir(out, "sparse" + suffix)], image=images_dir,
                             calib=images_dir / "calib")  # fmt: skip
        run_job(JbfJob(), radar, stage_dir(out, "jbf" + suffix), batch=batch)
        sparse = confidence = stage_dir(out, "jbf" + suffix)
    clouds = {str(f.key): str(f.cloud) for f in frames}
    sweeps_of = {str(f.key): tuple(f.sweeps) for f in frames}
    return _NuscenesStages(images_dir, sparse, gt, confidence, sample_params, merged, gt_totals,
                           clouds, sweeps_of)  # fmt: skip


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
    gt: str = "scan",
    filter_occluded: bool = False,
    gt_neighbours: int = 5,
    stereo_check: bool | None = None,
    icp_min_range: float = 0.0,
    resize_to: tuple[int, int] | None = None,
    split: str | None = None,
    split_files=None,
    official_split: str | None = None,
    seed: int = 0,
    sparse_format: str = "both",
    cameras: tuple[int, ...] | None = None,
    geometry: bool = False,
    store_points: bool = False,
    store: str = "copy",
    batch: Batch | None = None,
) -> RunSummary:
    """KITTI raw drives (a drive, a date folder or a root of dates) -> dataset: the camera
    image, the projected scan kept at ``beams`` beams as input (``None``: the full scan), and
    ground truth; splits by drive, by split files, or by an ``official_split`` (``eigen``,
    ``eigen_full``, ``eigen_benchmark``, ``odom``).

    Ground truth (``gt``; each manifest row records its own ``gt_method``,
    :data:`GT_METHOD_DOC`):

    - ``"scan"``: the full scan projected; ``filter_occluded``: without its see-through
      points (:func:`sparsetools.ops.occlusion.filter_occluded`);
    - ``"accumulated"``: KITTI's recipe, the scans of frames t-K..t+K (``gt_neighbours``)
      merged into frame t by :func:`sparsetools.pipeline.accumulate.accumulation_job`, with the
      drive's oxts poses when every drive has them, else ICP (``icp_min_range``), the occlusion
      test on every scan including frame t's own and the consistency (moving-object) test;
      windows clipped at a drive's ends use what they have. Then ``stereo_check``: drop the
      points that disagree with SGBM stereo of image_02 / image_03
      (:mod:`sparsetools.ops.stereo`); None: on for the frames whose image_03 exists.

    ``resize_to`` (width, height): every image resized to exactly this size (OpenCV area
    interpolation when shrinking) with its intrinsics scaled per axis
    (:meth:`~sparsetools.calibration.Calibration.resized_to`), staged in ``.sources/images``
    with per-frame calibrations; the input and the ground truth are projected directly at that
    size with the scaled calibration (no depth map is resized; ``gt="accumulated"`` merges
    its scans at that size and its stereo check matches the pair resized to it, fx scaled).
    monodepth2's KITTI setting is ``(640, 192)``. Without it the images are copied from the tree at their own size.
    ``cameras``: several KITTI cameras (``(2, 3)``: ``--cameras image_02,image_03``), one
    sample per frame and camera, ids ``<drive>/image_0N/<frame>``
    (:mod:`.cameras`); None or one camera: ``camera``, ids ``<drive>/<frame>`` as before.
    ``geometry``: the geometry columns (``K``, ``T_cam_lidar``, ``baseline_m``);
    ``store_points``: the points too (``points/part-*.parquet``).
    ``store``: ``copy`` the images into the dataset, ``link`` (reflinks) or ``reference``:
    leave them in the tree, recorded relative to the root ``kitti`` (``root``).

    Raises
    ------
    UsageError
        ``gt_neighbours`` / ``stereo_check`` / ``icp_min_range`` without ``gt="accumulated"``,
        ``stereo_check`` with another camera than 2.
    FormatError
        ``stereo_check=True`` and a frame without image_03.
    """
    from ...io.sources import is_kitti_raw

    cams = tuple(cameras) if cameras else (camera,)
    for c in cams:
        check_kitti_raw_gt(gt, gt_neighbours, stereo_check, icp_min_range, c)
    if resize_to is not None:
        from ...validate import parse_size

        resize_to = parse_size(resize_to, "--resize-to")
    batch = batch or Batch()
    out = Path(out_dir)
    if not is_kitti_raw(root):
        raise FormatError(
            f"{root}: not a KITTI raw drive, date folder or root (no <drive>/velodyne_points/"
            "data/ or image_0N/data/ with the calibration pair)"
        )
    plain_gt = gt == "scan" and not filter_occluded
    rig = len(cams) > 1
    if rig and resize_to is not None:
        raise UsageError(
            "--resize-to with several --cameras is not supported: build one dataset per camera",
            param="--resize-to",
        )
    if store == "reference" and (rig or resize_to is not None):
        raise UsageError(
            "--store reference leaves the tree's images in place: not with "
            + ("several --cameras" if rig else "--resize-to (the images are resized copies)")
            + "; use --store copy",
            param="--store",
        )
    if rig:  # every camera's images found before any stage runs
        from ...io.sources import index_input

        for c in cams:
            index_input(root, "image", option="--cameras", camera=c)
    staged = {
        c: kitti_raw_stages(
            root, out, camera=c, suffix=f"_image_0{c}" if rig else "", beams=beams, gt=gt,
            filter_occluded=filter_occluded, gt_neighbours=gt_neighbours,
            stereo_check=stereo_check, icp_min_range=icp_min_range, resize_to=resize_to,
            batch=batch,
        )
        for c in cams
    }  # fmt: skip
    params = {"route": "kitti-raw", "beams": beams}
    # Recorded only when not the default, so datasets of earlier versions resume.
    if gt != "scan":
        params.update(gt=gt, gt_neighbours=gt_neighbours,
                      stereo_check="auto" if stereo_check is None else stereo_check)  # fmt: skip
        if icp_min_range:
            params["icp_min_range"] = icp_min_range
    if filter_occluded and gt == "scan":  # accumulated always filters: not a setting there
        params["gt_filter_occluded"] = True
    if resize_to is not None:
        params["resize_to"] = list(resize_to)
    if rig:
        params["cameras"] = [f"image_0{c}" for c in cams]
    source = "lidar" if beams is None else f"lidar-{beams}beam"
    # The default (one scan) writes the rows 0.2 wrote, byte for byte: no gt_method, which
    # ``dataset info`` reads as ``scan`` for this route.
    per_sample = None
    if not plain_gt:
        per_sample = {}
        for c, (_, _, methods, windows, _, _) in staged.items():
            for k, m in methods.items():
                sid = camera_id(k, f"image_0{c}") if rig else k
                per_sample[sid] = (("gt_method", m),) + (
                    (("gt_window", windows[k]),) if k in windows else ()
                )
    sparse, gt_dir, methods, _, gt_totals, clouds = staged[cams[0]]
    if not rig:
        # After the projections, whose records refuse another --resize-to before anything is
        # written here: the images at the maps' size, with their calibrations.
        rgb, calib = root, None
        if resize_to is not None:
            from ...io.sources import cloud_frames

            rgb, calib = resized_images(cloud_frames([root], camera=cams[0]), out, resize_to,
                                         camera=cams[0], root=root, batch=batch)  # fmt: skip
        summary = build_dataset(
            out, rgb=rgb, calib=calib, sparse=sparse, gt=gt_dir, split=split,
            split_files=split_files,
            official_split=official_split, seed=seed, sparse_format=sparse_format,
            source=source, camera=cams[0], params=params, param_options=KITTI_RAW_OPTIONS,
            sample_params=per_sample, geometry=geometry, store_points=store_points,
            frame_fields={"cloud": clouds} if store_points else None, store=store,
            rgb_root_name="kitti", batch=batch,
        )  # fmt: skip
    else:
        settings = BuildSettings.with_splits(
            split, split_files, official_split=official_split, sparse_format=sparse_format,
            source=source, seed=seed, params=params, geometry=geometry,
            store_points=store_points, store=store,
        )  # fmt: skip
        found = find_rig_inputs(settings, [
            CameraInputs(f"image_0{c}", rgb=root, sparse=staged[c][0], gt=staged[c][1], index=c,
                         extra=(("cloud", staged[c][5]),) if store_points else ())
            for c in cams
        ])  # fmt: skip
        if per_sample:
            found = replace(found, frames=[
                replace(x, sample_params=per_sample.get(x.id, ())) for x in found.frames])  # fmt: skip
        job = DatasetJob.for_inputs(settings, found, param_options=KITTI_RAW_OPTIONS)
        summary = run_job(job, found.frames, out, batch=batch, inputs=found.roots,
                          desc="dataset")  # fmt: skip
        methods = {camera_id(k, f"image_0{c}"): m for c, st in staged.items()
                   for k, m in st[2].items()}  # fmt: skip
    method = "scan+occlusion" if gt == "scan" and filter_occluded else gt
    return summary.with_totals(
        {"gt": {"method": method, "methods": _count(methods.values()), **gt_totals}}
    )


GT_METHOD_DOC = """scan                      one LiDAR scan projected (kitti-raw's default: not recorded,
                          so its rows stay as 0.2 wrote them; dataset info reads them as scan)
scan+occlusion            the same without its see-through points (--filter-occluded)
accumulated(t-K..t+K,poses=P,occlusion,consistency[,stereo])
                          frames t-K..t+K merged (gt_window: the sample's own, t-A..t+B,
                          clipped at the drive's ends), poses oxts or icp, occlusion test on
                          every scan, moving-object test, stereo check
sweeps(N)[+occlusion]     N LiDAR sweeps merged (nuScenes), optionally occlusion-filtered
annotated                 kitti-dc: the tree's map set, KITTI's annotation (not recorded; dataset
                          info reads kitti-dc rows as annotated)
"""


def _count(values) -> dict[str, int]:
    out: dict[str, int] = {}
    for v in values:
        out[v] = out.get(v, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: (-kv[1], kv[0])))


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
    store: str = "copy",
    batch: Batch | None = None,
) -> RunSummary:
    """A KITTI depth-completion root -> dataset, split as the tree splits it.

    ``root`` holds ``data_depth_velodyne/`` and ``data_depth_annotated/`` (or is one of them
    with ``{train,val}/<drive>/proj_depth/``); images come from the KITTI raw tree ``raw``.
    ``selection``: the 1,000-frame ``depth_selection/val_selection_cropped`` set instead, with
    its own images and intrinsics (split ``val_selection``). Frames without ground truth (the
    first and last 5 of each drive) are counted in the summary's ``unmatched``. ``store``: as
    :func:`build_kitti_raw_dataset`'s; the images are referenced relative to the root
    ``kitti`` (``raw``; with ``selection``, the selection folder).
    """
    root = Path(root)
    if selection:
        sel = root / "depth_selection" / "val_selection_cropped"
        sel = sel if sel.is_dir() else root
        return build_dataset(
            out_dir, rgb=sel, sparse=sel, gt=sel, calib=sel, split="tree",
            sparse_format=sparse_format, source="lidar", camera=camera, store=store,
            rgb_root_name="kitti",
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
        gt_name=gt_name, sparse_format=sparse_format, camera=camera, store=store,
        rgb_root_name="kitti",
        source=f"lidar-{sparse_name}" if sparse_name else "lidar",
        params={"route": "kitti-dc", "sparse": sparse_name or "velodyne_raw"},
        param_options=KITTI_DC_OPTIONS, batch=batch,
    )  # fmt: skip
