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
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ParameterError
from ..io.atomic import atomic_path
from ..io.sources import Frame
from ..validate import check_choice, check_positive
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames
from .lowlight import image_frames

__all__ = [
    "LUT_FILE",
    "EqualizeInput",
    "EqualizeJob",
    "EqualizeSettings",
    "equalize_tasks",
    "resolve_reference",
    "run_equalize",
]

LUT_FILE = "mcie_lut.json"


@dataclass(frozen=True)
class EqualizeSettings:
    """What the equalised frames depend on: the clip limit, the reference frame and the
    table arithmetic (``nearest`` or ``rnw``, :func:`sparsetools.ops.enhance.mcie_lut`)."""

    clip: float = 0.004
    reference: str = field(default="", metadata={"option": "--reference"})
    rounding: str = "nearest"

    def __post_init__(self) -> None:
        from ..ops.enhance import ROUNDINGS

        check_positive(self.clip, "clip")
        check_choice(self.rounding, "rounding", ROUNDINGS)


@dataclass(frozen=True)
class EqualizeInput:
    image: str


def resolve_reference(reference, frames: list[Frame]) -> Path:
    """The reference frame: a path, or the frame id / name / file name of one input
    (default: the first)."""
    if reference is None:
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
            param="reference",
        )
    raise ParameterError(
        f"frame '{reference}' is neither a file nor the name of an input", param="reference"
    )


@dataclass(frozen=True)
class EqualizeJob:
    """The per-frame job (picklable): read (grey becomes RGB, 16-bit is refused), map, write."""

    lut: np.ndarray

    def __call__(self, task: FrameTask[EqualizeInput]) -> dict:
        from ..io.image import read_image, write_image
        from ..ops.enhance import apply_lut

        image = read_image(task.inputs.image)
        out = apply_lut(image, self.lut)
        write_image(task.outputs["image"], out)
        return {"mean_before": float(image.mean()), "mean_after": float(out.mean())}


def equalize_tasks(
    frames: list[Frame], out_dir: str | os.PathLike, reference: Path
) -> list[FrameTask[EqualizeInput]]:
    out = Path(out_dir)
    return [
        FrameTask(
            f.key,
            EqualizeInput(str(f.image)),
            {"image": f.key.path(out, ".png")},
            (f.image, reference),
        )
        for f in frames
    ]


def _lut_document(reference: Path, clip: float, rounding: str, lut: np.ndarray) -> dict:
    return {
        "method": "MCIE (RNW): per-channel clipped histogram equalisation, one table for all",
        "reference": str(reference),
        "clip": clip,
        "rounding": rounding,
        "lut": [lut[:, c].tolist() for c in range(lut.shape[1])],
    }


def run_equalize(
    images,
    out_dir: str | os.PathLike,
    *,
    clip: float = 0.004,
    reference=None,
    rounding: str = "nearest",
    batch: Batch | None = None,
) -> RunSummary:
    """Equalise a sequence with one MCIE table built from the reference frame.

    Parameters
    ----------
    images : list of path-like
        Image files and/or folders.
    out_dir : path-like
    clip : float
        Clip limit as a fraction of the reference's pixel count.
    reference : path-like or str, optional
        A file, or the frame id / name of one input (default: the first).
    rounding : {"nearest", "rnw"}
        Table arithmetic: rounded to nearest, or RNW's released integer version.
    batch : Batch, optional

    Returns
    -------
    RunSummary
        Totals: ``reference``, ``rounding`` and ``lut_file``.
    """
    from ..io.image import read_image
    from ..ops.enhance import mcie_lut

    batch = batch or Batch()
    frames = image_frames(images)
    ref = resolve_reference(reference, frames)
    settings = EqualizeSettings(clip=clip, reference=str(ref.resolve()), rounding=rounding)
    out = check_output_dir(out_dir, [*map(str, images), str(ref)])
    lut = mcie_lut(read_image(ref), clip=clip, rounding=rounding)
    tasks = equalize_tasks(frames, out, ref)
    spec = RunSpec(
        "equalize", out, settings, noun="equalised frames", shared_outputs=(out / LUT_FILE,)
    )
    summary = run_frames(EqualizeJob(lut), tasks, batch=batch, spec=spec)
    lut_path = out / LUT_FILE
    with atomic_path(lut_path) as tmp:
        tmp.write_text(json.dumps(_lut_document(ref, clip, rounding, lut)) + "\n", encoding="utf-8")
    return summary.with_totals(
        {"reference": str(ref), "rounding": rounding, "lut_file": str(lut_path)}
    )
