"""Batch job of ``sparsetools equalize``: one MCIE table from a reference frame, applied to all.

The table is built once (from ``--reference``, default the first image) and stored in
``OUT/mcie_lut.json`` with the reference and clip limit; every frame is mapped through it
with ``cv2.LUT`` and written as ``OUT/<stem>.png``. A rerun resumes; a rerun whose table
differs (other reference or clip) refuses to mix outputs unless ``overwrite``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import FormatError, OutputError, ParameterError
from ..io.atomic import atomic_path
from .core import FrameTask, check_output_dir, run_frames
from .lowlight import collect_images

__all__ = ["LUT_FILE", "equalize_frame", "equalize_tasks", "resolve_reference", "run_equalize"]

LUT_FILE = "mcie_lut.json"


def resolve_reference(reference, files: list[Path]) -> Path:
    """The reference frame: a path, or the stem/name of one of the inputs (default: the first)."""
    if reference is None:
        return files[0]
    ref = Path(reference)
    if ref.is_file():
        return ref
    matches = [f for f in files if str(reference) in (f.stem, f.name)]
    if len(matches) == 1:
        return matches[0]
    if len(matches) > 1:
        raise ParameterError(
            f"reference '{reference}' matches several inputs: {matches[0]}, {matches[1]}"
        )
    raise ParameterError(
        f"reference frame '{reference}' is neither a file nor the stem of an input"
    )


def equalize_tasks(
    files: list[Path], out_dir: str | os.PathLike, lut: np.ndarray
) -> list[FrameTask]:
    out = Path(out_dir)
    return [
        FrameTask(f.stem, {"image": str(f), "lut": lut}, (out / f"{f.stem}.png",)) for f in files
    ]


def equalize_frame(task: FrameTask) -> dict:
    """Per-frame job: read (grey becomes RGB, 16-bit is refused), map, write PNG."""
    from ..io.image import read_image, write_image
    from ..ops.enhance import apply_lut

    image = read_image(task.inputs["image"])
    out = apply_lut(image, task.inputs["lut"])
    write_image(task.outputs[0], out)
    return {"mean_before": float(image.mean()), "mean_after": float(out.mean())}


def _lut_document(reference: Path, clip: float, lut: np.ndarray) -> dict:
    return {
        "method": "MCIE (RNW): per-channel clipped histogram equalisation, one table for all",
        "reference": str(reference),
        "clip": clip,
        "lut": [lut[:, c].tolist() for c in range(lut.shape[1])],
    }


def run_equalize(
    images,
    out_dir: str | os.PathLike,
    *,
    clip: float = 0.004,
    reference=None,
    executor=None,
    overwrite: bool = False,
    on_error: str = "stop",
    progress: bool | None = None,
) -> dict:
    """Equalise a sequence with one MCIE table built from the reference frame.

    Returns
    -------
    dict
        Run summary plus ``reference`` and ``lut_file``.
    """
    from ..io.image import read_image
    from ..ops.enhance import mcie_lut

    files = collect_images(images)
    ref = resolve_reference(reference, files)
    check_output_dir(out_dir, [*map(str, images), str(ref)])
    lut = mcie_lut(read_image(ref), clip=clip)
    doc = _lut_document(ref, clip, lut)
    lut_path = Path(out_dir) / LUT_FILE
    if lut_path.is_file() and not overwrite:
        try:
            old = json.loads(lut_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise FormatError(f"{lut_path}: unreadable ({exc}); use --overwrite") from exc
        if old.get("lut") != doc["lut"]:
            raise OutputError(
                f"{out_dir} holds frames equalised with another table (reference "
                f"{old.get('reference')}, clip {old.get('clip')}); use --overwrite or another "
                "folder"
            )
    tasks = equalize_tasks(files, out_dir, lut)
    with atomic_path(lut_path) as tmp:
        tmp.write_text(json.dumps(doc) + "\n", encoding="utf-8")
    summary = run_frames(equalize_frame, tasks, executor=executor, overwrite=overwrite,
                         on_error=on_error, progress=progress, desc="equalize")  # fmt: skip
    out = summary.as_dict()
    out["reference"] = str(ref)
    out["lut_file"] = str(lut_path)
    return out
