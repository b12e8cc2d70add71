"""The stages of ``dataset kitti-raw`` (one camera's): the scan's projection, the occlusion-
filtered or accumulated (and stereo-checked) ground truth, the N-beam input, and the images of
``--resize-to``; each an ordinary sparsetools output folder in ``DATASET/.sources/``."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

from ...errors import FormatError, UsageError
from ..core import run_job
from .build import SOURCES_DIR

__all__ = [
    "accumulated_gt",
    "check_kitti_raw_gt",
    "kitti_raw_stages",
    "resized_images",
    "stage_dir",
]

log = logging.getLogger(__name__)


def stage_dir(out: Path, name: str) -> Path:
    """``DATASET/.sources/<name>``: a stage's output folder."""
    return Path(out) / SOURCES_DIR / name


def resized_images(frames, out: Path, size, *, camera, root, batch) -> tuple[Path, Path]:
    """The images stage of ``--resize-to``: every frame's camera image at ``size`` and its
    calibration (``.sources/images/calib``), the folders the dataset is built from."""
    from ...io.calib import load_calibration
    from ..camera_images import CameraImageJob, CameraImageSettings

    loaded = {}  # one read per calibration folder (a date's pair)
    for f in frames:
        if f.image is not None and f.calib not in loaded:
            loaded[f.calib] = load_calibration(f.calib, camera=camera)
    with_image = [replace(f, calibration=loaded[f.calib]) for f in frames if f.image is not None]
    images = stage_dir(out, "images")
    if with_image:
        job = CameraImageJob(CameraImageSettings(resize_to=size))
        run_job(job, with_image, images, batch=batch, inputs=[root], desc="images")
    return images, images / "calib"


def kitti_raw_stages(
    root,
    out: Path,
    *,
    camera,
    suffix,
    beams,
    gt,
    filter_occluded,
    gt_neighbours,
    stereo_check,
    icp_min_range,
    resize_to,
    batch,
):
    """One camera's stages of ``dataset kitti-raw`` (folders ``DATASET/.sources/<stage>
    <suffix>``): the sparse input folder, the ground-truth folder, each frame's ``gt_method``
    and window, the ground truth's totals, each frame's scan (by frame id)."""
    from ...io.sources import Frame, cloud_frames, kitti_raw_index
    from ..beams import BeamsJob, BeamsSettings
    from ..project import ProjectJob, ProjectSettings

    frames = cloud_frames([root], camera=camera)
    project = ProjectJob(ProjectSettings(camera=camera, resize_to=resize_to))
    plain_gt = gt == "scan" and not filter_occluded
    if plain_gt or beams is None:  # the scan's projection: the truth, or the 64-beam input
        run_job(project, frames, stage_dir(out, "gt" + suffix), batch=batch, inputs=[root])
    gt_dir, gt_totals = stage_dir(out, "gt" + suffix), {}
    methods, windows = dict.fromkeys((str(f.key) for f in frames), "scan"), {}
    if gt == "scan" and filter_occluded:
        gt_dir = stage_dir(out, "gt_occluded" + suffix)
        occluded = ProjectJob(replace(project.settings, filter_occluded=True))
        s = run_job(occluded, frames, gt_dir, batch=batch, inputs=[root], desc="gt")
        methods = dict.fromkeys(methods, "scan+occlusion")
        gt_totals = {"occluded_pixels": s.totals.get("occluded_pixels", 0)}
    elif gt == "accumulated":
        gt_dir, methods, windows, gt_totals = accumulated_gt(
            root, out, neighbours=gt_neighbours, stereo=stereo_check,
            icp_min_range=icp_min_range, camera=camera, resize_to=resize_to, batch=batch,
            suffix=suffix,
        )  # fmt: skip
    sparse = stage_dir(out, "gt" + suffix)
    if beams is not None:
        beams_dir = stage_dir(out, f"beams{beams}{suffix}")
        run_job(BeamsJob(BeamsSettings(n=(beams,))), frames, beams_dir, batch=batch,
                inputs=[root])  # fmt: skip
        raw = kitti_raw_index(root, what="cloud", camera=camera)
        beam_frames = [
            Frame(key=f.key, cloud=f.key.path(beams_dir, ".bin"), calib=raw.calib[f.key],
                  image=f.image)
            for f in frames
        ]  # fmt: skip
        sparse = stage_dir(out, f"sparse{beams}{suffix}")
        run_job(project, beam_frames, sparse, batch=batch)
    clouds = {str(f.key): str(f.cloud) for f in frames}
    return sparse, gt_dir, methods, windows, gt_totals, clouds


#: The vocabulary of ``generation_params["sample"]["gt_method"]`` (docs/dataset.md).


def check_kitti_raw_gt(gt, neighbours, stereo, icp_min_range, camera) -> None:
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


def accumulated_gt(
    root,
    out: Path,
    *,
    neighbours,
    stereo,
    icp_min_range,
    camera,
    batch,
    resize_to=None,
    suffix="",
):
    """The accumulate stage (and the stereo stage) of ``--gt-method accumulated``: the folder
    of the ground truth, each sample's ``gt_method`` and window (``t-A..t+B``, clipped at the
    drive's ends), the stages' totals."""
    from ...io.sources.kitti import kitti_raw_partner_image
    from ...ops.accumulate import AccumulateSettings
    from ..accumulate import IcpSettings, accumulation_job, sequences_of
    from ..stereo_check import StereoCheckJob

    job, frames = accumulation_job(
        [root], window=neighbours, accumulate=AccumulateSettings(occlude_own=True), icp=None,
        icp_settings=IcpSettings(min_range=icp_min_range), camera=camera, resize_to=resize_to,
    )  # fmt: skip
    job = replace(job, option_aliases=(("window", "--gt-neighbours"),))
    acc_dir = stage_dir(out, "gt_accumulated" + suffix)
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
    checked_dir = stage_dir(out, "gt_stereo" + suffix)
    check = StereoCheckJob(right=tuple(sorted(right.items())), resize_to=resize_to)
    s = run_job(check, stereo_frames, checked_dir, batch=batch, inputs=[root], desc="stereo")
    totals["stereo_removed"] = s.totals.get("removed", 0)
    return checked_dir, methods, windows, totals
