"""Batch job of ``sparsetools densify``: sparse depth maps to dense ones (IP-Basic, baselines).

Inputs are sparse depth maps (KITTI uint16 PNG or float32 ``.npy`` metres): files, folder
trees, folders written by ``project`` / ``beams`` / ``jbf-expand`` / ``accumulate`` (read
through their record), KITTI depth-completion trees (``proj_depth/velodyne_raw``), all
through :func:`sparsetools.io.sources.index_input` with the role ``sparse``. Each map goes
through :func:`sparsetools.ops.densify.densify` with one :class:`DensifySettings`.

Outputs, per frame ``<sequence>/<frame>`` (a flat input has no ``<sequence>/``):

- ``OUT/<sequence>/<frame>.png`` (role ``depth``): the dense map, KITTI uint16 (depth * 256,
  0 = no estimate), or ``.npy`` float32 metres with ``--format npy``;
- ``OUT/mask/<sequence>/<frame>.png`` (role ``mask``): uint8, 255 where the input held a
  measurement, 0 where the value was filled in (or there is no estimate: depth 0).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import FrameKey
from ..ops.densify import DensifySettings
from ..validate import check_choice
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames

__all__ = [
    "FORMATS",
    "MASK_DIR",
    "DensifyInput",
    "DensifyJob",
    "densify_tasks",
    "run_densify",
    "sparse_maps",
]

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
class DensifyJob:
    """The per-frame job (picklable): read, densify, write the dense map and the mask.

    Per-frame statistics: ``pixels``, ``measured`` (input pixels > 0), ``filled`` (estimated,
    not measured), ``empty`` (no estimate), ``clipped`` (PNG values clipped at 256 m) and
    the densification time ``t_densify`` (seconds; not recorded).
    """

    settings: DensifySettings
    fmt: str = "png"

    def __call__(self, task: FrameTask[DensifyInput]) -> dict:
        from ..io.dataset import read_depth_file
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
        measured = int(np.count_nonzero(res.measured))
        filled = int(np.count_nonzero(res.filled))
        return {
            "pixels": int(res.depth.size),
            "measured": measured,
            "filled": filled,
            "empty": int(res.depth.size) - estimated,
            "clipped": int(clipped),
            "t_densify": seconds,
        }


def sparse_maps(paths) -> dict[FrameKey, Path]:
    """Sparse depth maps of every input path, by frame key (sorted).

    Raises
    ------
    FormatError
        A path without depth maps, or two inputs that are one frame.
    """
    from ..io.sources import index_input

    paths = list(paths)
    if not paths:
        raise ParameterError("no sparse depth maps given")
    found: dict[FrameKey, Path] = {}
    for p in map(Path, paths):
        for key, f in index_input(p, "sparse", option="SPARSE").files.items():
            if key in found:
                raise FormatError(
                    f"{found[key]} and {f} are the same frame '{key}': give each once, or "
                    "folders whose frames differ"
                )
            found[key] = f
    return dict(sorted(found.items()))


def densify_tasks(
    maps: dict[FrameKey, Path], out_dir: str | os.PathLike, fmt: str
) -> list[FrameTask[DensifyInput]]:
    """One task per map: ``OUT/<sequence>/<frame>.<fmt>``, ``OUT/mask/<sequence>/<frame>.png``."""
    out = Path(out_dir)
    return [
        FrameTask(
            key,
            DensifyInput(str(path)),
            {"depth": key.path(out, f".{fmt}"), "mask": key.path(out, ".png", prefix=MASK_DIR)},
            (path,),
        )
        for key, path in maps.items()
    ]


def run_densify(
    sparse,
    out_dir: str | os.PathLike,
    *,
    settings: DensifySettings | None = None,
    fmt: str = "png",
    batch: Batch | None = None,
) -> RunSummary:
    """Densify every sparse map of ``sparse`` (files and folders).

    Parameters
    ----------
    sparse : list of path-like
    out_dir : path-like
    settings : DensifySettings, optional
        Default: IP-Basic as in the paper.
    fmt : {"png", "npy"}
        Format of the dense maps (the masks are PNG).
    batch : Batch, optional

    Returns
    -------
    RunSummary
        Totals: method, measured_pct, filled_pct (mean over frames of filled / pixels),
        empty_pct, clipped, seconds_per_frame (densification alone, frames computed now)
        and wall_seconds_per_frame (reading and writing included).
    """
    from .provenance import settings_dict

    batch = batch or Batch()
    settings = settings or DensifySettings()
    check_choice(fmt, "--format", FORMATS)
    paths = list(sparse)
    maps = sparse_maps(paths)
    out = check_output_dir(out_dir, [p for p in paths if Path(p).is_dir()])
    tasks = densify_tasks(maps, out, fmt)
    spec = RunSpec(
        "densify",
        out,
        {**settings_dict(settings), "fmt": fmt},
        noun="dense depth maps",
        options={"fmt": "--format"},
    )
    summary = run_frames(DensifyJob(settings, fmt), tasks, batch=batch, spec=spec)
    return summary.with_totals(_totals(summary, settings))


def _totals(summary: RunSummary, settings: DensifySettings) -> dict:
    ok, done = summary.ok, summary.done

    def mean_pct(key: str) -> float:
        values = [r.stats[key] / r.stats["pixels"] for r in ok if r.stats.get("pixels")]
        return round(100.0 * float(np.mean(values)), 4) if values else 0.0

    kernel = [r.stats["t_densify"] for r in done if "t_densify" in r.stats]
    return {
        "method": settings.method,
        "measured_pct": mean_pct("measured"),
        "filled_pct": mean_pct("filled"),
        "empty_pct": mean_pct("empty"),
        "clipped": int(summary.total("clipped")),
        "seconds_per_frame": round(float(np.mean(kernel)), 5) if kernel else 0.0,
        "wall_seconds_per_frame": round(summary.seconds / len(done), 5) if done else 0.0,
    }
