"""Batch job of ``sparsetools equalize``: one MCIE table from a reference frame, applied to all.

The table is built once (from ``--reference``, default the first image, with the table
arithmetic ``--rounding``: ``nearest`` or RNW's integer ``rnw``) and stored in
``OUT/mcie_lut.json`` with the reference, clip limit and rounding; every frame is mapped
through it with ``cv2.LUT`` and written as ``OUT/<sequence>/<frame>.png``. The reference frame
is an input of every frame: when it changes, every frame is recomputed; another clip limit,
reference or rounding is refused unless ``--overwrite``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import ParameterError
from ..io.atomic import atomic_path
from ..io.sources import Frame
from ..validate import check_choice, check_range
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask
from .provenance import settings_dict

__all__ = [
    "LUT_FILE",
    "EqualizeInput",
    "EqualizeJob",
    "EqualizeSettings",
    "EqualizeStats",
    "resolve_reference",
]

LUT_FILE = "mcie_lut.json"


@dataclass(frozen=True)
class EqualizeSettings:
    """What the equalised frames depend on: the clip limit, the reference frame and the
    table arithmetic (``nearest`` or ``rnw``, :func:`sparsetools.ops.enhance.mcie_lut`).

    ``reference`` is a file, or the frame id / name / file name of one input ("": the first
    input); the run records the file it resolves to. ``clip`` is a fraction of the pixel
    count in (0, 1]: 1 keeps every bin whole (no clipping), and a larger value means nothing
    more (with ``rnw`` arithmetic ``clip x pixels`` would overflow the table's integers).
    """

    clip: float = 0.004
    reference: str = field(default="", metadata={"option": "--reference-frame"})
    rounding: str = "nearest"

    def __post_init__(self) -> None:
        from ..ops.enhance import ROUNDINGS

        object.__setattr__(
            self, "clip", check_range(self.clip, "clip", low=0, low_open=True, high=1)
        )
        check_choice(self.rounding, "rounding", ROUNDINGS)
        object.__setattr__(self, "reference", str(self.reference or ""))


@dataclass(frozen=True)
class EqualizeInput:
    image: str


def resolve_reference(reference, frames: list[Frame]) -> Path:
    """The reference frame: a path, or the frame id / name of one input (default: the
    first)."""
    if not reference:
        return frames[0].image
    ref = Path(reference)
    if ref.is_file():
        return ref
    text = str(reference)
    matches = [f for f in frames if text in (f.id, f.key.frame, f.image.stem, f.image.name)]
    if len(matches) == 1:
        return matches[0].image
    if len(matches) > 1:
        raise ParameterError(
            f"'{reference}' matches several inputs: {matches[0].image}, {matches[1].image}",
            param="reference_frame",
        )
    raise ParameterError(
        f"frame '{reference}' is neither a file nor the name of an input", param="reference_frame"
    )


@dataclass(frozen=True)
class EqualizeStats(FrameStats):
    """One frame: mean grey level before and after the table."""

    mean_before: float
    mean_after: float


@dataclass(frozen=True)
class EqualizeJob(BatchJob[EqualizeInput]):
    """``sparsetools equalize`` (picklable): one MCIE table, built by :meth:`planned` from the
    reference frame, applied to every frame (grey becomes RGB, 16-bit is refused)."""

    command: ClassVar[str] = "equalize"
    noun: ClassVar[str] = "equalised frames"
    stats_type: ClassVar[type[FrameStats]] = EqualizeStats

    settings: EqualizeSettings = field(default_factory=EqualizeSettings)
    reference: str | None = None
    lut: np.ndarray | None = field(default=None, compare=False, repr=False)

    def planned(self, frames: list[Frame]) -> EqualizeJob:
        from ..io.image import read_image
        from ..ops.enhance import mcie_lut

        if not frames:
            raise ParameterError("no images given")
        ref = resolve_reference(self.settings.reference, frames)
        s = self.settings
        lut = mcie_lut(read_image(ref), clip=s.clip, rounding=s.rounding)
        return replace(self, reference=str(ref), lut=lut)

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[EqualizeInput]]:
        ref = Path(self.reference)
        return [
            FrameTask(f.key, EqualizeInput(str(f.image)), {"image": f.key.path(out_dir, ".png")},
                      (f.image, ref))
            for f in frames
        ]  # fmt: skip

    def record(self) -> dict:
        s = self.settings
        return settings_dict(replace(s, reference=str(Path(self.reference).resolve())))

    def shared_outputs(self, out_dir: Path) -> tuple[Path, ...]:
        return (out_dir / LUT_FILE,)

    def __call__(self, task: FrameTask[EqualizeInput]) -> EqualizeStats:
        from ..io.image import read_image, write_image
        from ..ops.enhance import apply_lut

        image = read_image(task.inputs.image)
        out = apply_lut(image, self.lut)
        write_image(task.outputs["image"], out)
        return EqualizeStats(mean_before=float(image.mean()), mean_after=float(out.mean()))

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Write the table (``OUT/mcie_lut.json``); totals: ``reference``, ``rounding`` and
        ``lut_file``."""
        s = self.settings
        lut_path = out_dir / LUT_FILE
        doc = _lut_document(Path(self.reference), s.clip, s.rounding, self.lut)
        with atomic_path(lut_path) as tmp:
            tmp.write_text(json.dumps(doc) + "\n", encoding="utf-8")
        return {"reference": self.reference, "rounding": s.rounding, "lut_file": str(lut_path)}


def _lut_document(reference: Path, clip: float, rounding: str, lut: np.ndarray) -> dict:
    return {
        "method": "MCIE (RNW): per-channel clipped histogram equalisation, one table for all",
        "reference": str(reference),
        "clip": clip,
        "rounding": rounding,
        "lut": [lut[:, c].tolist() for c in range(lut.shape[1])],
    }
