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
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import Frame, FrameKey
from ..validate import check_odd, check_positive
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask
from .provenance import settings_dict

__all__ = [
    "UnderwaterJob",
    "UnderwaterSegment",
    "UnderwaterSettings",
    "UnderwaterStats",
    "segment_tasks",
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
    """What the compensated frames depend on (besides their input frames).

    Attributes
    ----------
    window : int
        Seafloor frames in each temporal median (odd; ``--median-window``).
    eps : float
        Smallest factor F kept; pixels below are masked invalid.
    white_balance : bool
        Gray-world white balance of every output.
    a_ref : tuple of float, optional
        Reference albedo (one value or R, G, B; grey levels); None: each sequence's median of
        ``M - B`` over its first window.
    """

    window: int = field(default=31, metadata={"option": "--median-window"})
    eps: float = 1e-3
    white_balance: bool = False
    a_ref: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "window", check_odd(self.window, "median_window"))
        object.__setattr__(self, "eps", check_positive(self.eps, "eps"))
        object.__setattr__(self, "white_balance", bool(self.white_balance))
        if self.a_ref is not None:
            values = tuple(check_positive(v, "a_ref") for v in np.atleast_1d(self.a_ref))
            if len(values) not in (1, 3):
                raise ParameterError(
                    f"expected one value or three (R, G, B), got {len(values)}", param="a_ref"
                )
            object.__setattr__(self, "a_ref", values)


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
    backscatter : str
        The run's backscatter file (``OUT/backscatter.npy``).
    """

    paths: tuple[str, ...]
    emit: tuple[int, int]
    a_ref: tuple[float, ...]
    backscatter: str = ""


def segment_tasks(
    frames: list[Frame],
    out_dir: Path,
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
            outputs[f"image@{f.id}"] = f.key.path(out_dir, ".png")
            outputs[f"mask@{f.id}"] = f.key.path(out_dir, ".png", prefix=MASK_DIR)
        key = FrameKey(frames[s].key.sequence, f"{frames[s].key.frame}..{frames[e - 1].key.frame}")
        sources = tuple(f.image for f in frames[lo:hi]) + tuple(extra_sources)
        inp = UnderwaterSegment(tuple(str(f.image) for f in frames[lo:hi]), (s - lo, e - lo), a_ref,
                                str(out_dir / BACKSCATTER_FILE))  # fmt: skip
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
class UnderwaterStats(FrameStats):
    """One segment: images written, pixels masked invalid (``F < eps``)."""

    images: int
    invalid_pixels: int


@dataclass(frozen=True)
class UnderwaterJob(BatchJob[UnderwaterSegment]):
    """``sparsetools underwater`` (picklable): the backscatter and each sequence's A_ref are
    fixed by :meth:`planned`; a task streams one segment (with context) and writes its
    frames.

    Attributes
    ----------
    settings : UnderwaterSettings
    water : tuple of Path
        The water-only frames (one backscatter for every sequence).
    backscatter : (H, W, C) float array, set by :meth:`planned`
    a_refs : dict of sequence -> tuple of float, set by :meth:`planned`
    """

    command: ClassVar[str] = "underwater"
    noun: ClassVar[str] = "compensated frames"
    stats_type: ClassVar[type[FrameStats]] = UnderwaterStats
    #: workers read the backscatter from its file: the array is not sent with every task
    parent_only: ClassVar[tuple[str, ...]] = ("backscatter",)

    settings: UnderwaterSettings = field(default_factory=UnderwaterSettings)
    water: tuple[Path, ...] = ()
    backscatter: np.ndarray | None = field(default=None, compare=False, repr=False)
    a_refs: Mapping[str, tuple[float, ...]] = field(default_factory=dict)
    frames_total: int = 0

    def planned(self, frames: list[Frame]) -> UnderwaterJob:
        """Measure the backscatter (median of the water frames) and each sequence's A_ref
        (its first window), checking sizes and sequence lengths first."""
        from ..ops.underwater import UnderwaterCompensator

        st = self.settings
        if not self.water:
            raise FormatError("no water-only frames: give --water")
        if not frames:
            raise ParameterError("no seafloor frames given")
        for seq, fs in _sequences(frames).items():
            if len(fs) < st.window:
                name = f"sequence {seq}" if seq else "the sequence"
                raise ParameterError(
                    f"only {len(fs)} seafloor frame(s) in {name}, fewer than the median window "
                    f"of {st.window} (use --median-window {max(1, len(fs) - (1 - len(fs) % 2))} "
                    "or fewer)"
                )
        comp = UnderwaterCompensator(_frames([str(p) for p in self.water]), window=st.window,
                                     a_ref=None if st.a_ref is None else list(st.a_ref),
                                     eps=st.eps, white_balance=st.white_balance)  # fmt: skip
        shape = _first_shape(frames[0].image)
        if comp.backscatter.shape[:2] != shape[:2]:
            raise FormatError(
                f"water-only frames are {comp.backscatter.shape[1]}x{comp.backscatter.shape[0]} "
                f"but the seafloor frames are {shape[1]}x{shape[0]}"
            )
        a_refs = {}
        for seq, fs in _sequences(frames).items():
            if st.a_ref is None:
                median = comp.first_window_median(_frames([str(f.image) for f in fs[: st.window]]))
                a_refs[seq] = tuple(float(v) for v in comp.reference_albedo(median))
            else:
                a_refs[seq] = tuple(float(v) for v in np.broadcast_to(st.a_ref, (3,))[: shape[2]])
        return replace(self, backscatter=comp.backscatter, a_refs=a_refs,
                       frames_total=len(frames))  # fmt: skip

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[UnderwaterSegment]]:
        """Segments of consecutive frames of each sequence (:func:`segment_tasks`)."""
        st = self.settings
        tasks = []
        for seq, fs in _sequences(frames).items():
            a_sources = tuple(f.image for f in fs[: st.window]) if st.a_ref is None else ()
            tasks.extend(segment_tasks(fs, out_dir, window=st.window, a_ref=self.a_refs[seq],
                                       extra_sources=tuple(self.water) + a_sources))  # fmt: skip
        return tasks

    def shared_outputs(self, out_dir: Path) -> tuple[Path, ...]:
        return (out_dir / BACKSCATTER_FILE, out_dir / SETTINGS_FILE)

    def before(self, out_dir: Path, batch) -> None:
        """Write the backscatter (read by every task) and the run's ``underwater.json``."""
        _save_if_changed(out_dir / BACKSCATTER_FILE, self.backscatter)
        doc = {**settings_dict(self.settings),
               "a_ref_per_sequence": {k: list(v) for k, v in self.a_refs.items()},
               "frames": self.frames_total, "water_frames": len(self.water),
               "backscatter_file": BACKSCATTER_FILE}  # fmt: skip
        with atomic_path(out_dir / SETTINGS_FILE) as tmp:
            tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")

    def __call__(self, task: FrameTask[UnderwaterSegment]) -> UnderwaterStats:
        from ..ops.underwater import UnderwaterCompensator

        st, seg = self.settings, task.inputs
        comp = UnderwaterCompensator.from_backscatter(
            np.load(seg.backscatter),
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
        return UnderwaterStats(images=len(images), invalid_pixels=invalid)

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Totals, named by what they count (a task is a segment of frames): ``frames`` (the
        seafloor frames given), ``frames_processed`` (compensated now),
        ``frames_skipped_existing`` (up to date), ``segments`` and ``segments_processed``,
        ``segments_skipped_existing``, ``segments_recomputed``, ``segments_failed``; then
        ``window``, ``a_ref`` (per sequence when there are several) and ``invalid_pixels``."""
        stats = self.stats(summary)
        done = {r.frame_id for r in summary.done}
        images = {r.frame_id: st.images for r, st in zip(summary.ok, stats, strict=True)}
        a_refs = {k: list(v) for k, v in self.a_refs.items()}
        return {
            "frames": self.frames_total,
            "frames_processed": sum(n for fid, n in images.items() if fid in done),
            "frames_skipped_existing": sum(n for fid, n in images.items() if fid not in done),
            "segments": len(summary.results),
            "segments_processed": len(summary.done),
            "segments_skipped_existing": len(summary.resumed),
            "segments_recomputed": len(summary.recomputed),
            "segments_failed": len(summary.failed),
            "window": self.settings.window,
            "a_ref": a_refs[next(iter(a_refs))] if len(a_refs) == 1 else a_refs,
            "invalid_pixels": sum(st.invalid_pixels for st in stats),
        }


def _sequences(frames: list[Frame]) -> dict[str, list[Frame]]:
    sequences: dict[str, list[Frame]] = {}
    for f in frames:
        sequences.setdefault(f.key.sequence, []).append(f)
    return sequences


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


def _first_shape(path: Path) -> tuple[int, int, int]:
    from ..io.image import image_size_of

    w, h = image_size_of(path)
    return (h, w, 3)
