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

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from ..errors import FormatError, ParameterError
from ..io.sources import Frame, FrameKey, check_key_part
from ..validate import check_choice
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask
from .provenance import option_names, settings_dict

__all__ = ["LAYOUTS", "ExportJob", "ExportSettings", "ExportStats"]

LAYOUTS = ("kitti-dc", "kitti-selection")


@dataclass(frozen=True)
class ExportSettings:
    """Where maps go: the layout, the map set's name, the camera and the splits of drives."""

    layout: str = "kitti-dc"
    name: str = "velodyne_raw"
    camera: int = 2
    splits: dict = field(default_factory=dict, metadata={"option": "--split-from"})

    def __post_init__(self) -> None:
        check_choice(self.layout, "layout", LAYOUTS)
        check_key_part(self.name, "map set name")
        if not self.name or "/" in self.name:
            raise ParameterError(f"{self.name!r} is not one folder name", param="name")


@dataclass(frozen=True)
class ExportInput:
    source: str


@dataclass(frozen=True)
class ExportStats(FrameStats):
    """One map: bytes copied."""

    bytes: int


@dataclass(frozen=True)
class ExportJob(BatchJob[ExportInput]):
    """``dataset export`` (picklable): copy each map (its bytes, unchanged) to its place in
    the layout.

    Attributes
    ----------
    settings : ExportSettings
    default_split : str, optional
        The split of drives ``settings.splits`` does not name (None: such a drive is an
        error, naming it).
    """

    command: ClassVar[str] = "export"
    noun: ClassVar[str] = "exported maps"
    stats_type: ClassVar[type[FrameStats]] = ExportStats

    settings: ExportSettings = field(default_factory=ExportSettings)
    default_split: str | None = None

    def __post_init__(self) -> None:
        for split in (self.default_split, *self.settings.splits.values()):
            if split is not None:  # a folder name inside -o: no "..", no absolute path
                check_key_part(split, "--split")
                if not split or "/" in split:
                    raise ParameterError(f"{split!r} is not one folder name", param="split")

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[ExportInput]]:
        """One task per map (``Frame.depth``, keyed ``<drive>/<frame>``)."""
        s = self.settings
        tasks = []
        for f in frames:
            key, path = f.key, f.depth
            if not key.sequence or "/" in key.sequence:
                raise FormatError(
                    f"{path}: maps must be keyed <drive>/<frame> (a KITTI raw or "
                    f"depth-completion root's outputs), got frame '{key}'"
                )
            drive_split = s.splits.get(key.sequence, self.default_split)
            if s.layout == "kitti-dc" and drive_split is None:
                raise ParameterError(
                    f"no split for drive {key.sequence}: give --split-from (a depth-completion "
                    "tree) or --split",
                    param="split",
                )
            target = _target(out_dir, key, s, drive_split)
            tasks.append(FrameTask(key, ExportInput(str(path)), {"depth": target}, (path,)))
        return tasks

    def record(self) -> dict:
        return {**settings_dict(self.settings), "default_split": self.default_split}

    def option_names(self) -> dict:
        return {**option_names(self.settings), "default_split": "--split"}

    def __call__(self, task: FrameTask[ExportInput]) -> ExportStats:
        from ..io.atomic import atomic_path
        from ..io.image import read_depth_png

        read_depth_png(task.inputs.source)  # only KITTI uint16 depth PNGs are exported
        data = Path(task.inputs.source).read_bytes()
        with atomic_path(task.outputs["depth"]) as tmp:
            tmp.write_bytes(data)
        return ExportStats(bytes=len(data))

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        return {"layout": self.settings.layout, "name": self.settings.name,
                "output": str(out_dir)}  # fmt: skip


def _target(out: Path, key: FrameKey, s: ExportSettings, split: str | None) -> Path:
    cam = f"image_{s.camera:02d}"
    if s.layout == "kitti-selection":
        return out / s.name / f"{key.sequence}_{s.name}_{key.frame}_{cam}.png"
    return out / split / key.sequence / "proj_depth" / s.name / cam / f"{key.frame}.png"
