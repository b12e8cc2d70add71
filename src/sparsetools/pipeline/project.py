"""Batch job of ``sparsetools project``: point clouds to sparse depth maps.

Frames come from :mod:`sparsetools.io.sources` (cloud files and folders, KITTI raw drives,
date folders and roots, KITTI object, nuScenes with multi-sweep accumulation); build tasks
with :func:`project_tasks` and run them with :func:`run_project`.

Outputs, per frame with key ``<sequence>/<frame>`` (a flat input has no ``<sequence>/``):

- ``--format png``: ``OUT/<sequence>/<frame>.png`` (KITTI uint16, depth * 256, 0 = empty);
- ``--format npy``: ``OUT/<sequence>/<frame>.npy`` (float32 metres, 0 = empty);
- ``--format parquet``: one row of ``OUT/sparse.parquet`` (frame id, width, height, fx, fy,
  cx, cy, list columns u uint16, v uint16, depth float32 exact). Each frame first writes
  ``OUT/sparse.parts/<sequence>/<frame>.parquet``; at the end of the run the parts and the
  rows of an existing ``sparse.parquet`` are merged into a new ``sparse.parquet`` (atomically,
  sorted by frame id) and the parts are removed. An interrupted run keeps its parts and
  resumes from them.
- always ``OUT/calib/<sequence>/<frame>.json``: the calibration of the map (after resize and
  crop), which :func:`sparsetools.io.calib.load_calibration` reads.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..calibration import Calibration
from ..errors import FormatError, OutputError, ParameterError, SparsetoolsError
from ..io.atomic import atomic_path
from ..io.containment import remove_output
from ..io.sources import Frame, FrameKey, Sweep
from ..validate import (
    check_choice,
    check_flag,
    check_non_negative,
    check_ordered,
    check_positive,
    parse_crop,
    parse_size,
)
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask

__all__ = [
    "FORMATS",
    "PARQUET_NAME",
    "ProjectInput",
    "ProjectJob",
    "ProjectSettings",
    "ProjectStats",
    "resolve_calibration",
]

log = logging.getLogger(__name__)

FORMATS = ("png", "npy", "parquet")
PARQUET_NAME = "sparse.parquet"
PARTS_DIR = "sparse.parts"
_ROWS_PER_GROUP = 64


@dataclass(frozen=True)
class ProjectSettings:
    """Options of a projection run (the same for every frame).

    Attributes
    ----------
    fmt : {"png", "npy", "parquet"}
    min_depth, max_depth : float, metres
        Keep points with ``min_depth < depth <= max_depth`` (max_depth None: no limit).
    pixel_offset : {0, -1}
        Added to rounded pixel coordinates (-1 reproduces monodepth2).
    resize : float, optional
        Scale the image (and intrinsics) by this factor first.
    crop : (top, left, height, width), optional
        Then crop to this window (in resized pixels).
    camera : int or str
        KITTI camera index or nuScenes camera name, passed to the calibration reader.
    image_size : (width, height), optional
        Size of the camera image before resize/crop; overrides calibration and image.
    filter_occluded : bool
        Drop the points the camera cannot see (see-through points behind a foreground edge,
        :func:`sparsetools.ops.occlusion.filter_occluded` with its defaults) from the map.
    resize_to : (width, height), optional
        Instead of ``resize``: bring the image (and intrinsics, each axis by its own factor)
        to exactly this size first (``dataset kitti-raw --resize-to``).
    """

    fmt: str = field(default="png", metadata={"option": "--format"})
    min_depth: float = 0.1
    max_depth: float | None = None
    pixel_offset: int = 0
    resize: float | None = None
    crop: tuple[int, int, int, int] | None = None
    camera: int | str = 2
    image_size: tuple[int, int] | None = None
    filter_occluded: bool = field(
        default=False, metadata={"option": "--filter-occluded", "omit_default": True}
    )
    resize_to: tuple[int, int] | None = field(
        default=None, metadata={"option": "--resize-to", "omit_default": True}
    )

    def __post_init__(self) -> None:
        check_choice(self.fmt, "--format", FORMATS)
        check_flag(self.filter_occluded, "--filter-occluded")
        check_non_negative(self.min_depth, "min_depth")
        check_positive(self.max_depth, "max_depth", allow_none=True)
        check_ordered(self.min_depth, self.max_depth, "min_depth", "max_depth")
        check_choice(self.pixel_offset, "pixel_offset", (0, -1))
        check_positive(self.resize, "resize", allow_none=True)
        if self.crop is not None:
            object.__setattr__(self, "crop", parse_crop(self.crop))
        if self.image_size is not None:
            object.__setattr__(self, "image_size", parse_size(self.image_size))
        if self.resize_to is not None:
            object.__setattr__(self, "resize_to", parse_size(self.resize_to, "--resize-to"))
            if self.resize is not None:
                raise ParameterError("--resize and --resize-to exclude each other",
                                     param="resize_to")  # fmt: skip


@dataclass(frozen=True)
class ProjectInput:
    """One frame's inputs: the key sweep, earlier sweeps, and where its calibration comes from.

    Attributes
    ----------
    cloud : str
    sweeps : tuple of Sweep
        Earlier sweeps with their transform into the key sweep's frame (nuScenes).
    calib_path : str, optional
        Calibration file or KITTI raw folder (when ``calibration`` is None).
    calibration : Calibration, optional
        Already resolved (shared by the batch, or computed by the source).
    image : str, optional
        Image whose size the map takes.
    """

    cloud: str
    sweeps: tuple[Sweep, ...] = ()
    calib_path: str | None = None
    calibration: Calibration | None = None
    image: str | None = None


# -- calibration of one frame --------------------------------------------------------------------


def resolve_calibration(inp: ProjectInput, settings: ProjectSettings) -> Calibration:
    """The calibration a frame's depth map uses: loaded, sized and checked against the
    frame's image and cloud, resized, cropped (:func:`sparsetools.io.calib.frame_calibration`,
    :func:`~sparsetools.io.calib.check_sensor`)."""
    from ..io.calib import check_sensor, frame_calibration

    calib = frame_calibration(
        calib_path=inp.calib_path,
        calibration=inp.calibration,
        camera=settings.camera,
        image=inp.image,
        image_size=settings.image_size,
        resize=settings.resize,
        crop=settings.crop,
        resize_to=settings.resize_to,
    )
    check_sensor(calib, inp.cloud)
    return calib


# -- the per-frame job ---------------------------------------------------------------------------


def load_frame_points(cloud, sweeps=()) -> np.ndarray:
    """The points a frame projects: the key sweep ``cloud`` and its earlier ``sweeps``
    (:class:`~sparsetools.io.sources.Sweep`) moved into its sensor frame, as this job reads
    them (``dataset --store-points`` stores the same points)."""
    return _load_points(ProjectInput(str(cloud), tuple(sweeps)))


def _load_points(inp: ProjectInput) -> np.ndarray:
    from ..io.pointcloud import read_points
    from ..ops.projection import accumulate_sweeps

    key = read_points(inp.cloud)
    if not inp.sweeps:
        return key
    loaded = [(key, np.eye(4))]
    for s in inp.sweeps:
        T = (
            np.eye(4)
            if s.T_key_from_sweep is None
            else np.asarray(s.T_key_from_sweep).reshape(4, 4)
        )
        loaded.append((read_points(s.path), T))
    widths = {p.shape[1] for p, _ in loaded}
    if len(widths) > 1:
        raise FormatError(f"sweeps have different columns ({sorted(widths)}): {inp.cloud}")
    return accumulate_sweeps(loaded)


def _parquet_row(frame_id: str, depth: np.ndarray, calib: Calibration):
    import pyarrow as pa

    from ..ops.projection import sparse_from_depth

    u, v, d = sparse_from_depth(depth)
    offsets = pa.array([0, u.shape[0]], type=pa.int32())

    def lst(values, typ):
        return pa.ListArray.from_arrays(offsets, pa.array(values, type=typ))

    return pa.table(
        {
            "frame": pa.array([frame_id], type=pa.string()),
            "width": pa.array([calib.width], type=pa.int32()),
            "height": pa.array([calib.height], type=pa.int32()),
            "fx": pa.array([calib.fx]),
            "fy": pa.array([calib.fy]),
            "cx": pa.array([calib.cx]),
            "cy": pa.array([calib.cy]),
            "u": lst(u, pa.uint16()),
            "v": lst(v, pa.uint16()),
            "depth": lst(d, pa.float32()),
        }
    )


@dataclass(frozen=True)
class ProjectStats(FrameStats):
    """One frame's projection: points read, points inside the image (before the z-buffer),
    valid pixels of the map, its pixel count, PNG pixels clipped at 256 m, whether the map is
    empty (1) and why."""

    points_in: int
    points_in_image: int
    valid_pixels: int
    pixels: int
    clipped: int
    empty: int
    empty_reason: str | None = None
    occluded: int | None = None  # pixels removed by --filter-occluded (None: filter off)


@dataclass(frozen=True)
class ProjectJob(BatchJob[ProjectInput]):
    """``sparsetools project``: point clouds to sparse depth maps (picklable).

    Attributes
    ----------
    settings : ProjectSettings
    calibration : Calibration, optional
        One calibration for every frame: given, or the calibration file the frames share,
        read once by :meth:`planned`.
    """

    command: ClassVar[str] = "project"
    noun: ClassVar[str] = "depth maps"
    tasks_per_frame: ClassVar[bool] = True
    stats_type: ClassVar[type[FrameStats]] = ProjectStats

    settings: ProjectSettings
    calibration: Calibration | None = None

    def planned(self, frames: list[Frame]) -> ProjectJob:
        """Read the calibration the frames share once, and check the settings on the first
        frame (no image size, a crop that does not fit): an error every frame would have is
        reported once, before anything is written."""
        from ..io.calib import load_calibration

        if not frames:
            raise ParameterError("no frames to project")
        camera = self.settings.camera
        if isinstance(camera, str):
            kitti = sorted(str(f.calib) for f in frames
                           if f.calib is not None and f.calib.suffix.lower() != ".json")  # fmt: skip
            if kitti:
                raise ParameterError(
                    f"{camera!r} is a name, which only JSON calibrations use; {kitti[0]} is a "
                    "KITTI calibration: give an index 0-3",
                    param="camera",
                )
        job = self
        paths = {f.calib for f in frames if f.calibration is None}
        if self.calibration is None and paths:
            if None in paths:
                raise ParameterError("no calibration: give --calib")
            if len(paths) == 1 and len(frames) > 1:
                job = replace(self, calibration=load_calibration(next(iter(paths)), camera=camera))
        try:
            resolve_calibration(job._input(frames[0]), self.settings)
        except ParameterError:
            raise
        except SparsetoolsError:  # that frame's own problem: its job reports it
            pass
        return job

    def _input(self, f: Frame) -> ProjectInput:
        calib = f.calibration if f.calibration is not None else self.calibration
        return ProjectInput(
            cloud=str(f.cloud),
            sweeps=f.sweeps,
            calib_path=None if calib is not None or f.calib is None else str(f.calib),
            calibration=calib,
            image=None if f.image is None else str(f.image),
        )

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[ProjectInput]]:
        """One task per frame: the map ``OUT/<sequence>/<frame>.<fmt>`` (a part of the table
        for parquet) and its calibration ``OUT/calib/<sequence>/<frame>.json``."""
        s = self.settings
        tasks = []
        for f in frames:
            image_source = () if (s.image_size is not None or f.image is None) else (f.image,)
            sources = (f.cloud, *(sw.path for sw in f.sweeps), *([f.calib] if f.calib else []),
                       *image_source, *f.extra_inputs)  # fmt: skip
            tasks.append(FrameTask(f.key, self._input(f), _outputs(out_dir, f.key, s.fmt),
                                   tuple(sources)))  # fmt: skip
        return tasks

    def shared_outputs(self, out_dir: Path) -> tuple[Path, ...]:
        return (out_dir / PARQUET_NAME,) if self.settings.fmt == "parquet" else ()

    def is_complete(self, out_dir: Path):
        if self.settings.fmt != "parquet":
            return None
        target = out_dir / PARQUET_NAME

        def complete(t):  # a merged frame: its part is gone, the table holds it
            return t.outputs["calib"].is_file() and (
                t.outputs["depth"].is_file() or target.is_file()
            )

        return complete

    def prepare(self) -> None:
        """Load the libraries every frame uses (OpenCV's PNG codec, the calibration writer):
        called once in the parent before a pool forks, so workers inherit them."""
        from ..io.calib import write_json_calib  # noqa: F401
        from ..io.image import encode_depth_png

        encode_depth_png(np.zeros((2, 2), np.float32))

    def __call__(self, task: FrameTask[ProjectInput]) -> ProjectStats:
        from ..io.calib import write_json_calib
        from ..io.image import write_depth_png
        from ..ops.projection import project_points

        s, inp = self.settings, task.inputs
        points = _load_points(inp)  # a damaged cloud is named before a mismatched calibration
        calib = resolve_calibration(inp, s)
        depth, n_in_image = project_points(
            points,
            calib,
            min_depth=s.min_depth,
            max_depth=s.max_depth,
            pixel_offset=s.pixel_offset,
            return_count=True,
        )
        occluded = None
        if s.filter_occluded:
            from ..ops.occlusion import filter_occluded

            depth, removed = filter_occluded(depth, fx=calib.fx)
            occluded = int(np.count_nonzero(removed))
        depth_out = task.outputs["depth"]
        clipped = 0
        if s.fmt == "png":
            clipped = write_depth_png(depth_out, depth)
        elif s.fmt == "npy":
            with atomic_path(depth_out) as tmp, open(tmp, "wb") as fh:
                np.save(fh, depth)
        else:
            import pyarrow.parquet as pq

            table = _parquet_row(task.frame_id, depth, calib)
            with atomic_path(depth_out) as tmp:
                pq.write_table(table, tmp)
        write_json_calib(
            task.outputs["calib"],
            calib,
            frame=task.frame_id,
            cloud=[inp.cloud, *(str(sw.path) for sw in inp.sweeps)],
            image=inp.image,
            resize=s.resize,
            crop=s.crop,
            pixel_offset=s.pixel_offset,
            min_depth=s.min_depth,
            max_depth=s.max_depth,
            calibration=calib.source,
            # only when set: the files of the other settings stay as they were
            **({"resize_to": list(s.resize_to)} if s.resize_to is not None else {}),
        )
        valid = int(np.count_nonzero(depth))
        reason = None
        if valid == 0:
            if points.shape[0] == 0:
                reason = "the cloud has no points"
            else:
                reason = (
                    f"none of its {points.shape[0]} points is in front of the camera "
                    f"(depth > {s.min_depth} m) and inside the image"
                )
            log.warning("frame %s: empty depth map written: %s", task.frame_id, reason)
        return ProjectStats(
            points_in=int(points.shape[0]),
            points_in_image=int(n_in_image),
            valid_pixels=valid,
            pixels=int(depth.size),
            clipped=int(clipped),
            empty=int(valid == 0),
            empty_reason=reason,
            occluded=occluded,
        )

    def finish(self, summary: RunSummary, tasks: list[FrameTask], out_dir: Path) -> dict:
        """Merge the parquet parts (``--format parquet``); the totals: points_in,
        points_in_image, valid_pixels, density_pct (valid pixels / pixels of the frames),
        clipped, empty_maps, format, output, frames_per_s."""
        if self.settings.fmt == "parquet":
            target = out_dir / PARQUET_NAME
            try:
                _write_parquet(out_dir, tasks, keep_old=not summary.overwrite)
            except OutputError:
                raise
            except Exception as exc:  # pyarrow: a schema clash with an older table, I/O
                raise OutputError(
                    f"cannot merge the frames into {target} ({_first_line(exc)}); the per-frame "
                    f"parts are kept in {out_dir / PARTS_DIR}: rerun with --overwrite to "
                    "rebuild the table"
                ) from exc
        # one frame's statistics at a time: a run over a million frames holds none of them
        n = dict.fromkeys(("pixels", "valid", "points_in", "points_in_image", "clipped",
                           "occluded", "empty"), 0)  # fmt: skip
        shown = []
        for r, st in self.iter_stats(summary):
            n["pixels"] += st.pixels
            n["valid"] += st.valid_pixels
            n["points_in"] += st.points_in
            n["points_in_image"] += st.points_in_image
            n["clipped"] += st.clipped
            n["occluded"] += st.occluded or 0
            if st.empty:
                n["empty"] += 1
                if len(shown) < 3:
                    shown.append(f"{r.frame_id} ({st.empty_reason or ''})")
        if n["empty"]:
            more = f" and {n['empty'] - 3} more" if n["empty"] > 3 else ""
            log.warning("%d empty depth map(s): %s%s", n["empty"], ", ".join(shown), more)
        seconds = summary.seconds
        pixels, valid = n["pixels"], n["valid"]
        occluded = {"occluded_pixels": n["occluded"]} if self.settings.filter_occluded else {}
        return {
            **occluded,
            "points_in": n["points_in"],
            "points_in_image": n["points_in_image"],
            "valid_pixels": int(valid),
            "density_pct": round(100.0 * valid / pixels, 4) if pixels else 0.0,
            "clipped": n["clipped"],
            "empty_maps": n["empty"],
            "format": self.settings.fmt,
            "output": str(out_dir / PARQUET_NAME) if self.settings.fmt == "parquet"
            else str(out_dir),
            "frames_per_s": round(summary.counts()["processed"] / seconds, 2)
            if seconds > 0 else 0.0,
        }  # fmt: skip


# -- outputs and the parquet table ---------------------------------------------------------------


def _outputs(out_dir: Path, key: FrameKey, fmt: str) -> dict[str, Path]:
    if fmt == "parquet":
        depth = key.path(out_dir, ".parquet", prefix=PARTS_DIR)
    else:
        depth = key.path(out_dir, f".{fmt}")
    return {"depth": depth, "calib": key.path(out_dir, ".json", prefix="calib")}


def _first_line(exc: Exception) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def _write_parquet(out_dir: Path, tasks: list[FrameTask], keep_old: bool) -> int:
    """Merge the parts of ``tasks`` and the old file's rows into ``sparse.parquet``."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    target = out_dir / PARQUET_NAME
    sources: dict[str, tuple[str, object]] = {}
    old = None
    if keep_old and target.is_file():
        try:
            old = pq.ParquetFile(target)
            for rg in range(old.num_row_groups):
                for fid in old.read_row_group(rg, columns=["frame"]).column("frame").to_pylist():
                    sources[fid] = ("old", rg)
        except Exception as exc:  # pyarrow raises several types for a corrupt file
            raise OutputError(
                f"{target}: exists but is not a sparse depth table of this command "
                f"({_first_line(exc)}); remove it or use --overwrite"
            ) from exc
    parts = []
    for t in tasks:
        part = t.outputs["depth"]
        if part.is_file():
            sources[t.frame_id] = ("part", part)
            parts.append(part)
    if not parts:
        return 0
    cached_rg, cached_table = None, None
    pending: list = []
    with atomic_path(target) as tmp:
        writer = None
        try:
            for fid in sorted(sources):
                kind, where = sources[fid]
                if kind == "part":
                    row = pq.read_table(where)
                else:
                    if cached_rg != where:
                        cached_rg, cached_table = where, old.read_row_group(where)
                    row = cached_table.filter(pc.equal(cached_table.column("frame"), fid))
                pending.append(row)
                if len(pending) >= _ROWS_PER_GROUP:
                    table = pa.concat_tables(pending)
                    writer = writer or pq.ParquetWriter(tmp, table.schema)
                    writer.write_table(table)
                    pending = []
            if pending:
                table = pa.concat_tables(pending)
                writer = writer or pq.ParquetWriter(tmp, table.schema)
                writer.write_table(table)
        finally:
            if writer is not None:
                writer.close()
    for part in parts:
        remove_output(out_dir, part)
    parts_dir = out_dir / PARTS_DIR
    if parts_dir.is_dir() and not parts_dir.is_symlink():
        for d in sorted((p for p in parts_dir.rglob("*") if p.is_dir()), reverse=True):
            with contextlib.suppress(OSError):
                d.rmdir()  # only empty folders go
        with contextlib.suppress(OSError):
            parts_dir.rmdir()
    return len(sources)
