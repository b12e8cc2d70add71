"""``sparsetools predict``: a model's depth maps written as KITTI uint16 PNGs, one per sample.

The job writes what a *predictor* gives (any object with ``depth(index) -> (H, W) float32``
metres, :class:`DepthPredictor`; the command line hands in the torch one of
:mod:`sparsetools.train.predict`, this module needs no torch), in one of two layouts:

- ``tree``: ``OUT/<sequence>/<frame>.png``, the layout every sparsetools command writes
  (``eval --pred OUT --gt ...`` reads it back by frame);
- ``kitti-dc``: the KITTI depth-completion submission layout, flat in ``OUT``: a sample of a
  ``val_selection_cropped`` dataset (sequence = drive, frame = its 10-digit number) as
  ``<drive>_groundtruth_depth_<frame>_image_02.png`` (the name of its ground truth, which the
  devkit pairs with the prediction), any other sample (the anonymous test set, built from
  its flat ``image/`` folder) under its input's name (``0000000000.png``); every sample must
  be 1216x352, the size of both selection sets.

Values: depth x 256 rounded to the nearest integer (:func:`~sparsetools.io.image.encode_depth_png`),
or with ``format="npy"`` (``tree`` layout only) float32 metres in ``.npy`` files, which keep
the precision that relative depth (a camera-only self-supervised model's, often well under
1 m) loses in steps of 1/256 m. A pixel with no value (0, negative, NaN, infinite) is written
as 0 and counted as a hole: holes are never filled in silence, and the devkit treats 0 as a
missing prediction. A value outside what a uint16 PNG holds (depth >= 65535/256 = 255.996 m,
or below 1/512 m) is clipped to the range and counted (``clipped``), as every depth PNG
sparsetools writes. Both counts are in each frame's record and in the summary, with the
first frames that have any.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.sources import FrameKey
from ..validate import check_choice, check_int_range
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask

__all__ = [
    "DC_SIZE",
    "FORMATS",
    "LAYOUTS",
    "DepthPredictor",
    "PredictInput",
    "PredictJob",
    "PredictSample",
    "PredictSettings",
    "PredictStats",
    "kitti_dc_name",
]

LAYOUTS = ("tree", "kitti-dc")
FORMATS = ("png", "npy")
#: (width, height) of KITTI depth completion's val_selection_cropped and test sets.
DC_SIZE = (1216, 352)
_DRIVE = re.compile(r"\d{4}_\d{2}_\d{2}_drive_\d{4}_sync")
#: Frames named in the summary's lists.
_SHOWN = 5


class DepthPredictor(Protocol):
    """What the job asks for each sample: its predicted depth, (H, W) float metres."""

    def depth(self, index: int) -> np.ndarray: ...


@dataclass(frozen=True)
class PredictSample:
    """One sample to predict.

    Attributes
    ----------
    index : int
        Its position in the split (what the predictor is asked for).
    sequence, frame : str
        Its frame key (the dataset's ``sequence`` and ``frame``).
    width, height : int
        Its image size, pixels.
    sources : tuple of str
        Files the prediction is made from (the checkpoint, the sample's files): a changed one
        recomputes the frame on a rerun.
    """

    index: int
    sequence: str
    frame: str
    width: int
    height: int
    sources: tuple[str, ...] = ()

    @property
    def key(self) -> FrameKey:
        return FrameKey(self.sequence, self.frame)


@dataclass(frozen=True)
class PredictSettings:
    """What makes the predictions: recorded in ``OUT`` and compared on a rerun."""

    checkpoint: str = field(default="", metadata={"option": "CHECKPOINT"})
    dataset: str = field(default="", metadata={"option": "DATASET"})
    split: str = field(default="test", metadata={"option": "--split"})
    layout: str = field(default="tree", metadata={"option": "--layout"})
    format: str = field(default="png", metadata={"option": "--format"})

    def __post_init__(self) -> None:
        check_choice(self.layout, "layout", LAYOUTS)
        check_choice(self.format, "format", FORMATS)
        if self.layout == "kitti-dc" and self.format != "png":
            raise ParameterError(
                "--layout kitti-dc writes the benchmark's uint16 PNGs: use --format png",
                param="format",
            )


@dataclass(frozen=True)
class PredictInput:
    index: int
    width: int
    height: int


@dataclass(frozen=True)
class PredictStats(FrameStats):
    """One map: its pixels, those with no value (``holes``, written 0) and those clipped to
    the uint16 range (``clipped``), and the range of the values written (metres)."""

    pixels: int
    holes: int
    clipped: int
    min_depth: float | None = None
    max_depth: float | None = None


def kitti_dc_name(sample: PredictSample) -> str:
    """The file name of a sample's prediction in KITTI depth completion's layout.

    A ``val_selection_cropped`` frame (sequence a KITTI drive, a 10-digit frame) is named as
    its ground truth, ``<drive>_groundtruth_depth_<frame>_image_02.png``; any other sample (the
    anonymous test set, built from its flat ``image/`` folder) keeps its input's name,
    ``<frame>.png`` (two samples of one name are refused by the runner, naming both).

    Raises
    ------
    ParameterError
        A sample that is not 1216x352.
    """
    seq, frame = sample.sequence, sample.frame
    if (sample.width, sample.height) != DC_SIZE:
        raise ParameterError(
            f"--layout kitti-dc: sample '{seq}/{frame}' is {sample.width}x{sample.height}, the "
            f"depth-completion selection sets are {DC_SIZE[0]}x{DC_SIZE[1]} (build the dataset "
            "with `dataset kitti-dc --selection`)",
            param="layout",
        )
    if _DRIVE.fullmatch(seq) and frame.isdigit() and len(frame) == 10:
        return f"{seq}_groundtruth_depth_{frame}_image_02.png"
    return f"{frame}.png"


@dataclass(frozen=True)
class PredictJob(BatchJob[PredictInput]):
    """``predict``: each sample's predicted depth written as a KITTI depth PNG.

    Attributes
    ----------
    settings : PredictSettings
    predictor : DepthPredictor
        Runs in this process (the command runs frames serially: one model, one device).
    """

    command: ClassVar[str] = "predict"
    noun: ClassVar[str] = "predicted depth maps"
    stats_type: ClassVar[type[FrameStats]] = PredictStats

    settings: PredictSettings = field(default_factory=PredictSettings)
    predictor: Any = field(default=None, compare=False, repr=False)

    def planned(self, frames: list[PredictSample]) -> PredictJob:
        """Checks every sample's size (and ``kitti-dc`` name) before the output folder is made."""
        for s in frames:
            check_int_range(s.width, "width", low=1)
            check_int_range(s.height, "height", low=1)
            if self.settings.layout == "kitti-dc":
                kitti_dc_name(s)
        return self

    def tasks(self, frames: list[PredictSample], out_dir: Path) -> list[FrameTask[PredictInput]]:
        """One task per sample."""
        out = []
        for s in frames:
            if self.settings.layout == "kitti-dc":
                target = Path(out_dir) / kitti_dc_name(s)
            else:
                target = s.key.path(out_dir, f".{self.settings.format}")
            sources = tuple(Path(p) for p in s.sources)
            out.append(FrameTask(s.key, PredictInput(s.index, s.width, s.height),
                                 {"depth": target}, sources))  # fmt: skip
        return out

    def __call__(self, task: FrameTask[PredictInput]) -> PredictStats:
        from ..io.atomic import atomic_path
        from ..io.image import encode_depth_png

        inp = task.inputs
        depth = np.asarray(self.predictor.depth(inp.index))
        if depth.shape != (inp.height, inp.width):
            raise FormatError(
                f"the model gave a {depth.shape[-1]}x{depth.shape[0]} map for a "
                f"{inp.width}x{inp.height} sample"
            )
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(depth) & (depth > 0)
        n_valid = int(np.count_nonzero(valid))
        if self.settings.format == "npy":
            buf = io.BytesIO()
            np.save(buf, np.where(valid, depth, 0).astype(np.float32), allow_pickle=False)
            data, clipped = buf.getvalue(), 0
        else:
            data, clipped = encode_depth_png(depth)
        with atomic_path(task.outputs["depth"]) as tmp:
            tmp.write_bytes(data)
        return PredictStats(
            pixels=int(depth.size),
            holes=int(depth.size - n_valid),
            clipped=int(clipped),
            min_depth=float(depth[valid].min()) if n_valid else None,
            max_depth=float(depth[valid].max()) if n_valid else None,
        )

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Totals: ``holes`` and ``clipped`` pixels, the frames that have any (count and first
        names), the layout and the output folder."""
        ids = [r.frame_id for r in summary.ok]
        stats = self.stats(summary)
        with_holes = [i for i, s in zip(ids, stats, strict=True) if s.holes]
        with_clipped = [i for i, s in zip(ids, stats, strict=True) if s.clipped]
        out = {
            "layout": self.settings.layout,
            "holes": sum(s.holes for s in stats),
            "frames_with_holes": len(with_holes),
            "clipped": sum(s.clipped for s in stats),
            "frames_with_clipped": len(with_clipped),
        }
        if with_holes:
            out["holes_first"] = with_holes[:_SHOWN]
        if with_clipped:
            out["clipped_first"] = with_clipped[:_SHOWN]
        out["output"] = str(out_dir)
        return out
