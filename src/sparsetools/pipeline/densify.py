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
  measurement, 0 where the value was filled in (or there is no estimate: depth 0);
- with the learned densifier and ``uncertainty`` on, ``OUT/uncertainty/<sequence>/<frame>.npy``
  (role ``uncertainty``): float32 ``U = log sigma^2`` per pixel, sigma in metres (no scale,
  no offset: ``sigma = exp(U / 2)``).

The learned method (``--method learned``) runs a model handed in by the command line (any
object with ``densify(sparse) -> (depth, log_var)``, :class:`DepthUncertaintyModel`: the
torch one is :class:`sparsetools.train.densifier.LearnedDensifier`; this module needs no
torch). Its settings are :class:`LearnedSettings`; the checkpoint file is one of every
frame's sources, so a changed checkpoint recomputes the frames on a rerun. Every other
method's settings, outputs and record are what they were before the learned one existed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import Frame
from ..ops.densify import DensifySettings
from ..validate import check_choice
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask
from .provenance import settings_dict

__all__ = [
    "FORMATS",
    "LEARNED",
    "MASK_DIR",
    "UNCERTAINTY_DIR",
    "DensifyInput",
    "DensifyJob",
    "DensifyStats",
    "DepthUncertaintyModel",
    "LearnedSettings",
]

FORMATS = ("png", "npy")
MASK_DIR = "mask"
#: Folder of the log-variance maps of the learned method.
UNCERTAINTY_DIR = "uncertainty"
#: The ``--method`` of the learned densifier.
LEARNED = "learned"


class DepthUncertaintyModel(Protocol):
    """What the learned method asks of its model, per frame.

    ``densify(sparse)`` takes an (H, W) float32 map in metres (0 = no measurement) and
    returns ``(depth, log_var)``: (H, W) float32 depth in metres and (H, W) float32
    ``U = log sigma^2`` (sigma in metres).
    """

    def densify(self, sparse: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class LearnedSettings:
    """The learned method's settings: recorded in ``OUT`` and compared on a rerun.

    Attributes
    ----------
    checkpoint : str
        The densifier checkpoint (resolved path).
    uncertainty : bool
        Also write the log-variance maps.
    """

    checkpoint: str = field(default="", metadata={"option": "--densifier"})
    uncertainty: bool = field(default=False, metadata={"option": "--uncertainty"})


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
    #: learned method only: the median of sigma = exp(U / 2) over the frame, metres
    sigma_median: float | None = None


@dataclass(frozen=True)
class DensifyJob(BatchJob[DensifyInput]):
    """``sparsetools densify`` (picklable): per frame read, densify, write the dense map and
    the mask of measured pixels."""

    command: ClassVar[str] = "densify"
    noun: ClassVar[str] = "dense depth maps"
    stats_type: ClassVar[type[FrameStats]] = DensifyStats

    settings: DensifySettings = field(default_factory=DensifySettings)
    fmt: str = "png"
    #: the learned method's settings (None: ``settings.method`` runs)
    learned: LearnedSettings | None = None
    #: the learned method's model (:class:`DepthUncertaintyModel`, picklable)
    model: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        check_choice(self.fmt, "--format", FORMATS)
        if self.learned is not None and self.model is None:
            raise ParameterError("--method learned needs its model (--densifier CHECKPOINT)",
                                 param="--densifier")  # fmt: skip

    @property
    def method(self) -> str:
        return LEARNED if self.learned is not None else self.settings.method

    def prepare(self) -> None:
        """Build the learned method's network once per process (before a pool forks)."""
        build = getattr(self.model, "network", None)
        if callable(build):
            build()

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[DensifyInput]]:
        """One task per map: ``OUT/<sequence>/<frame>.<fmt>``,
        ``OUT/mask/<sequence>/<frame>.png`` (and ``OUT/uncertainty/<sequence>/<frame>.npy``
        with the learned method's uncertainty; its checkpoint is then a source of every
        frame)."""
        if not frames:
            raise ParameterError("no sparse depth maps given")
        learned = self.learned
        tasks = []
        for f in frames:
            outputs = {"depth": f.key.path(out_dir, f".{self.fmt}"),
                       "mask": f.key.path(out_dir, ".png", prefix=MASK_DIR)}  # fmt: skip
            sources: tuple[Path, ...] = (f.depth,)
            if learned is not None:
                sources += (Path(learned.checkpoint),)
                if learned.uncertainty:
                    outputs["uncertainty"] = f.key.path(out_dir, ".npy", prefix=UNCERTAINTY_DIR)
            tasks.append(FrameTask(f.key, DensifyInput(str(f.depth)), outputs, sources))
        return tasks

    def record(self) -> dict:
        if self.learned is not None:
            return {"method": LEARNED, **settings_dict(self.learned), "fmt": self.fmt}
        return {**settings_dict(self.settings), "fmt": self.fmt}

    def option_names(self) -> dict:
        return {"fmt": "--format", "max_depth": "--inversion-offset", "checkpoint": "--densifier",
                "uncertainty": "--uncertainty"}  # fmt: skip

    def _learned(self, task: FrameTask[DensifyInput], sparse: np.ndarray):
        """The learned method's result, its log-variance written when asked."""
        from ..ops.densify import DensifyResult

        depth, log_var = self.model.densify(sparse)
        with np.errstate(invalid="ignore"):
            measured = np.isfinite(sparse) & (sparse > 0)
        if "uncertainty" in task.outputs:
            with atomic_path(task.outputs["uncertainty"]) as tmp, open(tmp, "wb") as fh:
                np.save(fh, np.asarray(log_var, dtype=np.float32), allow_pickle=False)
        sigma = float(np.median(np.exp(0.5 * log_var.astype(np.float64))))
        return DensifyResult(depth=depth, measured=measured, method=LEARNED), sigma

    def __call__(self, task: FrameTask[DensifyInput]) -> DensifyStats:
        from ..io.depth_files import read_depth_file
        from ..io.image import write_depth_png
        from ..ops.densify import densify

        sparse = read_depth_file(task.inputs.sparse)
        t0 = time.perf_counter()
        sigma = None
        if self.learned is not None:
            res, sigma = self._learned(task, sparse)
        else:
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
            sigma_median=None if sigma is None else round(sigma, 4),
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
        extra = {}
        if self.learned is not None:
            sigmas = [st.sigma_median for st in stats if st.sigma_median is not None]
            extra["sigma_median_m"] = round(float(np.mean(sigmas)), 4) if sigmas else None
        return {
            "method": self.method,
            "measured_pct": mean_pct("measured"),
            "filled_pct": mean_pct("filled"),
            "empty_pct": mean_pct("empty"),
            "clipped": sum(st.clipped for st in self.stats(summary)),
            "seconds_per_frame": round(float(np.mean(kernel)), 5) if kernel else 0.0,
            "wall_seconds_per_frame": round(summary.seconds / len(done), 5) if done else 0.0,
            **extra,
        }
