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
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..calibration import Calibration
from ..errors import FormatError, ParameterError, SparsetoolsError
from ..io.atomic import atomic_path
from ..io.sources import Frame, FrameKey
from ..io.sources.poses import accumulation_inputs
from ..ops.accumulate import AccumulateSettings
from ..validate import check_int_range, check_non_negative, check_positive, parse_size
from .batch import Batch, RunSummary
from .core import BatchJob, FrameStats, FrameTask, run_job
from .provenance import clear_recorded, settings_dict

__all__ = [
    "ICP_DIR",
    "MAX_WINDOW",
    "AccumulateInput",
    "AccumulateJob",
    "AccumulateRunSettings",
    "AccumulateStats",
    "IcpPairJob",
    "IcpSettings",
    "IcpStats",
    "accumulation_job",
    "sequences_of",
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

    ``window`` is K (``--neighbours``: frames t-K..t+K); ``pose_source`` ``icp`` or the kinds :func:`attach_poses` used;
    ``poses_frame`` what a ``--poses`` file holds; ``mask``: masks given; ``icp`` is recorded
    with its defaults when the poses do not come from ICP; ``resize_to`` (``dataset kitti-raw
    --resize-to``): the maps made at exactly this (width, height), the intrinsics scaled per
    axis (recorded only when set).
    """

    window: int = field(default=5, metadata={"option": "--neighbours"})
    pose_source: str = field(default="", metadata={"option": "--poses/--icp"})
    poses_frame: str = "auto"
    mask: bool = False
    image_size: tuple[int, int] | None = None
    icp: IcpSettings = field(default_factory=IcpSettings)
    accumulate: AccumulateSettings = field(default_factory=AccumulateSettings)
    resize_to: tuple[int, int] | None = field(
        default=None, metadata={"option": "--resize-to", "omit_default": True}
    )

    def __post_init__(self) -> None:
        check_int_range(self.window, "neighbours", low=0, high=MAX_WINDOW)
        if self.resize_to is not None:
            object.__setattr__(self, "resize_to", parse_size(self.resize_to, "--resize-to"))

    def record(self) -> tuple[dict, dict]:
        """Flat settings for the folder's record and their option names."""
        flat = {k: v for k, v in settings_dict(self).items() if k not in ("icp", "accumulate")}
        flat.update({f"icp_{k}": v for k, v in settings_dict(self.icp).items()})
        flat.update(settings_dict(self.accumulate))
        return flat, {"pose_source": "--poses/--icp", "window": "--neighbours",
                      "occlude_own": "--filter-occluded"}  # fmt: skip


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


def _calibration(inp: AccumulateInput, image_size, resize_to=None) -> Calibration:
    from ..io.calib import check_sensor, frame_calibration

    calib = frame_calibration(calib_path=inp.calib_path, calibration=inp.calibration,
                              image=inp.image, image_size=image_size,
                              resize_to=resize_to)  # fmt: skip
    check_sensor(calib, inp.scans[inp.reference])
    return calib


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
class IcpPairInput:
    source: str
    target: str
    source_frame: str
    target_frame: str


@dataclass(frozen=True)
class IcpStats(FrameStats):
    """One pair: ICP's fitness (fraction of inliers) and inlier RMSE, metres."""

    fitness: float
    inlier_rmse_m: float


@dataclass(frozen=True)
class IcpPairJob(BatchJob[IcpPairInput]):
    """ICP of every consecutive pair (picklable): earlier scan <- this scan, written as
    ``OUT/icp/<sequence>/<frame>.json``; the pairs are a resumable batch of their own."""

    command: ClassVar[str] = "accumulate"
    noun: ClassVar[str] = "ICP poses"
    stats_type: ClassVar[type[FrameStats]] = IcpStats

    settings: IcpSettings = field(default_factory=IcpSettings)

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[IcpPairInput]]:
        """One task per consecutive pair of each sequence (in time order)."""
        pairs = []
        for fs in sequences_of(frames).values():
            for j in range(1, len(fs)):
                prev, f = fs[j - 1], fs[j]
                inp = IcpPairInput(str(f.cloud), str(prev.cloud), f.id, prev.id)
                pairs.append(FrameTask(f.key, inp, {"pose": f.key.path(out_dir, ".json")},
                                       (f.cloud, prev.cloud)))  # fmt: skip
        return pairs

    def record(self) -> dict:
        return {f"icp_{k}": v for k, v in settings_dict(self.settings).items()}

    def __call__(self, task: FrameTask[IcpPairInput]) -> IcpStats:
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
        return IcpStats(fitness=doc["fitness"], inlier_rmse_m=doc["inlier_rmse_m"])


@dataclass(frozen=True)
class AccumulateStats(FrameStats):
    """One frame: scans merged, its window (``first..last`` frame), points in, kept and
    removed by reason, valid pixels of the map (of them frame t's own), pixels, PNG pixels
    clipped at 256 m."""

    scans: int
    window: str
    points: int
    kept: int
    non_finite: int
    behind_camera: int
    beyond_max_depth: int
    outside_image: int
    masked: int
    inconsistent: int
    occluded: int
    valid_pixels: int
    own_pixels: int
    pixels: int
    clipped_png: int


@dataclass(frozen=True)
class AccumulateJob(BatchJob[AccumulateInput]):
    """``sparsetools accumulate`` (picklable): per frame read the window, merge, write the map
    and its calibration. With ICP poses, the pairs' batch runs first (:meth:`before`)."""

    command: ClassVar[str] = "accumulate"
    noun: ClassVar[str] = "accumulated depth maps"
    stats_type: ClassVar[type[FrameStats]] = AccumulateStats
    parent_only: ClassVar[tuple[str, ...]] = ("frames",)

    settings: AccumulateRunSettings = field(default_factory=AccumulateRunSettings)
    frames: tuple[Frame, ...] | None = None
    #: How another command names the recorded settings in messages (``dataset kitti-raw``:
    #: ``window`` is its ``--gt-neighbours``).
    option_aliases: tuple[tuple[str, str], ...] = ()

    @property
    def icp(self) -> bool:
        return self.settings.pose_source == "icp"

    def planned(self, frames: list[Frame]) -> AccumulateJob:
        """Keep the frames (for the ICP stage) and check the first frame's calibration: an
        error every frame would have (no image size) is reported before anything is
        written."""
        if not frames:
            raise ParameterError("no frames to accumulate")
        from ..io.calib import frame_calibration

        f, size = frames[0], self.settings.image_size
        try:
            frame_calibration(calib_path=f.calib, calibration=f.calibration, image_size=size,
                              image=f.image if size is None else None,
                              resize_to=self.settings.resize_to)  # fmt: skip
        except ParameterError:
            raise
        except SparsetoolsError:  # that frame's own problem: its job reports it
            pass
        return replace(self, frames=tuple(frames))

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[AccumulateInput]]:
        """One task per frame, sequence by sequence: its window's scans and their poses (or
        the ICP files of their pairs)."""
        out, k, icp = Path(out_dir), self.settings.window, self.icp
        tasks = []
        for seq, fs in sequences_of(frames).items():
            if len(fs) < 2 * k + 1:
                log.warning("sequence '%s' has %d frame(s), fewer than the %d of --neighbours "
                            "%d: every window is clipped to frames %s..%s", seq, len(fs),
                            2 * k + 1, k, fs[0].key.frame, fs[-1].key.frame)  # fmt: skip
            pair_files = [FrameKey(seq, f.key.frame).path(out / ICP_DIR, ".json") for f in fs]
            for i, t in enumerate(fs):
                lo, hi = max(0, i - k), min(len(fs), i + k + 1)
                window = fs[lo:hi]
                sized = self.settings.image_size is None and t.image is not None
                sources = [w.cloud for w in window]
                sources += [p for p in (t.calib, t.image if sized else None, t.mask)
                            if p is not None]  # fmt: skip
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
                    mask=None if t.mask is None else str(t.mask),
                )
                outputs = {"depth": t.key.path(out, ".png"),
                           "calib": t.key.path(out, ".json", prefix="calib")}  # fmt: skip
                tasks.append(FrameTask(t.key, inp, outputs, tuple(dict.fromkeys(sources))))
        return tasks

    def record(self) -> dict:
        return self.settings.record()[0]

    def option_names(self) -> dict:
        return {**self.settings.record()[1], **dict(self.option_aliases)}

    def before(self, out_dir: Path, batch: Batch) -> dict:
        """With ICP poses: register every consecutive pair first (its own resumable batch in
        ``OUT/icp``, in this run's lock); the totals of that stage."""
        if not self.icp or self.settings.window == 0:
            if batch.overwrite:  # the folder is this run's: an earlier run's ICP poses go
                clear_recorded(out_dir / ICP_DIR)
            return {}
        pairs = IcpPairJob(self.settings.icp)
        if not pairs.tasks(list(self.frames), out_dir / ICP_DIR):
            return {}
        summary = run_job(pairs, self.frames, out_dir / ICP_DIR, batch=batch, desc="icp")
        stats = pairs.stats(summary)
        return {
            "icp": {
                "pairs": len(summary.results), "computed": len(summary.done),
                "failed": len(summary.failed),
                "fitness_min": min((st.fitness for st in stats), default=0.0),
                "inlier_rmse_max_m": max((st.inlier_rmse_m for st in stats), default=0.0),
                "per_pair": {r.frame_id: {"fitness": st.fitness,
                                          "inlier_rmse_m": st.inlier_rmse_m}
                             for r, st in zip(summary.ok, stats, strict=True)},
            }
        }  # fmt: skip

    def __call__(self, task: FrameTask[AccumulateInput]) -> AccumulateStats:
        from ..io.calib import write_json_calib
        from ..io.image import write_depth_png
        from ..io.pointcloud import read_points
        from ..ops.accumulate import accumulate_scans
        from ..ops.registration import chain_poses

        inp, s = task.inputs, self.settings
        calib = _calibration(inp, s.image_size, s.resize_to)
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
                         calibration=calib.source,
                         **({"resize_to": list(s.resize_to)} if s.resize_to else {}))  # fmt: skip
        c = res.counts
        return AccumulateStats(
            scans=len(scans),
            window="..".join(FrameKey.parse(inp.frames[i]).frame for i in (0, -1)),
            points=c.points, kept=c.kept, **{r: getattr(c, r) for r in _REASONS},
            valid_pixels=int(np.count_nonzero(res.depth)),
            own_pixels=int(np.count_nonzero(res.source == inp.reference)),
            pixels=int(res.depth.size), clipped_png=int(clipped),
        )  # fmt: skip

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Totals: window, pose_source, clipped_windows, valid_pixels, density_pct, points,
        kept, removed (by reason), removed_per_frame."""
        k = self.settings.window
        rows = list(zip(summary.ok, self.stats(summary), strict=True))
        pixels = sum(st.pixels for _, st in rows)
        valid = sum(st.valid_pixels for _, st in rows)
        clipped = [(r, st) for r, st in rows if st.scans < 2 * k + 1]
        totals = {
            "window": k,
            "pose_source": self.settings.pose_source,
            "clipped_windows": len(clipped),
            "valid_pixels": int(valid),
            "density_pct": round(100.0 * valid / pixels, 4) if pixels else 0.0,
            "points": sum(st.points for _, st in rows),
            "kept": sum(st.kept for _, st in rows),
            "removed": {reason: sum(getattr(st, reason) for _, st in rows) for reason in _REASONS},
            "removed_per_frame": {
                r.frame_id: {n: getattr(st, n) for n in ("occluded", "inconsistent", "masked")}
                for r, st in rows
            },
        }
        if clipped:
            totals["clipped_window_frames"] = {r.frame_id: st.window for r, st in clipped}
        return totals


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


def accumulation_job(
    paths: list,
    *,
    window: int = 5,
    accumulate: AccumulateSettings | None = None,
    icp: bool | None = False,
    icp_settings: IcpSettings | None = None,
    calib=None,
    image=None,
    poses=None,
    poses_frame: str = "auto",
    mask=None,
    image_size: tuple[int, int] | None = None,
    camera: int = 2,
    resize_to: tuple[int, int] | None = None,
) -> tuple[AccumulateJob, list[Frame]]:
    """The job and frames of an accumulation of ``paths``: what ``sparsetools accumulate``
    runs, and ``dataset kitti-raw --gt accumulated``.

    Parameters
    ----------
    paths : list of path-like
        What :func:`~sparsetools.io.sources.poses.accumulation_frames` reads.
    window : int
        K: frames t-K..t+K.
    accumulate : AccumulateSettings, optional
        The merge and its filters.
    icp : bool or None
        Poses by ICP between consecutive scans; None: the input's own poses when every frame
        has one, else ICP (:func:`~sparsetools.io.sources.poses.accumulation_inputs`).
    icp_settings : IcpSettings, optional
    calib, image, poses, poses_frame, mask, image_size, camera
        As the command's options.
    resize_to : (width, height), optional
        The maps at exactly this size (``dataset kitti-raw --resize-to``).

    Returns
    -------
    job : AccumulateJob
        Its ``settings.pose_source`` says where the poses come from (``icp``, ``kitti-oxts``...).
    frames : list of Frame
    """
    inputs = accumulation_inputs(list(paths), calib=calib, image=image, poses=poses,
                                 poses_frame=poses_frame, icp=icp, mask=mask,
                                 camera=camera)  # fmt: skip
    settings = AccumulateRunSettings(
        window=window,
        pose_source=inputs.pose_source,
        poses_frame=poses_frame,
        mask=mask is not None,
        image_size=image_size,
        icp=IcpSettings() if icp_settings is None else icp_settings,
        accumulate=AccumulateSettings() if accumulate is None else accumulate,
        resize_to=resize_to,
    )
    return AccumulateJob(settings), inputs.frames
