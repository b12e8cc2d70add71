"""Batch job of ``sparsetools accumulate``: the scans of frames t-K..t+K merged into frame t.

Frames come from :func:`sparsetools.io.sources.poses.accumulation_frames`, their poses from
:func:`~sparsetools.io.sources.poses.attach_poses` or from ICP between consecutive scans.
Each sequence is put in time order (timestamps when every frame has one, else frame numbers
/ names); frame t's window is t-K..t+K of ITS sequence, clipped at the sequence's ends.
:func:`sparsetools.ops.accumulate.accumulate_scans` merges and filters. Outputs per frame:

- ``OUT/<sequence>/<frame>.png``: the accumulated sparse depth (KITTI uint16, depth * 256);
- ``OUT/calib/<sequence>/<frame>.json``: its calibration (as ``project`` writes it), with the
  window's frames and scans;
- with ICP, per consecutive pair ``OUT/icp/<sequence>/<frame>.json``: ``T_target_from_source``
  (the frame before <- this one), fitness, inlier RMSE. The pairs are a resumable batch of
  their own (a folder with its own record, run first): a pair is recomputed only when one of
  its two scans changed.

A frame's resume sources are every scan of its window, its calibration (and the image giving
its size), its mask and the window's pose files: changing one scan recomputes exactly the
frames whose window holds it.
"""

from __future__ import annotations

import json
import logging
import os
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..calibration import Calibration
from ..errors import FormatError, ParameterError, SparsetoolsError
from ..io.atomic import atomic_path
from ..io.sources import Frame, FrameKey
from ..io.sources.poses import attach_poses, moving_masks
from ..ops.accumulate import AccumulateSettings
from ..validate import check_int_range, check_non_negative, check_positive
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames

__all__ = [
    "ICP_DIR",
    "MAX_WINDOW",
    "AccumulateInput",
    "AccumulateJob",
    "AccumulateRunSettings",
    "IcpPairJob",
    "IcpSettings",
    "accumulate_tasks",
    "run_accumulate",
]

log = logging.getLogger(__name__)

ICP_DIR = "icp"
MAX_WINDOW = 100
_REASONS = ("non_finite", "behind_camera", "beyond_max_depth", "outside_image", "masked",
            "inconsistent", "occluded")  # fmt: skip


@dataclass(frozen=True)
class IcpSettings:
    """:func:`sparsetools.ops.registration.icp_pose` options of a run (metres)."""

    min_range: float = 0.0
    voxel: float = 0.2
    max_distance: float = 0.5

    def __post_init__(self) -> None:
        check_non_negative(self.min_range, "icp_min_range")
        check_positive(self.voxel, "icp_voxel")
        check_positive(self.max_distance, "icp_max_distance")


@dataclass(frozen=True)
class AccumulateRunSettings:
    """What every map of a run depends on (recorded; a rerun with others is refused).

    ``window`` is K; ``pose_source`` ``icp`` or the kinds :func:`attach_poses` used;
    ``poses_frame`` what a ``--poses`` file holds; ``mask``: masks given; ``icp`` is recorded
    with its defaults when the poses do not come from ICP.
    """

    window: int = 5
    pose_source: str = field(default="", metadata={"option": "--poses/--icp"})
    poses_frame: str = "auto"
    mask: bool = False
    image_size: tuple[int, int] | None = None
    icp: IcpSettings = field(default_factory=IcpSettings)
    accumulate: AccumulateSettings = field(default_factory=AccumulateSettings)

    def __post_init__(self) -> None:
        check_int_range(self.window, "window", low=0, high=MAX_WINDOW)

    def record(self) -> tuple[dict, dict]:
        """Flat settings for the folder's record and their option names."""
        from .provenance import settings_dict

        flat = {k: v for k, v in settings_dict(self).items() if k not in ("icp", "accumulate")}
        flat.update({f"icp_{k}": v for k, v in settings_dict(self.icp).items()})
        flat.update(settings_dict(self.accumulate))
        return flat, {"pose_source": "--poses/--icp"}


@dataclass(frozen=True)
class AccumulateInput:
    """One frame's inputs: its window's scans and frame ids (in sequence order), the position
    of frame t among them, their poses (``T_world_from_sensor``, row-major 16-tuples) or the
    ICP files of their pairs (``scans[k] <- scans[k + 1]``), where frame t's calibration and
    size come from, and its mask."""

    scans: tuple[str, ...]
    frames: tuple[str, ...]
    reference: int
    poses: tuple[tuple[float, ...], ...] | None = None
    icp_pairs: tuple[str, ...] = ()
    calib_path: str | None = None
    calibration: Calibration | None = None
    image: str | None = None
    mask: str | None = None


def _calibration(inp: AccumulateInput, image_size) -> Calibration:
    from .project import ProjectInput, ProjectSettings, resolve_calibration

    pi = ProjectInput(cloud=inp.scans[inp.reference], calib_path=inp.calib_path,
                      calibration=inp.calibration, image=inp.image)  # fmt: skip
    return resolve_calibration(pi, ProjectSettings(image_size=image_size))


def _read_mask(path: str, calib: Calibration) -> np.ndarray:
    """(H, W) bool: non-zero pixels of a mask PNG (uint8 0/255 or any single channel)."""
    from ..io.image import decode_image_bytes

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise FormatError(f"{path}: cannot read mask ({exc.strerror or exc})") from exc
    img = decode_image_bytes(data, source=path, what="moving-object mask")
    if img.ndim != 2:
        raise FormatError(f"{path}: moving-object mask not a single-channel PNG")
    if (img.shape[1], img.shape[0]) != calib.size:
        w, h = calib.size
        raise FormatError(f"{path}: mask is {img.shape[1]}x{img.shape[0]}, the map {w}x{h}")
    return img > 0


def _read_pair(path: str) -> np.ndarray:
    try:
        T = np.asarray(json.loads(Path(path).read_text(encoding="utf-8"))["T_target_from_source"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FormatError(f"{path}: no ICP pose of this pair ({exc}); rerun to make it") from exc
    return T.astype(np.float64).reshape(4, 4)


@dataclass(frozen=True)
class AccumulateJob:
    """The per-frame job (picklable): read the window, merge, write the map and calibration."""

    settings: AccumulateRunSettings

    def __call__(self, task: FrameTask[AccumulateInput]) -> dict:
        from ..io.calib import write_json_calib
        from ..io.image import write_depth_png
        from ..io.pointcloud import read_points
        from ..ops.accumulate import accumulate_scans
        from ..ops.registration import chain_poses

        inp, s = task.inputs, self.settings
        calib = _calibration(inp, s.image_size)
        scans = [read_points(p) for p in inp.scans]
        if inp.poses is not None:
            poses = np.array([np.reshape(T, (4, 4)) for T in inp.poses])
        else:
            poses = chain_poses([_read_pair(p) for p in inp.icp_pairs], reference=inp.reference)
        mask = None if inp.mask is None else _read_mask(inp.mask, calib)
        a = s.accumulate
        res = accumulate_scans(scans, poses, calib, reference=inp.reference, settings=a,
                               moving_mask=mask)  # fmt: skip
        clipped = write_depth_png(task.outputs["depth"], res.depth)
        write_json_calib(task.outputs["calib"], calib, frame=task.frame_id, cloud=list(inp.scans),
                         window=list(inp.frames), pixel_offset=a.pixel_offset,
                         min_depth=a.min_depth, max_depth=a.max_depth,
                         calibration=calib.source)  # fmt: skip
        c = res.counts
        valid = int(np.count_nonzero(res.depth))
        return {
            "scans": len(scans), "window": "..".join(FrameKey.parse(inp.frames[i]).frame
                                                     for i in (0, -1)),
            "points": c.points, "kept": c.kept, **{r: getattr(c, r) for r in _REASONS},
            "valid_pixels": valid, "own_pixels": int(np.count_nonzero(res.source == inp.reference)),
            "pixels": int(res.depth.size), "clipped_png": int(clipped),
        }  # fmt: skip


@dataclass(frozen=True)
class IcpPairInput:
    source: str
    target: str
    source_frame: str
    target_frame: str


@dataclass(frozen=True)
class IcpPairJob:
    """ICP of one consecutive pair (picklable): earlier scan <- this scan, written as JSON."""

    settings: IcpSettings

    def __call__(self, task: FrameTask[IcpPairInput]) -> dict:
        from ..io.pointcloud import read_points
        from ..ops.registration import icp_pose

        inp, s = task.inputs, self.settings
        r = icp_pose(read_points(inp.source), read_points(inp.target), voxel=s.voxel,
                     max_distance=s.max_distance, min_range=s.min_range)  # fmt: skip
        # Open3D's threaded reductions differ in the last bits from run to run: rounding to
        # 1e-9 (nm, nrad) makes every run, whatever --workers, write the same poses.
        T = np.round(r.T_target_from_source, 9) + 0.0
        doc = {"target": inp.target_frame, "source": inp.source_frame,
               "T_target_from_source": T.tolist(), "fitness": round(r.fitness, 6),
               "inlier_rmse_m": round(r.inlier_rmse, 6)}  # fmt: skip
        with atomic_path(task.outputs["pose"]) as tmp:
            tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        return {"fitness": doc["fitness"], "inlier_rmse_m": doc["inlier_rmse_m"]}


# -- tasks ---------------------------------------------------------------------------------------


def _order(name: str):
    return (0, int(name), name) if name.isdigit() else (1, 0, name)


def sequences_of(frames: list[Frame]) -> dict[str, list[Frame]]:
    """Frames by sequence, each in time order (timestamps when all have one, else names)."""
    groups: dict[str, list[Frame]] = defaultdict(list)
    for f in frames:
        groups[f.key.sequence].append(f)
    for fs in groups.values():
        if all(f.timestamp is not None for f in fs):
            fs.sort(key=lambda f: (f.timestamp, _order(f.key.frame)))
        else:
            fs.sort(key=lambda f: _order(f.key.frame))
    return dict(sorted(groups.items()))


def accumulate_tasks(
    frames: list[Frame],
    out_dir: str | os.PathLike,
    settings: AccumulateRunSettings,
    *,
    icp: bool = False,
    masks: dict[FrameKey, Path] | None = None,
) -> tuple[list[FrameTask[AccumulateInput]], list[FrameTask[IcpPairInput]]]:
    """The frame tasks and (with ``icp``) the pair tasks, sequence by sequence."""
    out, k = Path(out_dir), settings.window
    tasks, pairs = [], []
    for seq, fs in sequences_of(frames).items():
        if len(fs) < 2 * k + 1:
            log.warning("sequence '%s' has %d frame(s), fewer than the %d of --window %d: "
                        "every window is clipped to frames %s..%s", seq, len(fs), 2 * k + 1,
                        k, fs[0].key.frame, fs[-1].key.frame)  # fmt: skip
        pair_files = [FrameKey(seq, f.key.frame).path(out / ICP_DIR, ".json") for f in fs]
        if icp and k > 0:
            for j in range(1, len(fs)):
                prev, f = fs[j - 1], fs[j]
                inp = IcpPairInput(str(f.cloud), str(prev.cloud), f.id, prev.id)
                pairs.append(FrameTask(f.key, inp, {"pose": pair_files[j]}, (f.cloud, prev.cloud)))
        for i, t in enumerate(fs):
            lo, hi = max(0, i - k), min(len(fs), i + k + 1)
            window = fs[lo:hi]
            mask = None if masks is None else masks[t.key]
            sized = settings.image_size is None and t.image is not None
            sources = [w.cloud for w in window]
            sources += [p for p in (t.calib, t.image if sized else None, mask) if p is not None]
            sources += [p for w in window for p in w.extra_inputs]
            inp = AccumulateInput(
                scans=tuple(str(w.cloud) for w in window),
                frames=tuple(w.id for w in window),
                reference=i - lo,
                poses=None if icp else tuple(w.pose for w in window),
                icp_pairs=tuple(str(p) for p in pair_files[lo + 1 : hi]) if icp else (),
                calib_path=None if t.calib is None else str(t.calib),
                calibration=t.calibration,
                image=str(t.image) if sized else None,
                mask=None if mask is None else str(mask),
            )
            outputs = {"depth": t.key.path(out, ".png"),
                       "calib": t.key.path(out, ".json", prefix="calib")}  # fmt: skip
            tasks.append(FrameTask(t.key, inp, outputs, tuple(dict.fromkeys(sources))))
    return tasks, pairs


# -- running -------------------------------------------------------------------------------------


def _check_inputs(frames: list[Frame], poses, icp: bool, poses_frame: str, camera: int):
    if not frames:
        raise ParameterError("no frames to accumulate")
    no_calib = [f for f in frames if f.calib is None and f.calibration is None]
    if no_calib:
        raise ParameterError(
            f"no calibration for frame {no_calib[0].id} ({no_calib[0].cloud}): give --calib "
            "(a file, a KITTI raw date folder or per-frame files)", param="--calib")  # fmt: skip
    if icp:
        if poses is not None:
            raise ParameterError("give --poses or --icp, not both", param="--icp")
        return frames, "icp"
    att = attach_poses(frames, poses, poses_frame=poses_frame, camera=camera)
    if att.missing:
        key, why = next(iter(att.missing.items()))
        raise FormatError(
            f"no pose for frame {key} ({why}; {len(att.missing)} of {len(frames)} frames lack "
            "one): give --poses (a poses.txt or a folder of them) or --icp")  # fmt: skip
    return list(att.frames), att.source


def run_accumulate(
    frames: list[Frame],
    out_dir: str | os.PathLike,
    *,
    window: int = 5,
    accumulate: AccumulateSettings | None = None,
    poses: str | os.PathLike | None = None,
    poses_frame: str = "auto",
    icp: IcpSettings | None = None,
    mask: str | os.PathLike | None = None,
    image_size: tuple[int, int] | None = None,
    batch: Batch | None = None,
    inputs: list[str | os.PathLike] = (),
) -> RunSummary:
    """Accumulate every frame's window into its depth map (module docstring).

    Parameters
    ----------
    frames : list of Frame
        With a cloud and a calibration each (from ``accumulation_frames``).
    out_dir : path-like
    window : int
        K (0..100): frames t-K..t+K of the same sequence.
    accumulate : AccumulateSettings, optional
    poses : path-like, optional
        Pose file or folder (default: the inputs' own poses); ``poses_frame`` says of what.
    icp : IcpSettings, optional
        Poses by ICP between consecutive scans instead.
    mask : path-like, optional
        Moving-object masks matched by frame (a folder tree or a synthetic video folder).
    image_size : (W, H), optional
    batch : Batch, optional
    inputs : list of path-like
        What the user gave (the output may not be inside an input folder).

    Returns
    -------
    RunSummary
        Totals: window, pose_source, clipped_windows, valid_pixels, density_pct, removed (by
        reason), removed_per_frame, and with ICP ``icp`` (per-pair fitness and RMSE).
    """
    batch = batch or Batch()
    frames, source = _check_inputs(frames, poses, icp is not None, poses_frame, 2)
    settings = AccumulateRunSettings(
        window=window, pose_source=source, poses_frame=poses_frame, mask=mask is not None,
        image_size=image_size, icp=icp or IcpSettings(),
        accumulate=accumulate or AccumulateSettings(),
    )  # fmt: skip
    masks = None if mask is None else moving_masks(frames, mask)
    tasks, pairs = accumulate_tasks(frames, out_dir, settings, icp=icp is not None, masks=masks)
    out = check_output_dir(out_dir, [p for p in inputs if p is not None])
    try:  # one clear error before anything is written (no image size, a bad calibration)
        _calibration(tasks[0].inputs, image_size)
    except ParameterError:
        raise
    except SparsetoolsError:  # that frame's own problem: its job reports it
        pass
    record, options = settings.record()
    icp_summary: list[RunSummary] = []

    def register_pairs():
        if pairs:
            icp_record = {k: v for k, v in record.items() if k.startswith("icp_")}
            spec = RunSpec("accumulate", check_output_dir(out / ICP_DIR, []), icp_record,
                           noun="ICP poses")  # fmt: skip
            icp_summary.append(run_frames(IcpPairJob(settings.icp), pairs, batch=batch,
                                          spec=spec, desc="icp"))  # fmt: skip

    spec = RunSpec("accumulate", out, record, noun="accumulated depth maps", options=options)
    summary = run_frames(AccumulateJob(settings), tasks, batch=batch, spec=spec,
                         before=register_pairs)  # fmt: skip
    return summary.with_totals(_totals(summary, settings, icp_summary))


def _totals(summary: RunSummary, settings: AccumulateRunSettings, icp: list) -> dict:
    ok = summary.ok
    pixels, valid = summary.total("pixels"), summary.total("valid_pixels")
    clipped = [r for r in ok if r.stats.get("scans", 0) < 2 * settings.window + 1]
    totals = {
        "window": settings.window,
        "pose_source": settings.pose_source,
        "clipped_windows": len(clipped),
        "valid_pixels": int(valid),
        "density_pct": round(100.0 * valid / pixels, 4) if pixels else 0.0,
        "points": int(summary.total("points")),
        "kept": int(summary.total("kept")),
        "removed": {r: int(summary.total(r)) for r in _REASONS},
        "removed_per_frame": {
            r.frame_id: {k: int(r.stats.get(k, 0)) for k in ("occluded", "inconsistent", "masked")}
            for r in ok
        },
    }
    if clipped:
        totals["clipped_window_frames"] = {r.frame_id: r.stats.get("window") for r in clipped}
    if icp:
        pairs = icp[0].ok
        fit = [r.stats["fitness"] for r in pairs]
        rmse = [r.stats["inlier_rmse_m"] for r in pairs]
        totals["icp"] = {
            "pairs": len(icp[0].results), "computed": len(icp[0].done),
            "failed": len(icp[0].failed),
            "fitness_min": min(fit, default=0.0), "inlier_rmse_max_m": max(rmse, default=0.0),
            "per_pair": {r.frame_id: {"fitness": r.stats["fitness"],
                                      "inlier_rmse_m": r.stats["inlier_rmse_m"]} for r in pairs},
        }  # fmt: skip
    return totals
