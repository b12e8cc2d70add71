"""Batch job of ``sparsetools underwater``: median lighting compensation of a frame sequence.

The backscatter ``B`` (median of the water-only frames) and ``A_ref`` (from the first
window) are computed once, saved as ``OUT/backscatter.npy`` and ``OUT/underwater.json``,
and the sequence is cut into segments of consecutive frames. Each segment is one task: it
streams its frames plus ``window // 2`` frames of context on each side through an
:class:`~sparsetools.ops.underwater.UnderwaterCompensator`, so every frame gets exactly the
window a single pass would give it (the output does not depend on ``--workers``), and each
worker holds only ``window`` frames.

Outputs: ``OUT/<stem>.png`` (corrected albedo in image units, clipped to 8 bits) and
``OUT/mask/<stem>.png`` (255 = valid, 0 = ``F < eps``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import FormatError, OutputError, ParameterError
from ..io.atomic import atomic_path
from .core import FrameTask, check_output_dir, run_frames
from .lowlight import collect_images

__all__ = ["run_underwater", "underwater_segment", "underwater_tasks"]

SETTINGS_FILE = "underwater.json"
BACKSCATTER_FILE = "backscatter.npy"
MASK_DIR = "mask"


def _frames(paths: list[str], shape: tuple | None = None) -> Iterator[np.ndarray]:
    """Read frames lazily, checking that they share one size."""
    from ..io.image import read_image

    for p in paths:
        img = read_image(p)
        if shape is None:
            shape = img.shape
        elif img.shape != shape:
            raise FormatError(
                f"{p}: {img.shape[1]}x{img.shape[0]} image in a {shape[1]}x{shape[0]} sequence"
            )
        yield img


def segment_length(window: int) -> int:
    """Frames per task: long enough that the shared context (window - 1) costs little."""
    return max(2 * window, 32)


def underwater_tasks(
    files: list[Path], out_dir: str | os.PathLike, *, window: int, settings: dict
) -> list[FrameTask]:
    """Tasks of consecutive frames; ``settings`` holds the backscatter file and A_ref."""
    out = Path(out_dir)
    n_frames = len(files)
    h = window // 2
    seg = segment_length(window)
    tasks = []
    for s in range(0, n_frames, seg):
        e = min(s + seg, n_frames)
        # Context so frames s..e-1 see their centred (or end-shifted) windows.
        lo = min(max(s - h, 0), n_frames - window)
        hi = min(max(e - 1 - h, 0), n_frames - window) + window
        outputs = tuple(out / f"{f.stem}.png" for f in files[s:e]) + tuple(
            out / MASK_DIR / f"{f.stem}.png" for f in files[s:e]
        )
        tasks.append(FrameTask(
            f"{files[s].stem}..{files[e - 1].stem}",
            {"paths": [str(f) for f in files[lo:hi]], "emit": (s - lo, e - lo),
             "settings": settings},
            outputs,
        ))  # fmt: skip
    return tasks


def _write_png(path, array: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", array)
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 PNG
        raise FormatError(f"{path}: OpenCV cannot encode PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


def underwater_segment(task: FrameTask) -> dict:
    """Per-task job: stream one segment (with context) and write its corrected frames."""
    from ..ops.underwater import UnderwaterCompensator

    st = task.inputs["settings"]
    comp = UnderwaterCompensator.from_backscatter(
        np.load(st["backscatter_file"]),
        window=st["window"],
        a_ref=st["a_ref"],
        eps=st["eps"],
        white_balance=st["white_balance"],
    )
    n_out = len(task.outputs) // 2
    invalid = 0
    results = comp.process(_frames(task.inputs["paths"]), emit=tuple(task.inputs["emit"]))
    for k, (albedo, valid) in enumerate(results):
        rgb = np.clip(np.rint(albedo), 0, 255).astype(np.uint8)
        if rgb.shape[2] == 1:
            rgb = np.repeat(rgb, 3, axis=2)
        _write_png(task.outputs[k], np.ascontiguousarray(rgb[:, :, ::-1]))
        _write_png(task.outputs[n_out + k], valid.astype(np.uint8) * 255)
        invalid += int(valid.size - np.count_nonzero(valid))
    return {"images": n_out, "invalid_pixels": invalid}


def run_underwater(
    seafloor,
    water,
    out_dir: str | os.PathLike,
    *,
    window: int = 31,
    eps: float = 1e-3,
    a_ref=None,
    white_balance: bool = False,
    executor=None,
    overwrite: bool = False,
    on_error: str = "stop",
    progress: bool | None = None,
) -> dict:
    """Compensate the lighting of a seafloor sequence.

    Parameters
    ----------
    seafloor : path-like or list of path-like
        Folder(s)/files of seafloor frames, in time order (sorted by name within a folder).
    water : path-like or list of path-like
        Water-only frames (folder or files).
    out_dir : path-like
    window, eps, a_ref, white_balance
        See :class:`~sparsetools.ops.underwater.UnderwaterCompensator`.

    Returns
    -------
    dict
        Run summary plus ``a_ref`` (per channel), ``window`` and ``invalid_pixels``.
    """
    from ..ops.underwater import UnderwaterCompensator

    seafloor = [seafloor] if isinstance(seafloor, (str, os.PathLike)) else list(seafloor)
    water = [water] if isinstance(water, (str, os.PathLike)) else list(water)
    try:
        water_files = collect_images(water)
    except (FormatError, ParameterError) as exc:
        raise FormatError(f"no water-only frames: {exc}") from exc
    files = collect_images(seafloor)
    if len(files) < window:
        raise ParameterError(
            f"only {len(files)} seafloor frame(s), fewer than the median window of {window} "
            f"(use --window {max(1, len(files) - (1 - len(files) % 2))} or fewer)"
        )
    check_output_dir(out_dir, [*map(str, seafloor), *map(str, water)])
    comp = UnderwaterCompensator(_frames([str(f) for f in water_files]), window=window,
                                 a_ref=a_ref, eps=eps, white_balance=white_balance)  # fmt: skip
    if comp.backscatter.shape[:2] != _first_shape(files[0])[:2]:
        raise FormatError(
            f"water-only frames are {comp.backscatter.shape[1]}x{comp.backscatter.shape[0]} but "
            f"the seafloor frames are {_first_shape(files[0])[1]}x{_first_shape(files[0])[0]}"
        )
    if comp.a_ref is None:
        median = comp.first_window_median(_frames([str(f) for f in files[:window]]))
        comp.a_ref = comp.reference_albedo(median)
    out = Path(out_dir)
    settings = {
        "window": int(window), "eps": float(eps), "white_balance": bool(white_balance),
        "a_ref": [float(v) for v in comp.a_ref], "frames": len(files),
        "water_frames": len(water_files), "first_frame": str(files[0]),
        "backscatter_file": BACKSCATTER_FILE,  # relative to OUT
    }  # fmt: skip
    settings_path = out / SETTINGS_FILE
    if settings_path.is_file() and not overwrite:
        try:
            old = json.loads(settings_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise FormatError(f"{settings_path}: unreadable ({exc}); use --overwrite") from exc
        if old != settings:
            raise OutputError(
                f"{out_dir} holds frames compensated with other settings (window, eps, A_ref or "
                "inputs); use --overwrite or another output folder"
            )
    with atomic_path(out / BACKSCATTER_FILE) as tmp, open(tmp, "wb") as fh:
        np.save(fh, comp.backscatter)
    with atomic_path(settings_path) as tmp:
        tmp.write_text(json.dumps(settings, indent=1) + "\n", encoding="utf-8")
    task_settings = {**settings, "backscatter_file": str(out / BACKSCATTER_FILE)}
    tasks = underwater_tasks(files, out_dir, window=window, settings=task_settings)
    summary = run_frames(underwater_segment, tasks, executor=executor, overwrite=overwrite,
                         on_error=on_error, progress=progress, desc="underwater")  # fmt: skip
    result = summary.as_dict()  # frames / processed / skipped count segments (tasks)
    result["segments"] = result.pop("frames")
    result["frames"] = len(files)
    result["images"] = int(summary.total("images"))
    result["window"] = int(window)
    result["a_ref"] = settings["a_ref"]
    result["invalid_pixels"] = int(summary.total("invalid_pixels"))
    return result


def _first_shape(path: Path) -> tuple[int, int, int]:
    from ..io.sources import image_size_of

    w, h = image_size_of(path)
    return (h, w, 3)
