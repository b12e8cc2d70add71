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

import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..calibration import Calibration
from ..errors import FormatError, OutputError, ParameterError, SparsetoolsError
from ..io.atomic import atomic_path
from ..io.sources import Frame, FrameKey, Sweep
from ..validate import check_choice, check_non_negative, check_positive, parse_crop
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames

__all__ = [
    "FORMATS",
    "PARQUET_NAME",
    "ProjectInput",
    "ProjectJob",
    "ProjectSettings",
    "project_tasks",
    "resolve_calibration",
    "run_project",
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
    """

    fmt: str = field(default="png", metadata={"option": "--format"})
    min_depth: float = 0.1
    max_depth: float | None = None
    pixel_offset: int = 0
    resize: float | None = None
    crop: tuple[int, int, int, int] | None = None
    camera: int | str = 2
    image_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        check_choice(self.fmt, "--format", FORMATS)
        check_non_negative(self.min_depth, "min_depth")
        check_positive(self.max_depth, "max_depth", allow_none=True)
        if self.max_depth is not None and not self.max_depth > self.min_depth:
            raise ParameterError(
                f"({self.max_depth}) must be > --min-depth ({self.min_depth})", param="max_depth"
            )
        if self.pixel_offset not in (0, -1):
            raise ParameterError(f"must be 0 or -1, got {self.pixel_offset}", param="pixel_offset")
        check_positive(self.resize, "resize", allow_none=True)
        if self.crop is not None:
            object.__setattr__(self, "crop", parse_crop(self.crop))
        if self.image_size is not None:
            w, h = self.image_size
            if int(w) <= 0 or int(h) <= 0:
                raise ParameterError(f"must be positive, got {self.image_size}", param="image_size")
            object.__setattr__(self, "image_size", (int(w), int(h)))


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
    """The calibration a frame's depth map uses: loaded, sized, resized, cropped.

    Image size, first found: ``settings.image_size``, the frame's image header, the
    calibration's own size (KITTI raw ``S_rect``, JSON ``width``/``height``, nuScenes).
    """
    from ..io.calib import load_calibration
    from ..io.image import check_pixel_count, image_size_of

    calib = inp.calibration
    if calib is None:
        if inp.calib_path is None:
            raise ParameterError("no calibration: give --calib")
        calib = load_calibration(inp.calib_path, camera=settings.camera)
    if settings.image_size is not None:
        calib = calib.for_size(*settings.image_size, given_by="--image-size")
    elif calib.width is not None and calib.height is not None and inp.calibration is not None:
        pass  # a size the source knows (nuScenes) wins over reading the image header
    elif inp.image is not None:
        calib = calib.for_size(*image_size_of(inp.image), given_by=f"image {inp.image}")
    elif calib.width is None or calib.height is None:
        raise ParameterError(
            "image size missing: give --image-size WxH or --image IMG "
            f"(calibration {calib.source or '?'} holds no size)"
        )
    if settings.resize is not None:
        calib = calib.resized(settings.resize)
    if settings.crop is not None:
        top, left, h, w = settings.crop
        calib = calib.cropped(top, left, h, w)
    # A size from an option or a calibration file is not bounded by anything else.
    check_pixel_count(calib.width, calib.height, "depth map")
    return calib


# -- the per-frame job ---------------------------------------------------------------------------


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
class ProjectJob:
    """The per-frame job of ``project`` (picklable): project one frame and write its outputs.

    Returns per frame: points_in, points_in_image (before the z-buffer), valid_pixels,
    pixels, clipped (PNG pixels clipped at 256 m), empty (1 if the map has no valid pixel)
    and, for an empty map, empty_reason.
    """

    settings: ProjectSettings

    def prepare(self) -> None:
        """Load the libraries every frame uses (OpenCV's PNG codec, the calibration writer):
        called once in the parent before a pool forks, so workers inherit them."""
        from ..io.calib import write_json_calib  # noqa: F401
        from ..io.image import encode_depth_png

        encode_depth_png(np.zeros((2, 2), np.float32))

    def __call__(self, task: FrameTask[ProjectInput]) -> dict:
        from ..io.calib import write_json_calib
        from ..io.image import write_depth_png
        from ..ops.projection import project_points

        s, inp = self.settings, task.inputs
        calib = resolve_calibration(inp, s)
        points = _load_points(inp)
        depth, n_in_image = project_points(
            points,
            calib,
            min_depth=s.min_depth,
            max_depth=s.max_depth,
            pixel_offset=s.pixel_offset,
            return_count=True,
        )
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
        )
        valid = int(np.count_nonzero(depth))
        stats = {
            "points_in": int(points.shape[0]),
            "points_in_image": int(n_in_image),
            "valid_pixels": valid,
            "pixels": int(depth.size),
            "clipped": int(clipped),
            "empty": int(valid == 0),
        }
        if valid == 0:
            if points.shape[0] == 0:
                reason = "the cloud has no points"
            else:
                reason = (
                    f"none of its {points.shape[0]} points is in front of the camera "
                    f"(depth > {s.min_depth} m) and inside the image"
                )
            stats["empty_reason"] = reason
            log.warning("frame %s: empty depth map written: %s", task.frame_id, reason)
        return stats


# -- task building -------------------------------------------------------------------------------


def _outputs(out_dir: Path, key: FrameKey, fmt: str) -> dict[str, Path]:
    if fmt == "parquet":
        depth = key.path(out_dir, ".parquet", prefix=PARTS_DIR)
    else:
        depth = key.path(out_dir, f".{fmt}")
    return {"depth": depth, "calib": key.path(out_dir, ".json", prefix="calib")}


def project_tasks(
    frames: list[Frame],
    out_dir: str | os.PathLike,
    settings: ProjectSettings,
    *,
    calibration: Calibration | None = None,
) -> list[FrameTask[ProjectInput]]:
    """One task per frame.

    Parameters
    ----------
    frames : list of Frame
        With ``cloud`` and a calibration (``calib`` path or ``calibration``).
    out_dir : path-like
    settings : ProjectSettings
    calibration : Calibration, optional
        Used for every frame (instead of the frames' calibrations).

    A calibration path shared by every frame is read once, here, so a bad calibration file
    is reported before the batch starts.
    """
    from ..io.calib import load_calibration

    if not frames:
        raise ParameterError("no frames to project")
    out = Path(out_dir)
    if isinstance(settings.camera, str):
        kitti = sorted(
            str(f.calib)
            for f in frames
            if f.calib is not None and f.calib.suffix.lower() != ".json"
        )
        if kitti:
            raise ParameterError(
                f"{settings.camera!r} is a name, which only JSON calibrations use; "
                f"{kitti[0]} is a KITTI calibration: give an index 0-3",
                param="camera",
            )
    shared = calibration
    paths = {f.calib for f in frames if f.calibration is None}
    if shared is None and paths:
        if None in paths:
            raise ParameterError("no calibration: give --calib")
        if len(paths) == 1 and len(frames) > 1:
            shared = load_calibration(next(iter(paths)), camera=settings.camera)
    tasks = []
    for f in frames:
        calib = f.calibration if f.calibration is not None else shared
        inp = ProjectInput(
            cloud=str(f.cloud),
            sweeps=f.sweeps,
            calib_path=None if calib is not None or f.calib is None else str(f.calib),
            calibration=calib,
            image=None if f.image is None else str(f.image),
        )
        image_source = () if (settings.image_size is not None or f.image is None) else (f.image,)
        sources = (f.cloud, *(s.path for s in f.sweeps), *([f.calib] if f.calib else []),
                   *image_source, *f.extra_inputs)  # fmt: skip
        tasks.append(FrameTask(f.key, inp, _outputs(out, f.key, settings.fmt), tuple(sources)))
    return tasks


# -- parquet table -------------------------------------------------------------------------------


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
        part.unlink(missing_ok=True)
    parts_dir = out_dir / PARTS_DIR
    if parts_dir.is_dir():
        for d in sorted((p for p in parts_dir.rglob("*") if p.is_dir()), reverse=True):
            if not any(d.iterdir()):
                d.rmdir()
        if not any(parts_dir.iterdir()):
            shutil.rmtree(parts_dir, ignore_errors=True)
    return len(sources)


# -- running -------------------------------------------------------------------------------------


def run_project(
    tasks: list[FrameTask[ProjectInput]],
    out_dir: str | os.PathLike,
    settings: ProjectSettings,
    *,
    batch: Batch | None = None,
    inputs: list[str | os.PathLike] = (),
) -> RunSummary:
    """Run projection tasks (from :func:`project_tasks`).

    Parameters
    ----------
    tasks : list of FrameTask
    out_dir : path-like
        Output folder (created). Refused when it is a file, not writable, inside one of
        ``inputs`` (folders), or when an output would replace an input file.
    settings : ProjectSettings
    batch : Batch, optional
    inputs : list of path-like
        Input folders given by the user.

    Returns
    -------
    RunSummary
        Totals: points_in, points_in_image, valid_pixels, density_pct (valid pixels / pixels
        of the frames processed), clipped, empty_maps, format, output, frames_per_s.
    """
    batch = batch or Batch()
    if not tasks:
        raise ParameterError("no frames to project")
    out = check_output_dir(out_dir, inputs)
    # Settings errors (no image size, a crop that does not fit) would fail every frame:
    # report them once, before anything is written.
    try:
        resolve_calibration(tasks[0].inputs, settings)
    except ParameterError:
        raise
    except SparsetoolsError:  # that frame's own problem: its job reports it
        pass
    target = out / PARQUET_NAME
    parquet = settings.fmt == "parquet"
    complete = None
    if parquet:

        def complete(t, _target=target):  # a merged frame: its part is gone, the table holds it
            return t.outputs["calib"].is_file() and (
                t.outputs["depth"].is_file() or _target.is_file()
            )

    spec = RunSpec(
        "project", out, settings, noun="depth maps", shared_outputs=(target,) if parquet else ()
    )
    summary = run_frames(ProjectJob(settings), tasks, batch=batch, spec=spec, complete=complete)
    if parquet:
        try:
            _write_parquet(out, tasks, keep_old=not batch.overwrite)
        except OutputError:
            raise
        except Exception as exc:  # pyarrow: a schema clash with an older sparse.parquet, I/O
            raise OutputError(
                f"cannot merge the frames into {target} ({_first_line(exc)}); the per-frame "
                f"parts are kept in {out / PARTS_DIR}: rerun with --overwrite to rebuild the table"
            ) from exc
    return _with_totals(summary, settings, out)


def _with_totals(summary: RunSummary, settings: ProjectSettings, out: Path) -> RunSummary:
    pixels = summary.total("pixels")
    valid = summary.total("valid_pixels")
    empty = [r for r in summary.ok if r.stats.get("empty")]
    if empty:
        shown = ", ".join(f"{r.frame_id} ({r.stats.get('empty_reason', '')})" for r in empty[:3])
        more = f" and {len(empty) - 3} more" if len(empty) > 3 else ""
        log.warning("%d empty depth map(s): %s%s", len(empty), shown, more)
    seconds = summary.seconds
    return summary.with_totals(
        {
            "points_in": int(summary.total("points_in")),
            "points_in_image": int(summary.total("points_in_image")),
            "valid_pixels": int(valid),
            "density_pct": round(100.0 * valid / pixels, 4) if pixels else 0.0,
            "clipped": int(summary.total("clipped")),
            "empty_maps": len(empty),
            "format": settings.fmt,
            "output": str(out / PARQUET_NAME) if settings.fmt == "parquet" else str(out),
            "frames_per_s": round(len(summary.done) / seconds, 2) if seconds > 0 else 0.0,
        }
    )
