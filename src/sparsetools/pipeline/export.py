"""Write depth maps back in the KITTI depth-completion layouts other code reads.

Many depth-completion codebases read only the official layout. Maps of a KITTI raw or
depth-completion root (``project``, ``beams`` + ``project``, ``jbf-expand``, ``densify``
outputs, keyed ``<drive>/<frame>``) are copied, byte for byte, to

- ``OUT/{train,val}/<drive>/proj_depth/<name>/image_0N/<frame>.png`` (the split of each drive
  taken from a depth-completion tree, ``split_from``, or one split for all), or
- ``OUT/<name>/<drive>_<name>_<frame>_image_0N.png`` (the ``val_selection_cropped`` naming),

so a 4-beam or radar variant of the benchmark drops into such code unchanged.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import FormatError, ParameterError
from ..io.sources import FrameKey, check_key_part, index_input
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames

__all__ = ["ExportSettings", "export_kitti_dc"]

LAYOUTS = ("kitti-dc", "kitti-selection")


@dataclass(frozen=True)
class ExportSettings:
    """Where maps go: the layout, the map set's name, the camera and the splits of drives."""

    layout: str = "kitti-dc"
    name: str = "velodyne_raw"
    camera: int = 2
    splits: dict = field(default_factory=dict, metadata={"option": "--split-from"})

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ParameterError(f"must be one of {', '.join(LAYOUTS)}", param="layout")
        check_key_part(self.name, "map set name")
        if not self.name or "/" in self.name:
            raise ParameterError(f"{self.name!r} must be one folder name", param="name")


@dataclass(frozen=True)
class ExportInput:
    source: str


@dataclass(frozen=True)
class ExportJob:
    """Copy one map (its bytes, unchanged) to its place in the layout."""

    def __call__(self, task: FrameTask[ExportInput]) -> dict:
        from ..io.atomic import atomic_path
        from ..io.image import read_depth_png

        read_depth_png(task.inputs.source)  # only KITTI uint16 depth PNGs are exported
        data = Path(task.inputs.source).read_bytes()
        with atomic_path(task.outputs["depth"]) as tmp:
            tmp.write_bytes(data)
        return {"bytes": len(data)}


def _target(out: Path, key: FrameKey, s: ExportSettings, split: str | None) -> Path:
    cam = f"image_{s.camera:02d}"
    if s.layout == "kitti-selection":
        return out / s.name / f"{key.sequence}_{s.name}_{key.frame}_{cam}.png"
    return out / split / key.sequence / "proj_depth" / s.name / cam / f"{key.frame}.png"


def drive_splits(tree: str | os.PathLike) -> dict[str, str]:
    """``drive -> split`` of a KITTI depth-completion tree (``{train,val}/<drive>/``)."""
    from ..io.sources.kitti import _proj_depth_drives

    out = {}
    for drive, split in _proj_depth_drives(Path(tree)):
        if split is not None:
            out[drive.name] = split
    if not out:
        raise FormatError(
            f"{tree}: no {{train,val}}/<drive>/proj_depth/ folders to take splits from"
        )
    return out


def export_kitti_dc(
    maps: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: ExportSettings,
    *,
    split: str | None = None,
    batch: Batch | None = None,
) -> RunSummary:
    """Copy the depth maps in ``maps`` (keyed ``<drive>/<frame>``) into ``settings.layout``.

    Parameters
    ----------
    maps : path-like
        A folder of depth maps per drive (``<drive>/<frame>.png``), e.g. a ``project`` output
        for a KITTI raw root.
    out_dir : path-like
    settings : ExportSettings
        ``splits``: drive -> split (:func:`drive_splits` of a depth-completion tree).
    split : str, optional
        The split of drives ``settings.splits`` does not name (default: such drives are an
        error, naming the first).
    """
    batch = batch or Batch()
    index = index_input(maps, "depth", option="MAPS")
    out = check_output_dir(out_dir, [maps])
    tasks = []
    for key, path in index.files.items():
        if not key.sequence or "/" in key.sequence:
            raise FormatError(
                f"{path}: maps must be keyed <drive>/<frame> (a KITTI raw or depth-completion "
                f"root's outputs), got frame '{key}'"
            )
        drive_split = settings.splits.get(key.sequence, split)
        if settings.layout == "kitti-dc" and drive_split is None:
            raise ParameterError(
                f"no split for drive {key.sequence}: give --split-from (a depth-completion tree) "
                "or --split",
                param="split",
            )
        target = _target(out, key, settings, drive_split)
        tasks.append(FrameTask(key, ExportInput(str(path)), {"depth": target}, (path,)))
    spec = RunSpec("export", out, {**_settings(settings), "default_split": split},
                   noun="exported maps", options={"default_split": "--split"})  # fmt: skip
    return run_frames(ExportJob(), tasks, batch=batch, spec=spec).with_totals(
        {"layout": settings.layout, "name": settings.name, "output": str(out)}
    )


def _settings(settings: ExportSettings) -> dict:
    from .provenance import settings_dict

    return settings_dict(settings)
