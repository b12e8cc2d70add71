"""Batch job of ``sparsetools densify``: sparse depth maps to dense ones (IP-Basic, baselines).

Inputs are sparse depth maps (KITTI uint16 PNG or float32 ``.npy`` metres): files, folder
trees, folders written by ``project`` / ``beams`` / ``jbf-expand`` / ``accumulate`` (read
through their record), KITTI depth-completion trees (``proj_depth/velodyne_raw``), all
through :func:`sparsetools.io.sources.depth_frames`. Each map goes
through :func:`sparsetools.ops.densify.densify` with one :class:`DensifySettings`.

Outputs, per frame ``<sequence>/<frame>`` (a flat input has no ``<sequence>/``):

- ``OUT/<sequence>/<frame>.png`` (role ``depth``): the dense map, KITTI uint16 (depth * 256,
  0 = no estimate), or ``.npy`` float32 metres with ``--format npy``;
- ``OUT/mask/<sequence>/<frame>.png`` (role ``mask``): uint8, 255 where the input held a
  measurement, 0 where the value was filled in (or there is no estimate: depth 0).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import Frame
from ..ops.densify import DensifySettings
from ..validate import check_choice
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask
from .provenance import settings_dict

__all__ = ["FORMATS", "MASK_DIR", "DensifyInput", "DensifyJob", "DensifyStats"]

FORMATS = ("png", "npy")
MASK_DIR = "mask"


@dataclass(frozen=True)
class DensifyInput:
    """One frame's input: the sparse depth map (PNG or ``.npy``)."""

    sparse: str


def _write_mask(path: Path, measured: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", measured.astype(np.uint8) * np.uint8(255))
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 PNG
        raise FormatError(f"{path}: OpenCV cannot encode the mask")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


@dataclass(frozen=True)
class DensifyStats(FrameStats):
    """One frame: pixels, measured (input pixels > 0), filled (estimated, not measured), empty
    (no estimate), PNG values clipped at 256 m, and the densification time ``t_densify``
    (seconds; never recorded)."""

    pixels: int
    measured: int
    filled: int
    empty: int
    clipped: int
    t_densify: float | None = None


@dataclass(frozen=True)
class DensifyJob(BatchJob[DensifyInput]):
    """``sparsetools densify`` (picklable): per frame read, densify, write the dense map and
    the mask of measured pixels."""

    command: ClassVar[str] = "densify"
    noun: ClassVar[str] = "dense depth maps"
    stats_type: ClassVar[type[FrameStats]] = DensifyStats

    settings: DensifySettings = field(default_factory=DensifySettings)
    fmt: str = "png"

    def __post_init__(self) -> None:
        check_choice(self.fmt, "--format", FORMATS)

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[DensifyInput]]:
        """One task per map: ``OUT/<sequence>/<frame>.<fmt>``,
        ``OUT/mask/<sequence>/<frame>.png``."""
        if not frames:
            raise ParameterError("no sparse depth maps given")
        return [
            FrameTask(
                f.key,
                DensifyInput(str(f.depth)),
                {"depth": f.key.path(out_dir, f".{self.fmt}"),
                 "mask": f.key.path(out_dir, ".png", prefix=MASK_DIR)},
                (f.depth,),
            )
            for f in frames
        ]  # fmt: skip

    def record(self) -> dict:
        return {**settings_dict(self.settings), "fmt": self.fmt}

    def option_names(self) -> dict:
        return {"fmt": "--format", "max_depth": "--inversion-offset"}

    def __call__(self, task: FrameTask[DensifyInput]) -> DensifyStats:
        from ..io.depth_files import read_depth_file
        from ..io.image import write_depth_png
        from ..ops.densify import densify

        sparse = read_depth_file(task.inputs.sparse)
        t0 = time.perf_counter()
        res = densify(sparse, self.settings)
        seconds = time.perf_counter() - t0
        out = task.outputs["depth"]
        clipped = 0
        if self.fmt == "png":
            clipped = write_depth_png(out, res.depth)
        else:
            with atomic_path(out) as tmp, open(tmp, "wb") as fh:
                np.save(fh, res.depth, allow_pickle=False)
        _write_mask(task.outputs["mask"], res.measured)
        estimated = int(np.count_nonzero(res.depth > 0))
        return DensifyStats(
            pixels=int(res.depth.size),
            measured=int(np.count_nonzero(res.measured)),
            filled=int(np.count_nonzero(res.filled)),
            empty=int(res.depth.size) - estimated,
            clipped=int(clipped),
            t_densify=seconds,
        )

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Totals: method, measured_pct, filled_pct (mean over frames of filled / pixels),
        empty_pct, clipped, seconds_per_frame (densification alone, frames computed now) and
        wall_seconds_per_frame (reading and writing included)."""
        stats = [st for st in self.stats(summary) if st.pixels]

        def mean_pct(name: str) -> float:
            values = [getattr(st, name) / st.pixels for st in stats]
            return round(100.0 * float(np.mean(values)), 4) if values else 0.0

        done = summary.done
        kernel = [r.stats["t_densify"] for r in done if "t_densify" in r.stats]
        return {
            "method": self.settings.method,
            "measured_pct": mean_pct("measured"),
            "filled_pct": mean_pct("filled"),
            "empty_pct": mean_pct("empty"),
            "clipped": sum(st.clipped for st in self.stats(summary)),
            "seconds_per_frame": round(float(np.mean(kernel)), 5) if kernel else 0.0,
            "wall_seconds_per_frame": round(summary.seconds / len(done), 5) if done else 0.0,
        }
