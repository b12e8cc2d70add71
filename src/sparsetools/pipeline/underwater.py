"""Batch job of ``sparsetools underwater``: median lighting compensation of a frame sequence.

The backscatter ``B`` (median of the water-only frames) and each sequence's ``A_ref`` (from
its first window) are computed once, saved as ``OUT/backscatter.npy`` and
``OUT/underwater.json``, and every sequence is cut into segments of consecutive frames. Each segment is one task: it
streams its frames plus ``window // 2`` frames of context on each side through an
:class:`~sparsetools.ops.underwater.UnderwaterCompensator`, so every frame gets exactly the
window a single pass would give it (the output does not depend on ``--workers``), and each
worker holds only ``window`` frames.

Outputs: ``OUT/<sequence>/<frame>.png`` (corrected albedo in image units, clipped to 8 bits)
and ``OUT/mask/<sequence>/<frame>.png`` (255 = valid, 0 = ``F < eps``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import Frame, FrameKey
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames
from .provenance import settings_dict

__all__ = [
    "UnderwaterJob",
    "UnderwaterSegment",
    "UnderwaterSettings",
    "run_underwater",
    "underwater_tasks",
]

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


@dataclass(frozen=True)
class UnderwaterSettings:
    """What the compensated frames depend on (besides their input frames)."""

    window: int = 31
    eps: float = 1e-3
    white_balance: bool = False
    a_ref: tuple[float, ...] | None = None


@dataclass(frozen=True)
class UnderwaterSegment:
    """One task: consecutive frames of a sequence plus their context, and where to emit.

    Attributes
    ----------
    paths : tuple of str
        The frames streamed (segment plus ``window // 2`` context frames on each side).
    emit : (start, stop)
        Indices into ``paths`` of the frames written.
    a_ref : tuple of float
        The sequence's reference albedo per channel.
    """

    paths: tuple[str, ...]
    emit: tuple[int, int]
    a_ref: tuple[float, ...]


def underwater_tasks(
    frames: list[Frame],
    out_dir: str | os.PathLike,
    *,
    window: int,
    a_ref: tuple[float, ...],
    extra_sources: tuple[Path, ...] = (),
) -> list[FrameTask[UnderwaterSegment]]:
    """Tasks of consecutive frames of ONE sequence (frames in time order).

    Each task's sources are its streamed frames plus ``extra_sources`` (the water frames and
    the frames A_ref was measured on), so a changed input recomputes exactly the segments
    that see it.
    """
    out = Path(out_dir)
    n_frames = len(frames)
    h = window // 2
    seg = segment_length(window)
    tasks = []
    for s in range(0, n_frames, seg):
        e = min(s + seg, n_frames)
        # Context so frames s..e-1 see their centred (or end-shifted) windows.
        lo = min(max(s - h, 0), n_frames - window)
        hi = min(max(e - 1 - h, 0), n_frames - window) + window
        outputs = {}
        for f in frames[s:e]:
            outputs[f"image@{f.id}"] = f.key.path(out, ".png")
            outputs[f"mask@{f.id}"] = f.key.path(out, ".png", prefix=MASK_DIR)
        key = FrameKey(frames[s].key.sequence, f"{frames[s].key.frame}..{frames[e - 1].key.frame}")
        sources = tuple(f.image for f in frames[lo:hi]) + tuple(extra_sources)
        inp = UnderwaterSegment(tuple(str(f.image) for f in frames[lo:hi]), (s - lo, e - lo), a_ref)
        tasks.append(FrameTask(key, inp, outputs, tuple(dict.fromkeys(sources))))
    return tasks


def _write_png(path, array: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", array)
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 PNG
        raise FormatError(f"{path}: OpenCV cannot encode PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


@dataclass(frozen=True)
class UnderwaterJob:
    """The per-task job (picklable): stream one segment (with context), write its frames."""

    settings: UnderwaterSettings
    backscatter_file: str

    def __call__(self, task: FrameTask[UnderwaterSegment]) -> dict:
        from ..ops.underwater import UnderwaterCompensator

        st, seg = self.settings, task.inputs
        comp = UnderwaterCompensator.from_backscatter(
            np.load(self.backscatter_file),
            window=st.window,
            a_ref=list(seg.a_ref),
            eps=st.eps,
            white_balance=st.white_balance,
        )
        roles = list(task.outputs)
        images = [task.outputs[r] for r in roles if r.startswith("image@")]
        masks = [task.outputs[r] for r in roles if r.startswith("mask@")]
        invalid = 0
        results = comp.process(_frames(list(seg.paths)), emit=tuple(seg.emit))
        for k, (albedo, valid) in enumerate(results):
            rgb = np.clip(np.rint(albedo), 0, 255).astype(np.uint8)
            if rgb.shape[2] == 1:
                rgb = np.repeat(rgb, 3, axis=2)
            _write_png(images[k], np.ascontiguousarray(rgb[:, :, ::-1]))
            _write_png(masks[k], valid.astype(np.uint8) * 255)
            invalid += int(valid.size - np.count_nonzero(valid))
        return {"images": len(images), "invalid_pixels": invalid}


def _save_if_changed(path: Path, array: np.ndarray) -> None:
    """Write ``array`` as .npy unless the file holds exactly these bytes (keeps its mtime)."""
    import io

    buf = io.BytesIO()
    np.save(buf, array)
    data = buf.getvalue()
    if path.is_file() and path.stat().st_size == len(data) and path.read_bytes() == data:
        return
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def run_underwater(
    seafloor,
    water,
    out_dir: str | os.PathLike,
    *,
    window: int = 31,
    eps: float = 1e-3,
    a_ref=None,
    white_balance: bool = False,
    batch: Batch | None = None,
) -> RunSummary:
    """Compensate the lighting of seafloor sequences.

    Parameters
    ----------
    seafloor : path-like or list of path-like
        Folder(s)/files of seafloor frames; each sequence (sub-folder) is one dive, in time
        order (frame names sorted).
    water : path-like or list of path-like
        Water-only frames (folder or files): one backscatter for every sequence.
    out_dir : path-like
    window, eps, a_ref, white_balance
        See :class:`~sparsetools.ops.underwater.UnderwaterCompensator`. ``a_ref`` None: each
        sequence's per-channel median of ``M - B`` over its first window.
    batch : Batch, optional

    Returns
    -------
    RunSummary
        Tasks are segments of consecutive frames. Totals: ``segments``, ``frames``,
        ``images``, ``window``, ``a_ref`` (per sequence), ``invalid_pixels``.
    """
    from ..ops.underwater import UnderwaterCompensator
    from .lowlight import image_frames

    batch = batch or Batch()
    seafloor = [seafloor] if isinstance(seafloor, (str, os.PathLike)) else list(seafloor)
    water = [water] if isinstance(water, (str, os.PathLike)) else list(water)
    try:
        water_frames = image_frames(water, option="--water")
    except (FormatError, ParameterError) as exc:
        raise FormatError(f"no water-only frames: {exc}") from exc
    frames = image_frames(seafloor, option="SEAFLOOR")
    sequences: dict[str, list[Frame]] = {}
    for f in frames:
        sequences.setdefault(f.key.sequence, []).append(f)
    for seq, fs in sequences.items():
        if len(fs) < window:
            name = f"sequence {seq}" if seq else "the sequence"
            raise ParameterError(
                f"only {len(fs)} seafloor frame(s) in {name}, fewer than the median window of "
                f"{window} (use --window {max(1, len(fs) - (1 - len(fs) % 2))} or fewer)"
            )
    settings = UnderwaterSettings(
        window=int(window), eps=float(eps), white_balance=bool(white_balance),
        a_ref=None if a_ref is None else tuple(float(v) for v in np.atleast_1d(a_ref)),
    )  # fmt: skip
    out = check_output_dir(out_dir, [*map(str, seafloor), *map(str, water)])
    water_paths = [str(f.image) for f in water_frames]
    comp = UnderwaterCompensator(_frames(water_paths), window=window, a_ref=a_ref, eps=eps,
                                 white_balance=white_balance)  # fmt: skip
    shape = _first_shape(frames[0].image)
    if comp.backscatter.shape[:2] != shape[:2]:
        raise FormatError(
            f"water-only frames are {comp.backscatter.shape[1]}x{comp.backscatter.shape[0]} but "
            f"the seafloor frames are {shape[1]}x{shape[0]}"
        )
    backscatter = out / BACKSCATTER_FILE
    tasks, a_refs = [], {}
    water_sources = tuple(f.image for f in water_frames)
    for seq, fs in sequences.items():
        if settings.a_ref is None:
            median = comp.first_window_median(_frames([str(f.image) for f in fs[:window]]))
            seq_a_ref = tuple(float(v) for v in comp.reference_albedo(median))
            a_sources = tuple(f.image for f in fs[:window])
        else:
            seq_a_ref = tuple(float(v) for v in np.broadcast_to(settings.a_ref, (3,))[: shape[2]])
            a_sources = ()
        a_refs[seq] = list(seq_a_ref)
        tasks.extend(
            underwater_tasks(fs, out, window=window, a_ref=seq_a_ref,
                             extra_sources=water_sources + a_sources)
        )  # fmt: skip
    spec = RunSpec(
        "underwater", out, settings, noun="compensated frames",
        shared_outputs=(out / BACKSCATTER_FILE, out / SETTINGS_FILE),
    )  # fmt: skip
    doc = {**settings_dict(settings), "a_ref_per_sequence": a_refs, "frames": len(frames),
           "water_frames": len(water_frames), "backscatter_file": BACKSCATTER_FILE}  # fmt: skip

    def prepare():
        _save_if_changed(backscatter, comp.backscatter)
        with atomic_path(out / SETTINGS_FILE) as tmp:
            tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")

    summary = run_frames(
        UnderwaterJob(settings, str(backscatter)), tasks, batch=batch, spec=spec,
        before=prepare,
    )  # fmt: skip
    n_tasks = len(summary.results)
    return summary.with_totals(
        {
            "segments": n_tasks,
            "frames": len(frames),
            "images": int(summary.total("images")),
            "window": int(window),
            "a_ref": a_refs[next(iter(a_refs))] if len(a_refs) == 1 else a_refs,
            "invalid_pixels": int(summary.total("invalid_pixels")),
        }
    )


def _first_shape(path: Path) -> tuple[int, int, int]:
    from ..io.image import image_size_of

    w, h = image_size_of(path)
    return (h, w, 3)
