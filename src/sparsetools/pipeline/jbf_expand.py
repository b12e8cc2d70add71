"""Batch job of ``sparsetools jbf-expand``: sparse radar depth to expanded depth + confidence.

Inputs, per frame (key ``<sequence>/<frame>``, matched across inputs by key):

- a radar depth PNG (KITTI uint16, e.g. written by ``sparsetools project``) or a nuScenes
  radar ``.pcd`` projected on the fly with the frame's calibration;
- the camera image (a file for a single frame, or a folder matched by frame);
- the focal lengths: ``--fx/--fy`` or a calibration (one file, or a folder of per-frame
  ``.json|.txt``);
- optionally the LiDAR depth map for the intrinsic-error table.

Outputs: ``OUT/<sequence>/<frame>.png`` (expanded depth, KITTI uint16, depth * 256) and,
unless disabled, ``OUT/<sequence>/<frame>_conf.png`` (confidence * 65535, uint16) or
``_conf.npy`` (float32); a flat input has no ``<sequence>/`` level.

With ``resize`` the image is resized with OpenCV (area interpolation when shrinking) and the
sparse maps (radar, LiDAR) are resized by moving each valid pixel to its scaled position
(``u' = rint(s (u + 0.5) - 0.5)``, pixel centres at integers), nearest depth winning: depths
are never interpolated. A ``.pcd`` input is projected directly at the resized resolution.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import Frame, FrameKey
from ..validate import check_positive
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames

__all__ = [
    "CONF_FORMATS",
    "METHODS",
    "JbfInput",
    "JbfJob",
    "JbfSettings",
    "format_intrinsic_table",
    "intrinsic_summary",
    "jbf_tasks",
    "radar_frames",
    "resize_sparse_depth",
    "run_jbf_expand",
]

log = logging.getLogger(__name__)

METHODS = ("jbf", "height-extend")
CONF_FORMATS = ("png", "npy")
RADAR_SUFFIXES = (".png", ".pcd")


@dataclass(frozen=True)
class JbfSettings:
    """Options of a run, the same for every frame (see :func:`sparsetools.ops.jbf.jbf_expand`).

    Attributes
    ----------
    method : {"jbf", "height-extend"}
    sigma_s, sigma_r, threshold, window_m, kernel, range_metric, conflict
        :func:`~sparsetools.ops.jbf.jbf_expand` options.
    below_m, above_m : float, metres
        :func:`~sparsetools.ops.jbf.height_extend` options (also for the table's baseline row).
    resize : float, optional
        Scale factor applied to the image, the radar and the LiDAR maps and the intrinsics.
    confidence : bool
        Write the confidence map.
    conf_format : {"png", "npy"}
    max_depth : float, metres
        LiDAR cap of the intrinsic error.
    """

    method: str = "jbf"
    sigma_s: float = 25.0
    sigma_r: float = 10.0
    threshold: float = 0.05
    window_m: tuple[float, float] = field(default=(2.35, 2.35), metadata={"option": "--window"})
    kernel: str = "jbf"
    range_metric: str = "gray"
    conflict: str = "nearest"
    below_m: float = 0.25
    above_m: float = 1.5
    resize: float | None = None
    confidence: bool = True
    conf_format: str = "png"
    max_depth: float = 80.0

    def check(self) -> None:
        """Validate every option before any frame runs (one clear error, no partial output)."""
        from ..ops.jbf import CONFLICTS, KERNELS, RANGE_METRICS, pruning_radius

        if self.method not in METHODS:
            raise ParameterError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.conf_format not in CONF_FORMATS:
            raise ParameterError(f"confidence format must be png or npy, got {self.conf_format!r}")
        for name in ("sigma_s", "sigma_r"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be finite and > 0, got {v}")
        if not (0.0 < float(self.threshold) <= 1.0):
            raise ParameterError(f"threshold must be in (0, 1], got {self.threshold}")
        if len(self.window_m) != 2 or not all(
            math.isfinite(float(v)) and float(v) > 0 for v in self.window_m
        ):
            raise ParameterError(f"window must be two sizes > 0 in metres, got {self.window_m}")
        if self.kernel not in KERNELS:
            raise ParameterError(f"kernel must be one of {', '.join(KERNELS)}, got {self.kernel!r}")
        if self.range_metric not in RANGE_METRICS:
            raise ParameterError(f"range metric must be gray or rgb, got {self.range_metric!r}")
        if self.conflict not in CONFLICTS:
            raise ParameterError(f"conflict must be one of {', '.join(CONFLICTS)}")
        for name in ("below_m", "above_m"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise ParameterError(f"{name} must be finite and >= 0, got {v}")
        if self.resize is not None and not (math.isfinite(self.resize) and self.resize > 0):
            raise ParameterError(f"resize factor must be > 0, got {self.resize}")
        if not (math.isfinite(self.max_depth) and self.max_depth > 0):
            raise ParameterError(f"max_depth must be > 0, got {self.max_depth}")
        pruning_radius(float(self.sigma_s), float(self.threshold))


# -- inputs -------------------------------------------------------------------------------------


def radar_frames(paths: list[str | os.PathLike]) -> list[Frame]:
    """Radar inputs as frames: files as given, folders expanded to their ``*.png`` / ``*.pcd``.

    In a folder, ``<frame>_sweep<k>.pcd`` (or ``.png``) is left out when ``<frame>.pcd`` (or
    ``.png``) is there too: those are the single sweeps of a merged multi-sweep frame (the
    layout ``synth-scene`` writes). A folder written by ``project`` is read through its record.
    """
    from ..io.sources import index_input, merge_frames
    from ..io.sources.tree import index_tree

    if not paths:
        raise ParameterError("no radar inputs given")

    def index(p: Path):
        if p.is_file() and p.suffix.lower() not in RADAR_SUFFIXES:
            raise FormatError(
                f"{p}: not a radar input (expected a depth .png or a nuScenes radar .pcd)"
            )
        if p.is_dir() and not any(p.iterdir()):
            raise FormatError(f"{p}: no radar depth PNG or .pcd file in this folder")
        try:
            return index_tree(p, RADAR_SUFFIXES, option="RADAR", role="depth")
        except FormatError:
            return index_input(p, "depth", option="RADAR")  # a KITTI depth-completion tree

    return merge_frames((index(p) for p in map(Path, paths)), "depth")


@dataclass(frozen=True)
class JbfInput:
    """One frame's files: radar (depth PNG or ``.pcd``), image, calibration, LiDAR depth."""

    radar: str
    image: str
    calib: str | None = None
    lidar: str | None = None


def jbf_tasks(
    frames: list[Frame],
    out_dir: str | os.PathLike,
    settings: JbfSettings,
    *,
    lidar: dict[FrameKey, Path] | None = None,
) -> list[FrameTask[JbfInput]]:
    """One task per frame (``depth`` = the radar input, ``image``, optional ``calib``; LiDAR
    depth maps by key); outputs ``OUT/<sequence>/<frame>.png`` and
    ``OUT/<sequence>/<frame>_conf.png``."""
    out = Path(out_dir)
    tasks = []
    for f in frames:
        outputs = {"depth": f.key.path(out, ".png")}
        if settings.confidence:
            outputs["confidence"] = f.key.path(out, f"_conf.{settings.conf_format}")
        lid = (lidar or {}).get(f.key)
        inp = JbfInput(
            radar=str(f.depth),
            image=str(f.image),
            calib=None if f.calib is None else str(f.calib),
            lidar=None if lid is None else str(lid),
        )
        sources = tuple(p for p in (f.depth, f.image, f.calib, lid) if p is not None)
        tasks.append(FrameTask(f.key, inp, outputs, sources))
    return tasks


# -- one frame ----------------------------------------------------------------------------------


def resize_sparse_depth(depth: np.ndarray, scale: float, size: tuple[int, int]) -> np.ndarray:
    """Resize a sparse depth map without inventing depths.

    Each valid pixel (u, v) moves to ``(rint(s (u + 0.5) - 0.5), rint(s (v + 0.5) - 0.5))``
    (pixel centres at integers, the intrinsics convention of METHODS.md), clipped into the new
    image; where several land in one pixel the nearest depth wins.

    Parameters
    ----------
    depth : (H, W) float, metres; 0 or non-finite = empty.
    scale : float (> 0)
    size : (width, height) of the result.

    Returns
    -------
    (height, width) float32, metres.
    """
    width, height = size
    depth = np.asarray(depth)
    valid = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(valid)
    d = depth[v, u].astype(np.float32)
    u2 = np.clip(np.rint(scale * (u + 0.5) - 0.5), 0, width - 1).astype(np.int64)
    v2 = np.clip(np.rint(scale * (v + 0.5) - 0.5), 0, height - 1).astype(np.int64)
    out = np.full(height * width, np.inf, dtype=np.float32)
    np.minimum.at(out, v2 * width + u2, d)
    out[np.isinf(out)] = 0
    return out.reshape(height, width)


def _resize_image(rgb: np.ndarray, size: tuple[int, int], scale: float) -> np.ndarray:
    import cv2

    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.resize(rgb, size, interpolation=interp)


def _frame_calibration(path: str, image_size: tuple[int, int]):
    from ..io.calib import load_calibration

    calib = load_calibration(path)
    if calib.width is not None and calib.height is not None:
        if (calib.width, calib.height) != image_size:
            raise ParameterError(
                f"calibration {path} is for {calib.width}x{calib.height} images but the image "
                f"is {image_size[0]}x{image_size[1]}"
            )
        return calib
    return calib.with_size(*image_size)


def _write_confidence(path: Path, confidence: np.ndarray, fmt: str) -> None:
    import cv2

    with atomic_path(path) as tmp:
        if fmt == "npy":
            with open(tmp, "wb") as fh:
                np.save(fh, confidence.astype(np.float32))
        else:
            c = np.clip(confidence.astype(np.float64), 0.0, 1.0)
            scaled = np.rint(c * 65535.0).astype(np.uint16)
            ok, buf = cv2.imencode(".png", scaled)
            if not ok:  # pragma: no cover - OpenCV always encodes uint16 PNG
                raise FormatError(f"{path}: OpenCV failed to encode the confidence PNG")
            tmp.write_bytes(buf.tobytes())


@dataclass(frozen=True)
class JbfJob:
    """The per-frame job of ``jbf-expand`` (picklable): read, (resize,) expand, write; returns
    seeds, points and, with LiDAR, the intrinsic errors."""

    settings: JbfSettings
    fx: float | None = None
    fy: float | None = None

    def __call__(self, task: FrameTask[JbfInput]) -> dict:
        from ..io.image import read_depth_png, read_image, write_depth_png
        from ..ops.intrinsic import intrinsic_error
        from ..ops.jbf import height_extend, jbf_expand

        inp, s = task.inputs, self.settings
        rgb = read_image(inp.image)
        size0 = (rgb.shape[1], rgb.shape[0])
        scale = s.resize if s.resize is not None and s.resize != 1.0 else None
        calib = _frame_calibration(inp.calib, size0) if inp.calib else None
        fx, fy = (calib.fx, calib.fy) if calib is not None else (float(self.fx), float(self.fy))
        if scale is not None:
            size = (max(1, round(size0[0] * scale)), max(1, round(size0[1] * scale)))
            rgb = _resize_image(rgb, size, scale)
            fx, fy = fx * scale, fy * scale
        else:
            size = size0

        radar_path = Path(inp.radar)
        if radar_path.suffix.lower() == ".pcd":
            from ..io.nuscenes import read_radar_pcd
            from ..ops.projection import project_points

            points = read_radar_pcd(radar_path)
            cam = calib.resized(scale).with_size(*size) if scale is not None else calib
            radar = project_points(points, cam)
        else:
            radar = read_depth_png(radar_path)
            if (radar.shape[1], radar.shape[0]) != size0:
                raise ParameterError(
                    f"radar depth {radar_path} is {radar.shape[1]}x{radar.shape[0]} but the "
                    f"image is {size0[0]}x{size0[1]}: they must have the same size"
                )
            if scale is not None:
                radar = resize_sparse_depth(radar, scale, size)

        if s.method == "jbf":
            depth, confidence = jbf_expand(
                radar,
                rgb,
                fx=fx,
                fy=fy,
                sigma_s=s.sigma_s,
                sigma_r=s.sigma_r,
                threshold=s.threshold,
                window_m=s.window_m,
                kernel=s.kernel,
                range_metric=s.range_metric,
                conflict=s.conflict,
            )
        else:
            depth = height_extend(radar, fy=fy, below_m=s.below_m, above_m=s.above_m)
            confidence = (depth > 0).astype(np.float32)

        stats = {
            "seeds": int(np.count_nonzero(radar > 0)),
            "points": int(np.count_nonzero(depth > 0)),
        }
        if inp.lidar:
            lidar = read_depth_png(inp.lidar)
            if (lidar.shape[1], lidar.shape[0]) != size0:
                raise ParameterError(
                    f"LiDAR depth {inp.lidar} is {lidar.shape[1]}x{lidar.shape[0]} but the "
                    f"image is {size0[0]}x{size0[1]}"
                )
            if scale is not None:
                lidar = resize_sparse_depth(lidar, scale, size)
            rows = {"raw": intrinsic_error(radar, lidar, max_depth=s.max_depth)}
            name = s.kernel if s.method == "jbf" else "height-extend"
            rows[name] = intrinsic_error(depth, lidar, max_depth=s.max_depth)
            if s.method == "jbf":
                baseline = height_extend(radar, fy=fy, below_m=s.below_m, above_m=s.above_m)
                rows["height-extend"] = intrinsic_error(baseline, lidar, max_depth=s.max_depth)
            stats["intrinsic"] = rows

        stats["clipped"] = write_depth_png(task.outputs["depth"], depth)
        if s.confidence:
            _write_confidence(task.outputs["confidence"], confidence, s.conf_format)
        return stats


# -- run and report -----------------------------------------------------------------------------


def run_jbf_expand(
    radar: list[str | os.PathLike],
    *,
    image: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: JbfSettings = JbfSettings(),
    calib: str | os.PathLike | None = None,
    fx: float | None = None,
    fy: float | None = None,
    lidar: str | os.PathLike | None = None,
    batch: Batch | None = None,
) -> RunSummary:
    """Expand every radar frame (see the module docstring).

    Parameters
    ----------
    radar : list of path-like
        Radar depth PNGs and/or radar ``.pcd`` files, or folders of them.
    image : path-like
        Camera image (one frame) or folder of images matched by frame.
    out_dir : path-like
    settings : JbfSettings
    calib : path-like, optional
        Calibration file (shared) or folder of per-frame ``.json|.txt``: gives fx, fy and,
        for ``.pcd`` inputs, the radar-to-camera projection.
    fx, fy : float, optional, pixels
        Focal lengths of the (unresized) image, instead of a calibration.
    lidar : path-like, optional
        LiDAR depth PNG (one frame) or folder matched by frame, for the intrinsic error.
    batch : Batch, optional

    Returns
    -------
    RunSummary
        Totals: mean_seeds, mean_points, expansion_factor and, with LiDAR, intrinsic_error
        (per frame and mean; frames up to date included, from the folder's record).
    """
    from ..io.sources import attach, index_input, match_keys

    batch = batch or Batch()
    settings.check()
    if calib is None:
        if fx is None or fy is None:
            raise ParameterError("give the focal lengths: --fx and --fy, or --calib")
        check_positive(fx, "fx")
        check_positive(fy, "fy")
    elif fx is not None or fy is not None:
        raise ParameterError("give either --calib or --fx/--fy, not both")
    frames = radar_frames(list(radar))
    if any(f.depth.suffix.lower() == ".pcd" for f in frames) and calib is None:
        raise ParameterError("radar .pcd inputs need --calib (the radar-to-camera calibration)")
    frames, missing = attach(
        frames, image, "image", role="image", option="--image", shared_ok=False
    )
    if missing:
        raise FormatError(_missing(frames, "image", image, missing))
    frames, missing = attach(frames, calib, "calib", role="calib", option="--calib")
    if missing:
        raise FormatError(_missing(frames, "calib", calib, missing))
    lidar_files = None
    if lidar is not None:
        lp = Path(lidar)
        if lp.is_file():
            if len(frames) > 1:
                raise ParameterError(
                    f"{lp} is one LiDAR depth file but {len(frames)} radar frames were given: "
                    "pass a folder of LiDAR depth maps matched by frame",
                    param="lidar",
                )
            lidar_files = {frames[0].key: lp}
        else:
            index = index_input(lp, "depth", option="--lidar")
            lidar_files = match_keys([f.key for f in frames], index.files)
            if len(lidar_files) < len(frames):
                absent = next(f.key for f in frames if f.key not in lidar_files)
                raise FormatError(
                    f"--lidar: {lp}: no LiDAR depth map for frame {absent} "
                    f"({len(frames) - len(lidar_files)} of {len(frames)} missing)"
                )
    tasks = jbf_tasks(frames, out_dir, settings, lidar=lidar_files)
    inputs = [Path(p) for p in (*radar, image, calib, lidar) if p is not None]
    out = check_output_dir(out_dir, [p for p in inputs if p.is_dir()])
    from .provenance import option_names, settings_dict

    spec = RunSpec(
        "jbf-expand",
        out,
        {**settings_dict(settings), "fx": fx, "fy": fy},
        noun="expanded radar maps",
        options=option_names(settings),
    )
    summary = run_frames(JbfJob(settings, fx, fy), tasks, batch=batch, spec=spec)
    return _with_totals(summary, lidar is not None)


def _missing(frames: list[Frame], field: str, path, n: int) -> str:
    f = next(f for f in frames if not Path(getattr(f, field)).exists())
    return (
        f"--{field}: {path}: no {'image' if field == 'image' else 'calibration'} for frame "
        f"{f.key} (expected {getattr(f, field)}; {n} of {len(frames)} frames lack one)"
    )


def _with_totals(summary: RunSummary, with_lidar: bool) -> RunSummary:
    ok = summary.ok
    totals: dict = {}
    if ok:
        seeds = summary.total("seeds") / len(ok)
        points = summary.total("points") / len(ok)
        totals.update(
            mean_seeds=seeds,
            mean_points=points,
            expansion_factor=points / seeds if seeds else 0.0,
        )
    if with_lidar:
        totals["intrinsic_error"] = intrinsic_summary(summary)
    return summary.with_totals(totals)


def intrinsic_summary(summary: RunSummary) -> dict:
    """Per-frame and mean intrinsic errors of a run: ``{"frames": {id: {row: {...}}}, "mean":
    {row: {...}}}`` (rows: raw, the expansion, height-extend)."""
    from ..ops.intrinsic import mean_intrinsic_error

    frames = {r.frame_id: r.stats["intrinsic"] for r in summary.ok if "intrinsic" in r.stats}
    names: list[str] = []
    for rows in frames.values():
        names.extend(n for n in rows if n not in names)
    mean = {
        n: mean_intrinsic_error(rows[n] for rows in frames.values() if n in rows) for n in names
    }
    return {"frames": frames, "mean": mean}


def format_intrinsic_table(table: dict, *, max_depth: float = 80.0) -> str:
    """The intrinsic-error table as text, one line per (frame, method), then the means."""
    head = (
        f"{'frame':<14} {'method':<14} {'delta1':>7} {'delta2':>7} {'RMSE':>8} "
        f"{'points':>9} {'density%':>9} {'evaluated':>9}"
    )
    lines = [f"intrinsic error against LiDAR (depth <= {max_depth:g} m)", head]

    def row(frame: str, name: str, e: dict) -> str:
        return (
            f"{frame:<14} {name:<14} {e['delta1']:>7.3f} {e['delta2']:>7.3f} {e['rmse']:>8.3f} "
            f"{e['points']:>9.0f} {e['density_percent']:>9.3f} {e['evaluated']:>9.0f}"
        )

    for frame, rows in table["frames"].items():
        for name, e in rows.items():
            lines.append(row(frame, name, e))
    n = len(table["frames"])
    for name, e in table["mean"].items():
        lines.append(row(f"mean of {n}", name, e))
    return "\n".join(lines)
