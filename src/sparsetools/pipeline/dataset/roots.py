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
    "gt": "--gt-sensor", "jbf": "--jbf", "gt_filter_occluded": "--filter-occluded",
}  # fmt: skip
KITTI_RAW_OPTIONS = {
    "route": "dataset", "beams": "--beams", "gt": "--gt-method", "gt_neighbours": "--gt-neighbours",
    "stereo_check": "--stereo-check/--no-stereo-check", "icp_min_range": "--icp-min-range",
    "gt_filter_occluded": "--filter-occluded",
}  # fmt: skip
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
    filter_occluded: bool = False,
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
    ``sweeps_merged``, with ground truth ``gt_sweeps_merged`` and ``gt_method``, e.g.
    ``sweeps(3)+occlusion``); the summary's ``sweeps`` gives the requested count and the
    merged minimum, maximum and mean. ``filter_occluded``: the ground truth without the points
    the camera cannot see (:func:`sparsetools.ops.occlusion.filter_occluded` on the merged
    sweeps' map).

    Raises
    ------
    UsageError
        ``sensor`` is also ``gt_sensor`` (the input would be the ground truth itself), or
        ``filter_occluded`` without ground truth.
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
    if filter_occluded and gt_sensor is None:
        raise UsageError("--filter-occluded filters the ground truth: not with --gt-sensor none",
                         param="filter_occluded")  # fmt: skip
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
    tag = "+occlusion" if filter_occluded else ""
    sample_params = {
        k: (("sweeps_merged", n),) + (
            (("gt_sweeps_merged", gt_merged[k]), ("gt_method", f"sweeps({gt_merged[k]}){tag}"))
            if gt_merged else ()
        )
        for k, n in merged.items()
    }  # fmt: skip
    images = CameraImageJob(CameraImageSettings(resize=resize, crop=crop))
    run_job(images, frames, _stage(out, "images"), batch=batch, desc="images")
    project = ProjectJob(ProjectSettings(resize=resize, crop=crop, camera=camera))
    run_job(project, frames, _stage(out, "sparse"), batch=batch, inputs=[root])
    gt, gt_totals = None, {}
    if gt_sensor is not None:
        gt = _stage(out, "gt_occluded" if filter_occluded else "gt")
        gt_job = ProjectJob(replace(project.settings, filter_occluded=filter_occluded))
        done = run_job(gt_job, gt_frames, gt, batch=batch, inputs=[root], desc="gt")
        gt_totals = {"gt": {"methods": _count(dict(sample_params[k])["gt_method"]
                                              for k in gt_merged)}}  # fmt: skip
        if filter_occluded:
            gt_totals["gt"]["occluded_pixels"] = done.totals.get("occluded_pixels", 0)
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
            # recorded only when set, so datasets of earlier versions resume
            **({"gt_filter_occluded": True} if filter_occluded else {}),
        },
    )  # fmt: skip
    found = find_build_inputs(settings, rgb=_stage(out, "images"), sparse=sparse, gt=gt,
                              confidence=confidence, calib=_stage(out, "images") / "calib")  # fmt: skip
    found = replace(found, frames=[
        replace(x, sample_params=sample_params.get(x.id, ())) for x in found.frames
    ])  # fmt: skip
    job = DatasetJob.for_inputs(settings, found, param_options=NUSCENES_OPTIONS)
    summary = run_job(job, found.frames, out, batch=batch, inputs=found.roots, desc="dataset")
    return summary.with_totals({"sweeps": sweeps_summary(sweeps, merged.values()), **gt_totals})


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
    split: str | None = None,
    split_files=None,
    official_split: str | None = None,
    seed: int = 0,
    sparse_format: str = "both",
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
    from ...io.sources import Frame, cloud_frames, is_kitti_raw, kitti_raw_index
    from ..beams import BeamsJob, BeamsSettings
    from ..project import ProjectJob, ProjectSettings

    _check_kitti_raw_gt(gt, gt_neighbours, stereo_check, icp_min_range, camera)
    batch = batch or Batch()
    out = Path(out_dir)
    if not is_kitti_raw(root):
        raise FormatError(
            f"{root}: not a KITTI raw drive, date folder or root (no <drive>/velodyne_points/"
            "data/ or image_0N/data/ with the calibration pair)"
        )
    frames = cloud_frames([root], camera=camera)
    project = ProjectJob(ProjectSettings(camera=camera))
    plain_gt = gt == "scan" and not filter_occluded
    if plain_gt or beams is None:  # the scan's projection: the truth, or the 64-beam input
        run_job(project, frames, _stage(out, "gt"), batch=batch, inputs=[root])
    gt_dir, gt_totals = _stage(out, "gt"), {}
    methods, windows = dict.fromkeys((str(f.key) for f in frames), "scan"), {}
    if gt == "scan" and filter_occluded:
        gt_dir = _stage(out, "gt_occluded")
        occluded = ProjectJob(ProjectSettings(camera=camera, filter_occluded=True))
        s = run_job(occluded, frames, gt_dir, batch=batch, inputs=[root], desc="gt")
        methods = dict.fromkeys(methods, "scan+occlusion")
        gt_totals = {"occluded_pixels": s.totals.get("occluded_pixels", 0)}
    elif gt == "accumulated":
        gt_dir, methods, windows, gt_totals = _accumulated_gt(
            root, out, neighbours=gt_neighbours, stereo=stereo_check,
            icp_min_range=icp_min_range, camera=camera, batch=batch,
        )  # fmt: skip
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
    params = {"route": "kitti-raw", "beams": beams}
    # Recorded only when not the default, so datasets of earlier versions resume.
    if gt != "scan":
        params.update(gt=gt, gt_neighbours=gt_neighbours,
                      stereo_check="auto" if stereo_check is None else stereo_check)  # fmt: skip
        if icp_min_range:
            params["icp_min_range"] = icp_min_range
    if filter_occluded and gt == "scan":  # accumulated always filters: not a setting there
        params["gt_filter_occluded"] = True
    # The default (one scan) writes the rows 0.2 wrote, byte for byte: no gt_method, which
    # ``dataset info`` reads as ``scan`` for this route.
    per_sample = None
    if not plain_gt:
        per_sample = {
            k: (("gt_method", m),) + ((("gt_window", windows[k]),) if k in windows else ())
            for k, m in methods.items()
        }
    summary = build_dataset(
        out,
        rgb=root,
        sparse=sparse,
        gt=gt_dir,
        split=split,
        split_files=split_files,
        official_split=official_split,
        seed=seed,
        sparse_format=sparse_format,
        store=store,
        rgb_root_name="kitti",
        source="lidar" if beams is None else f"lidar-{beams}beam",
        camera=camera,
        params=params,
        param_options=KITTI_RAW_OPTIONS,
        sample_params=per_sample,
        batch=batch,
    )
    method = "scan+occlusion" if gt == "scan" and filter_occluded else gt
    return summary.with_totals(
        {"gt": {"method": method, "methods": _count(methods.values()), **gt_totals}}
    )


#: The vocabulary of ``generation_params["sample"]["gt_method"]`` (docs/dataset.md).
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


def _check_kitti_raw_gt(gt, neighbours, stereo, icp_min_range, camera) -> None:
    from ...validate import check_choice, check_int_range, check_non_negative

    check_choice(gt, "--gt-method", ("scan", "accumulated"))
    check_int_range(neighbours, "--gt-neighbours", low=0, high=100)
    check_non_negative(icp_min_range, "--icp-min-range")
    if gt != "accumulated":
        given = [name for name, off in (("--gt-neighbours", neighbours == 5),
                                        ("--stereo-check/--no-stereo-check", stereo is None),
                                        ("--icp-min-range", icp_min_range == 0.0)) if not off]  # fmt: skip
        if given:
            raise UsageError(f"{given[0]} goes with --gt-method accumulated", param=given[0])
    if stereo and camera != 2:
        raise UsageError(
            "--stereo-check matches image_02 (left) with image_03: camera 2 only",
            param="--stereo-check",
        )


def _accumulated_gt(root, out: Path, *, neighbours, stereo, icp_min_range, camera, batch):
    """The accumulate stage (and the stereo stage) of ``--gt-method accumulated``: the folder
    of the ground truth, each sample's ``gt_method`` and window (``t-A..t+B``, clipped at the
    drive's ends), the stages' totals."""
    from ...io.sources.kitti import kitti_raw_partner_image
    from ...ops.accumulate import AccumulateSettings
    from ..accumulate import IcpSettings, accumulation_job, sequences_of
    from ..stereo_check import StereoCheckJob

    job, frames = accumulation_job(
        [root], window=neighbours, accumulate=AccumulateSettings(occlude_own=True), icp=None,
        icp_settings=IcpSettings(min_range=icp_min_range), camera=camera,
    )  # fmt: skip
    job = replace(job, option_aliases=(("window", "--gt-neighbours"),))
    acc_dir = _stage(out, "gt_accumulated")
    acc = run_job(job, frames, acc_dir, batch=batch, inputs=[root], desc="accumulate")
    source = job.settings.pose_source
    poses = {"kitti-oxts": "oxts"}.get(source, source)
    if poses == "icp":
        log.info("--gt-method accumulated: poses by ICP (not every drive has oxts)")
    right = {}
    if stereo is not False and camera == 2:
        for f in frames:
            partner = None if f.image is None else kitti_raw_partner_image(f.image, camera=3)
            if partner is not None:
                right[f.id] = str(partner)
            elif stereo:
                raise FormatError(f"--stereo-check: frame {f.id} has no image_03 ({f.image})")
        if stereo is None and len(right) < len(frames):
            log.warning(
                "--gt-method accumulated: %d of %d frame(s) have no image_03: their ground truth is not "
                "stereo-checked (each row's gt_method says so)", len(frames) - len(right),
                len(frames),
            )  # fmt: skip
    methods, windows = {}, {}
    for fs in sequences_of(frames).values():
        for i, f in enumerate(fs):
            lo, hi = max(0, i - neighbours), min(len(fs), i + neighbours + 1)
            tags = f"poses={poses},occlusion,consistency" + (",stereo" if f.id in right else "")
            methods[f.id] = f"accumulated(t-{neighbours}..t+{neighbours},{tags})"
            windows[f.id] = f"t-{i - lo}..t+{hi - 1 - i}"
    t = acc.totals
    totals = {"pose_source": poses, "clipped_windows": t.get("clipped_windows", 0),
              "density_pct": t.get("density_pct"), "removed": t.get("removed"),
              "stereo_checked": len(right)}  # fmt: skip
    if "icp" in t:
        totals["icp"] = {k: v for k, v in t["icp"].items() if k != "per_pair"}
    if not right:
        return acc_dir, methods, windows, totals
    stereo_frames = [replace(f, depth=f.key.path(acc_dir, ".png")) for f in frames]
    checked_dir = _stage(out, "gt_stereo")
    s = run_job(StereoCheckJob(right=tuple(sorted(right.items()))), stereo_frames, checked_dir,
                batch=batch, inputs=[root], desc="stereo")  # fmt: skip
    totals["stereo_removed"] = s.totals.get("removed", 0)
    return checked_dir, methods, windows, totals


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
