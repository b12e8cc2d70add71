"""Batch job of ``sparsetools project``: point clouds to sparse depth maps.

Build tasks with :func:`tasks_from_frames` (clouds + calibration files, KITTI raw / object
layouts via :mod:`sparsetools.io.sources`) or :func:`nuscenes_tasks` (nuScenes tables, with
multi-sweep accumulation), then run them with :func:`run_project`.

Outputs, per frame ``<id>``:

- ``--format png``: ``OUT/<id>.png`` (KITTI uint16, depth * 256, 0 = empty);
- ``--format npy``: ``OUT/<id>.npy`` (float32 metres, 0 = empty);
- ``--format parquet``: one row of ``OUT/sparse.parquet`` (frame, width, height, fx, fy, cx,
  cy, list columns u uint16, v uint16, depth float32 exact). Each frame first writes
  ``OUT/sparse.parts/<id>.parquet``; at the end of the run the parts and the rows of an
  existing ``sparse.parquet`` are merged into a new ``sparse.parquet`` (atomically, sorted by
  frame) and the parts are removed. An interrupted run keeps its parts and resumes from them;
  frames already in ``sparse.parquet`` are skipped unless ``overwrite``.
- always ``OUT/calib/<id>.json``: the calibration of the map (after resize and crop), which
  :func:`sparsetools.io.calib.load_calibration` reads.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calibration import Calibration
from ..errors import FormatError, OutputError, ParameterError
from ..io.atomic import atomic_path
from ..io.image import check_pixel_count
from ..io.sources import SourceFrame, image_size_of
from .core import FrameResult, FrameTask, RunSummary, check_output_dir, run_frames

__all__ = [
    "FORMATS",
    "PARQUET_NAME",
    "ProjectSettings",
    "nuscenes_tasks",
    "project_frame",
    "resolve_calibration",
    "run_project",
    "tasks_from_frames",
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

    fmt: str = "png"
    min_depth: float = 0.1
    max_depth: float | None = None
    pixel_offset: int = 0
    resize: float | None = None
    crop: tuple[int, int, int, int] | None = None
    camera: int | str = 2
    image_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.fmt not in FORMATS:
            raise ParameterError(f"unknown format {self.fmt!r} (choose {', '.join(FORMATS)})")
        if not np.isfinite(self.min_depth) or self.min_depth < 0:
            raise ParameterError(f"min_depth must be >= 0, got {self.min_depth}")
        if self.max_depth is not None and not self.max_depth > self.min_depth:
            raise ParameterError(
                f"max_depth ({self.max_depth}) must be > min_depth ({self.min_depth})"
            )
        if self.pixel_offset not in (0, -1):
            raise ParameterError(f"pixel_offset must be 0 or -1, got {self.pixel_offset}")
        if self.resize is not None and not (np.isfinite(self.resize) and self.resize > 0):
            raise ParameterError(f"resize factor must be > 0, got {self.resize}")
        if self.crop is not None:
            if len(self.crop) != 4:
                raise ParameterError(f"crop must be TOP,LEFT,H,W, got {self.crop}")
            top, left, h, w = self.crop
            if top < 0 or left < 0 or h <= 0 or w <= 0:
                raise ParameterError(f"crop needs TOP, LEFT >= 0 and H, W > 0, got {self.crop}")
        if self.image_size is not None and min(self.image_size) <= 0:
            raise ParameterError(f"image size must be positive, got {self.image_size}")


# -- calibration of one frame --------------------------------------------------------------------


def resolve_calibration(inputs: dict) -> Calibration:
    """The calibration a frame's depth map uses: loaded, sized, resized, cropped.

    Image size, first found: ``settings.image_size``, the frame's image header, the
    calibration's own size (KITTI raw ``S_rect``, JSON ``width``/``height``, nuScenes).
    """
    from ..io.calib import load_calibration

    settings: ProjectSettings = inputs["settings"]
    calib = inputs.get("calib")
    if calib is None:
        if inputs.get("calib_path") is None:
            raise ParameterError("no calibration: give --calib")
        calib = load_calibration(inputs["calib_path"], camera=settings.camera)
    if settings.image_size is not None:
        calib = calib.with_size(*settings.image_size)
    elif inputs.get("image") is not None:
        calib = calib.with_size(*image_size_of(inputs["image"]))
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


def _load_points(sweeps) -> np.ndarray:
    from ..io.pointcloud import read_points
    from ..ops.projection import accumulate_sweeps

    if len(sweeps) == 1 and sweeps[0][1] is None:
        return read_points(sweeps[0][0])
    loaded = []
    for path, T in sweeps:
        pts = read_points(path)
        loaded.append((pts, np.eye(4) if T is None else T))
    widths = {p.shape[1] for p, _ in loaded}
    if len(widths) > 1:
        raise FormatError(f"sweeps have different columns ({sorted(widths)}): {sweeps[0][0]}")
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


def project_frame(task: FrameTask) -> dict:
    """Project one frame and write its depth map and calibration (atomically).

    Returns
    -------
    dict
        points_in, points_in_image (before the z-buffer), valid_pixels, pixels, clipped
        (PNG pixels clipped at 256 m), empty (1 if the map has no valid pixel) and, for an
        empty map, empty_reason.
    """
    from ..io.calib import write_json_calib
    from ..io.image import write_depth_png
    from ..ops.projection import project_points

    inputs = task.inputs
    settings: ProjectSettings = inputs["settings"]
    calib = resolve_calibration(inputs)
    points = _load_points(inputs["sweeps"])
    depth, n_in_image = project_points(
        points,
        calib,
        min_depth=settings.min_depth,
        max_depth=settings.max_depth,
        pixel_offset=settings.pixel_offset,
        return_count=True,
    )
    depth_out = Path(inputs["depth_out"])
    clipped = 0
    if settings.fmt == "png":
        clipped = write_depth_png(depth_out, depth)
    elif settings.fmt == "npy":
        with atomic_path(depth_out) as tmp, open(tmp, "wb") as fh:
            np.save(fh, depth)
    else:
        import pyarrow.parquet as pq

        table = _parquet_row(task.frame_id, depth, calib)
        with atomic_path(depth_out) as tmp:
            pq.write_table(table, tmp)
    write_json_calib(
        inputs["calib_out"],
        calib,
        frame=task.frame_id,
        cloud=[str(p) for p, _ in inputs["sweeps"]],
        image=inputs.get("image"),
        resize=settings.resize,
        crop=settings.crop,
        pixel_offset=settings.pixel_offset,
        min_depth=settings.min_depth,
        max_depth=settings.max_depth,
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
                f"(depth > {settings.min_depth} m) and inside the image"
            )
        stats["empty_reason"] = reason
        log.warning("frame %s: empty depth map written: %s", task.frame_id, reason)
    return stats


# -- task building -------------------------------------------------------------------------------


def _outputs(out_dir: Path, frame_id: str, fmt: str) -> tuple[Path, Path]:
    if fmt == "parquet":
        depth = out_dir / PARTS_DIR / f"{frame_id}.parquet"
    else:
        depth = out_dir / f"{frame_id}.{fmt}"
    return depth, out_dir / "calib" / f"{frame_id}.json"


def _task(frame_id, out_dir, settings, *, sweeps, calib=None, calib_path=None, image=None):
    depth_out, calib_out = _outputs(Path(out_dir), frame_id, settings.fmt)
    inputs = {
        "settings": settings,
        "sweeps": tuple(sweeps),
        "calib": calib,
        "calib_path": None if calib_path is None else str(calib_path),
        "image": None if image is None else str(image),
        "depth_out": str(depth_out),
        "calib_out": str(calib_out),
    }
    return FrameTask(frame_id, inputs, (depth_out, calib_out))


def tasks_from_frames(
    frames: list[SourceFrame],
    out_dir: str | os.PathLike,
    settings: ProjectSettings,
    *,
    calib: Calibration | None = None,
) -> list[FrameTask]:
    """One task per frame of :mod:`sparsetools.io.sources` (clouds, KITTI raw, KITTI object).

    Parameters
    ----------
    frames : list of SourceFrame
    out_dir : path-like
    settings : ProjectSettings
    calib : Calibration, optional
        Used for every frame (overrides the frames' calibration paths).

    A calibration path shared by every frame is read once, here, so a bad calibration file
    is reported before the batch starts.
    """
    from ..io.calib import load_calibration

    if not frames:
        raise ParameterError("no frames to project")
    shared = calib
    paths = {f.calib for f in frames}
    if isinstance(settings.camera, str):
        kitti = sorted(str(p) for p in paths if p is not None and p.suffix.lower() != ".json")
        if kitti:
            raise ParameterError(
                f"camera {settings.camera!r} is a name, which only JSON calibrations use; "
                f"{kitti[0]} is a KITTI calibration: give an index 0-3"
            )
    if shared is None:
        if None in paths:
            raise ParameterError("no calibration: give --calib")
        if len(paths) == 1:
            shared = load_calibration(next(iter(paths)), camera=settings.camera)
    return [
        _task(
            f.frame_id,
            out_dir,
            settings,
            sweeps=[(str(f.cloud), None)],
            calib=shared,
            calib_path=None if shared is not None else f.calib,
            image=f.image,
        )
        for f in frames
    ]


def nuscenes_tasks(
    root: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: ProjectSettings,
    *,
    version: str = "v1.0-mini",
    sensor: str = "RADAR_FRONT",
    camera: str = "CAM_FRONT",
    sweeps: int = 5,
) -> list[FrameTask]:
    """One task per nuScenes sample holding both ``sensor`` and ``camera`` key frames.

    Each task accumulates the key sweep and up to ``sweeps - 1`` previous sweeps of ``sensor``
    into the key sweep's sensor frame (each with its own ego pose), and projects with the
    chain key sensor -> ego (sensor time) -> global -> ego (camera time) -> camera. The frame
    id is the sample token.
    """
    from ..io.nuscenes import NuScenesTables
    from ..ops.projection import nuscenes_T_cam_from_sensor, rigid_inverse

    if sweeps < 1:
        raise ParameterError(f"--sweeps must be >= 1, got {sweeps}")
    tables = NuScenesTables(root, version)
    tasks = []
    missing = 0
    for sample in tables.samples():
        try:
            key = tables.sample_data(sample["token"], sensor)
            cam = tables.sample_data(sample["token"], camera)
        except FormatError:
            missing += 1
            continue
        T_global_from_key = tables.T_global_from_ego(key) @ tables.T_ego_from_sensor(key)
        T_cam_from_key = nuscenes_T_cam_from_sensor(
            tables.T_ego_from_sensor(key),
            tables.T_global_from_ego(key),
            tables.T_global_from_ego(cam),
            tables.T_ego_from_sensor(cam),
        )
        chain = []
        for k, sd in enumerate(tables.sweeps(key, sweeps)):
            if k == 0:
                T = None
            else:
                T = rigid_inverse(T_global_from_key) @ (
                    tables.T_global_from_ego(sd) @ tables.T_ego_from_sensor(sd)
                )
            chain.append((str(tables.path(sd)), T))
        image = tables.path(cam)
        w, h = cam.get("width") or None, cam.get("height") or None
        calib = Calibration(
            K=tables.intrinsics(cam),
            T_cam_from_sensor=T_cam_from_key,
            width=w,
            height=h,
            source=f"nuScenes {version} sample {sample['token']} {sensor}->{camera}",
        )
        tasks.append(
            _task(
                sample["token"],
                out_dir,
                settings,
                sweeps=chain,
                calib=calib,
                image=None if w and h else image,
            )
        )
    if not tasks:
        raise FormatError(
            f"{root}: no sample of {version} has key frames of both {sensor} and {camera}"
        )
    if missing:
        log.warning("%d sample(s) lack %s or %s and were left out", missing, sensor, camera)
    return tasks


# -- running -------------------------------------------------------------------------------------


def _input_files(tasks: list[FrameTask]) -> set[Path]:
    files = set()
    for t in tasks:
        for p, _ in t.inputs["sweeps"]:
            files.add(Path(p).resolve())
        for key in ("calib_path", "image"):
            if t.inputs.get(key):
                files.add(Path(t.inputs[key]).resolve())
    return files


def _first_line(exc: Exception) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def _parquet_frames(path: Path) -> list[str]:
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path, columns=["frame"]).column("frame").to_pylist()
    except Exception as exc:  # pyarrow raises several types for a corrupt file
        raise OutputError(
            f"{path}: exists but is not a sparse depth table of this command "
            f"({_first_line(exc)}); "
            "remove it or use --overwrite"
        ) from exc


def _write_parquet(out_dir: Path, tasks: list[FrameTask], keep_old: bool) -> int:
    """Merge the parts of ``tasks`` and the old file's rows into ``sparse.parquet``."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    target = out_dir / PARQUET_NAME
    sources: dict[str, tuple[str, object]] = {}
    old = None
    if keep_old and target.is_file():
        old = pq.ParquetFile(target)
        for rg in range(old.num_row_groups):
            for fid in old.read_row_group(rg, columns=["frame"]).column("frame").to_pylist():
                sources[fid] = ("old", rg)
    parts = []
    for t in tasks:
        part = Path(t.inputs["depth_out"])
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
                    mask = pc.equal(cached_table.column("frame"), fid)
                    row = cached_table.filter(mask)
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
    if parts_dir.is_dir() and not any(parts_dir.iterdir()):
        shutil.rmtree(parts_dir, ignore_errors=True)
    return len(sources)


def run_project(
    tasks: list[FrameTask],
    out_dir: str | os.PathLike,
    *,
    inputs: list[str | os.PathLike] = (),
    executor=None,
    overwrite: bool = False,
    on_error: str = "stop",
    progress: bool | None = None,
) -> dict:
    """Run projection tasks and return the summary.

    Parameters
    ----------
    tasks : list of FrameTask
        From :func:`tasks_from_frames` or :func:`nuscenes_tasks`.
    out_dir : path-like
        Output folder (created). Refused when it is a file, not writable, inside one of
        ``inputs`` (folders), or when an output would replace an input file.
    inputs : list of path-like
        Input folders given by the user.
    executor, overwrite, on_error, progress
        As :func:`sparsetools.pipeline.run_frames`.

    Returns
    -------
    dict
        frames, processed, skipped_existing, failed, points_in, points_in_image, valid_pixels,
        density_pct (valid pixels / pixels of the frames processed), clipped, empty_maps,
        format, output, seconds, frames_per_s, failures.
    """
    if not tasks:
        raise ParameterError("no frames to project")
    settings: ProjectSettings = tasks[0].inputs["settings"]
    out = check_output_dir(out_dir, inputs)
    in_files = _input_files(tasks)
    for t in tasks:
        for p in t.outputs:
            if Path(p).resolve() in in_files:
                raise OutputError(f"output {p} would replace an input file: choose another -o")
    # Settings errors (no image size, a crop that does not fit) would fail every frame:
    # report them once, before anything is written.
    try:
        resolve_calibration(tasks[0].inputs)
    except ParameterError:
        raise
    except Exception:  # that frame's own problem: its job reports it under the error policy
        pass

    todo, already = tasks, []
    target = out / PARQUET_NAME
    keep_old = settings.fmt == "parquet" and not overwrite and target.is_file()
    if keep_old:
        done = set(_parquet_frames(target))
        todo = [t for t in tasks if t.frame_id not in done or not Path(t.outputs[1]).is_file()]
        already = [t for t in tasks if t not in todo]
        for t in already:  # a part left by an interrupted merge is superseded by the file
            Path(t.inputs["depth_out"]).unlink(missing_ok=True)
    summary = run_frames(
        project_frame,
        todo,
        executor=executor,
        overwrite=overwrite,
        on_error=on_error,
        progress=progress,
        desc="project",
    )
    if already:
        skipped = {t.frame_id: FrameResult(t.frame_id, True, skipped=True) for t in already}
        by_id = {r.frame_id: r for r in summary.results}
        summary = RunSummary(
            [
                skipped.get(t.frame_id) or by_id[t.frame_id]
                for t in tasks
                if t.frame_id in skipped or t.frame_id in by_id
            ],
            summary.seconds,
        )
    if settings.fmt == "parquet":
        try:
            _write_parquet(out, tasks, keep_old)
        except OutputError:
            raise
        except Exception as exc:  # pyarrow: a schema clash with an older sparse.parquet, I/O
            raise OutputError(
                f"cannot merge the frames into {out / PARQUET_NAME} ({_first_line(exc)}); "
                "the per-frame parts "
                f"are kept in {out / PARTS_DIR}: rerun with --overwrite to rebuild the table"
            ) from exc
    return _summary(summary, settings, out)


def _summary(summary: RunSummary, settings: ProjectSettings, out: Path) -> dict:
    base = summary.as_dict()
    failures = base.pop("failures")
    pixels = summary.total("pixels")
    valid = summary.total("valid_pixels")
    empty = [r for r in summary.done if r.stats.get("empty")]
    if empty:
        shown = ", ".join(f"{r.frame_id} ({r.stats.get('empty_reason', '')})" for r in empty[:3])
        more = f" and {len(empty) - 3} more" if len(empty) > 3 else ""
        log.warning("%d empty depth map(s): %s%s", len(empty), shown, more)
    seconds = base.pop("seconds")
    result = {
        **base,
        "points_in": int(summary.total("points_in")),
        "points_in_image": int(summary.total("points_in_image")),
        "valid_pixels": int(valid),
        "density_pct": round(100.0 * valid / pixels, 4) if pixels else 0.0,
        "clipped": int(summary.total("clipped")),
        "empty_maps": len(empty),
        "format": settings.fmt,
        "output": str(out / PARQUET_NAME) if settings.fmt == "parquet" else str(out),
        "seconds": seconds,
        "frames_per_s": round(len(summary.done) / seconds, 2) if seconds > 0 else 0.0,
        "failures": failures,
    }
    return result
