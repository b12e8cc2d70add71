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
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import Frame
from ..validate import (
    check_choice,
    check_non_negative,
    check_positive,
    check_probability,
    parse_size,
)
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask
from .provenance import settings_dict

__all__ = [
    "CONF_FORMATS",
    "METHODS",
    "JbfInput",
    "JbfJob",
    "JbfSettings",
    "JbfStats",
    "format_intrinsic_table",
    "intrinsic_summary",
    "resize_sparse_depth",
]

log = logging.getLogger(__name__)

METHODS = ("jbf", "height-extend")
CONF_FORMATS = ("png", "npy")


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
    window_m: tuple[float, float] = field(default=(2.35, 2.35), metadata={"option": "--window-m"})
    kernel: str = "jbf"
    range_metric: str = "gray"
    conflict: str = "nearest"
    below_m: float = 0.25
    above_m: float = 1.5
    resize: float | None = None
    confidence: bool = True
    conf_format: str = "png"
    max_depth: float = 80.0

    def __post_init__(self) -> None:
        """Every option checked once, before any frame runs (one clear error, no output)."""
        from ..ops.jbf import CONFLICTS, KERNELS, RANGE_METRICS, pruning_radius

        check_choice(self.method, "method", METHODS)
        check_choice(self.conf_format, "conf_format", CONF_FORMATS)
        check_positive(self.sigma_s, "sigma_s")
        check_positive(self.sigma_r, "sigma_r")
        check_probability(self.threshold, "threshold")
        w, h = parse_size(self.window_m, "window_m", integer=False)
        object.__setattr__(self, "window_m", (w, h))
        check_choice(self.kernel, "kernel", KERNELS)
        check_choice(self.range_metric, "range_metric", RANGE_METRICS)
        check_choice(self.conflict, "conflict", CONFLICTS)
        check_non_negative(self.below_m, "below_m")
        check_non_negative(self.above_m, "above_m")
        check_positive(self.resize, "resize", allow_none=True)
        check_positive(self.max_depth, "max_depth")
        pruning_radius(float(self.sigma_s), float(self.threshold))


# -- inputs -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JbfInput:
    """One frame's files: radar (depth PNG or ``.pcd``), image, calibration, LiDAR depth."""

    radar: str
    image: str
    calib: str | None = None
    lidar: str | None = None


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


def _frame_calibration(inp: JbfInput):
    """The frame's calibration, checked against its image's size."""
    from ..io.calib import frame_calibration

    return frame_calibration(calib_path=inp.calib, image=inp.image, what="expanded map")


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
class JbfStats(FrameStats):
    """One frame: radar seeds, points of the expanded map, PNG pixels clipped at 256 m and,
    with LiDAR, the intrinsic error of each method (rows ``raw``, the expansion,
    ``height-extend``; :func:`sparsetools.ops.intrinsic.intrinsic_error`)."""

    seeds: int
    points: int
    clipped: int = 0
    intrinsic: Mapping | None = None


@dataclass(frozen=True)
class JbfJob(BatchJob[JbfInput]):
    """``sparsetools jbf-expand`` (picklable): per frame read, (resize,) expand, write.

    Attributes
    ----------
    settings : JbfSettings
    fx, fy : float, optional, pixels
        Focal lengths of the (unresized) images, when the frames have no calibration.
    """

    command: ClassVar[str] = "jbf-expand"
    noun: ClassVar[str] = "expanded radar maps"
    stats_type: ClassVar[type[FrameStats]] = JbfStats

    settings: JbfSettings = field(default_factory=JbfSettings)
    fx: float | None = None
    fy: float | None = None

    def __post_init__(self) -> None:
        check_positive(self.fx, "fx", allow_none=True)
        check_positive(self.fy, "fy", allow_none=True)

    def planned(self, frames: list[Frame]) -> JbfJob:
        """The focal lengths come from one place: the frames' calibration or fx, fy."""
        if not frames:
            raise ParameterError("no radar inputs given")
        has_calib = frames[0].calib is not None
        if not has_calib and any(f.depth.suffix.lower() == ".pcd" for f in frames):
            raise ParameterError("radar .pcd inputs need --calib (the radar-to-camera calibration)")
        if not has_calib and (self.fx is None or self.fy is None):
            raise ParameterError("give the focal lengths: --fx and --fy, or --calib")
        if has_calib and (self.fx is not None or self.fy is not None):
            raise ParameterError("give either --calib or --fx/--fy, not both")
        return self

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[JbfInput]]:
        """One task per frame: ``OUT/<sequence>/<frame>.png`` and, unless disabled,
        ``OUT/<sequence>/<frame>_conf.png`` (or ``.npy``)."""
        tasks = []
        for f in frames:
            outputs = {"depth": f.key.path(out_dir, ".png")}
            if self.settings.confidence:
                outputs["confidence"] = f.key.path(out_dir, f"_conf.{self.settings.conf_format}")
            inp = JbfInput(
                radar=str(f.depth),
                image=str(f.image),
                calib=None if f.calib is None else str(f.calib),
                lidar=None if f.gt is None else str(f.gt),
            )
            sources = tuple(p for p in (f.depth, f.image, f.calib, f.gt) if p is not None)
            tasks.append(FrameTask(f.key, inp, outputs, sources))
        return tasks

    def record(self) -> dict:
        return {**settings_dict(self.settings), "fx": self.fx, "fy": self.fy}

    def __call__(self, task: FrameTask[JbfInput]) -> JbfStats:
        from ..io.image import read_depth_png, read_image, write_depth_png
        from ..ops.intrinsic import intrinsic_error
        from ..ops.jbf import height_extend, jbf_expand

        inp, s = task.inputs, self.settings
        rgb = read_image(inp.image)
        size0 = (rgb.shape[1], rgb.shape[0])
        scale = s.resize if s.resize is not None and s.resize != 1.0 else None
        calib = _frame_calibration(inp) if inp.calib else None
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
            radar = _read_map(radar_path, size0, "radar depth", read_depth_png)
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

        intrinsic = None
        if inp.lidar:
            lidar = _read_map(Path(inp.lidar), size0, "LiDAR depth", read_depth_png)
            if scale is not None:
                lidar = resize_sparse_depth(lidar, scale, size)
            intrinsic = {"raw": intrinsic_error(radar, lidar, max_depth=s.max_depth)}
            name = s.kernel if s.method == "jbf" else "height-extend"
            intrinsic[name] = intrinsic_error(depth, lidar, max_depth=s.max_depth)
            if s.method == "jbf":
                baseline = height_extend(radar, fy=fy, below_m=s.below_m, above_m=s.above_m)
                intrinsic["height-extend"] = intrinsic_error(baseline, lidar, max_depth=s.max_depth)

        clipped = write_depth_png(task.outputs["depth"], depth)
        if s.confidence:
            _write_confidence(task.outputs["confidence"], confidence, s.conf_format)
        return JbfStats(
            seeds=int(np.count_nonzero(radar > 0)),
            points=int(np.count_nonzero(depth > 0)),
            clipped=clipped,
            intrinsic=intrinsic,
        )

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Totals: mean_seeds, mean_points, expansion_factor and, with LiDAR,
        intrinsic_error (per frame and mean; frames up to date included, from the record)."""
        stats = self.stats(summary)
        totals: dict = {}
        if stats:
            seeds = sum(st.seeds for st in stats) / len(stats)
            points = sum(st.points for st in stats) / len(stats)
            totals.update(mean_seeds=seeds, mean_points=points,
                          expansion_factor=points / seeds if seeds else 0.0)  # fmt: skip
        if any(t.inputs.lidar for t in tasks):
            totals["intrinsic_error"] = intrinsic_summary(summary)
        return totals


def _read_map(path: Path, size: tuple[int, int], what: str, read) -> np.ndarray:
    depth = read(path)
    if (depth.shape[1], depth.shape[0]) != size:
        raise ParameterError(
            f"{what} {path} is {depth.shape[1]}x{depth.shape[0]} but the image is "
            f"{size[0]}x{size[1]}: they must have the same size"
        )
    return depth


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
