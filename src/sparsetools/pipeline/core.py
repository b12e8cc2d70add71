"""Batch execution of a per-frame function over many frames.

Every batch command builds a list of :class:`FrameTask` (one per frame: its id, its inputs,
the outputs it will write) and hands it to :func:`run_frames`, which

- skips tasks whose outputs all exist (outputs are written atomically, so existing means
  complete) unless ``overwrite`` — an interrupted run resumes where it stopped;
- runs the rest on an :class:`Executor` (serial, a local process pool, or Dask — the
  interface is :meth:`Executor.map`), in chunks so a lost worker loses little;
- shows a progress bar on stderr (off when stderr is not a TTY or ``progress=False``);
- applies the error policy: ``on_error="stop"`` raises at the first failed frame,
  ``"skip"`` records it and goes on; the summary lists failures.

The per-frame function must be a picklable module-level callable ``fn(task) -> dict`` that
writes its outputs itself (atomically) and returns per-frame statistics.
"""

from __future__ import annotations

import logging
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from ..errors import FrameError, OutputError, ParameterError, SparsetoolsError
from ..io.atomic import remove_stale_temporaries

__all__ = [
    "Executor",
    "FrameResult",
    "FrameTask",
    "LocalExecutor",
    "RunSummary",
    "SerialExecutor",
    "check_output_dir",
    "make_executor",
    "run_frames",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameTask:
    """One unit of batch work.

    Attributes
    ----------
    frame_id : str
        Stable identifier (usually the file stem); used for messages and per-frame seeds.
    inputs : dict
        Whatever the per-frame function needs (paths, parameters); must be picklable.
    outputs : tuple of Path
        Files the function writes. When all exist the task is skipped (resume).
    """

    frame_id: str
    inputs: dict = field(default_factory=dict)
    outputs: tuple[Path, ...] = ()


@dataclass
class FrameResult:
    frame_id: str
    ok: bool
    stats: dict = field(default_factory=dict)
    error: str = ""
    skipped: bool = False


@dataclass
class RunSummary:
    """What a batch did: per-frame results, in task order."""

    results: list[FrameResult] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def done(self) -> list[FrameResult]:
        return [r for r in self.results if r.ok and not r.skipped]

    @property
    def resumed(self) -> list[FrameResult]:
        return [r for r in self.results if r.skipped]

    @property
    def failed(self) -> list[FrameResult]:
        return [r for r in self.results if not r.ok]

    def total(self, key: str) -> float:
        """Sum of a numeric per-frame statistic over the frames done in this run."""
        return sum(r.stats.get(key, 0) for r in self.done)

    def as_dict(self) -> dict:
        return {
            "frames": len(self.results),
            "processed": len(self.done),
            "skipped_existing": len(self.resumed),
            "failed": len(self.failed),
            "failures": {r.frame_id: r.error for r in self.failed},
            "seconds": round(self.seconds, 3),
        }


class Executor(Protocol):
    """Maps a function over items; results may arrive in any order.

    ``map(fn, items)`` yields ``fn(item)`` for each item. A Dask executor implements the
    same method on a cluster.
    """

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]: ...


class SerialExecutor:
    """Runs everything in this process (``--workers 1``): simplest, best for debugging."""

    def map(self, fn, items):
        for item in items:
            yield fn(item)


class LocalExecutor:
    """A local process pool of ``workers`` processes."""

    def __init__(self, workers: int):
        self.workers = workers

    def map(self, fn, items):
        # chunksize keeps the inter-process overhead small for cheap frames.
        chunksize = max(1, min(16, len(items) // (4 * self.workers) or 1))
        with ProcessPoolExecutor(max_workers=self.workers) as pool:
            yield from pool.map(fn, items, chunksize=chunksize)


def make_executor(
    kind: str = "local", *, workers: int = 1, scheduler: str | None = None
) -> Executor:
    """Executor by name: ``local`` (serial for 1 worker, else a process pool) or ``dask``."""
    if workers < 1:
        raise ParameterError(f"--workers must be >= 1, got {workers}")
    if kind == "local":
        return SerialExecutor() if workers == 1 else LocalExecutor(workers)
    if kind == "dask":
        from .dask import DaskExecutor  # optional dependency, imported only when asked

        return DaskExecutor(workers=workers, scheduler=scheduler)
    raise ParameterError(f"unknown executor '{kind}' (choose local or dask)")


class _Guarded:
    """Picklable wrapper turning exceptions into FrameResult (so one bad frame can't kill a pool)."""

    def __init__(self, fn: Callable[[FrameTask], dict], debug: bool):
        self.fn = fn
        self.debug = debug

    def __call__(self, task: FrameTask) -> FrameResult:
        try:
            stats = self.fn(task) or {}
            return FrameResult(task.frame_id, True, stats)
        except SparsetoolsError as exc:
            return FrameResult(task.frame_id, False, error=str(exc))
        except Exception as exc:  # an unexpected bug: keep the traceback for --debug
            detail = traceback.format_exc() if self.debug else f"{type(exc).__name__}: {exc}"
            return FrameResult(task.frame_id, False, error=f"internal error: {detail}")


def _complete(task: FrameTask) -> bool:
    return bool(task.outputs) and all(Path(p).is_file() for p in task.outputs)


def run_frames(
    fn: Callable[[FrameTask], dict],
    tasks: Iterable[FrameTask],
    *,
    executor: Executor | None = None,
    overwrite: bool = False,
    on_error: str = "stop",
    progress: bool | None = None,
    desc: str = "frames",
    debug: bool = False,
) -> RunSummary:
    """Run ``fn`` over ``tasks`` with resume, progress and an error policy.

    Parameters
    ----------
    fn : callable(FrameTask) -> dict
        Module-level (picklable) per-frame function; writes its outputs atomically.
    tasks : iterable of FrameTask
    executor : Executor, optional
        Default: serial.
    overwrite : bool
        Recompute frames whose outputs exist.
    on_error : {"stop", "skip"}
        Stop at the first failed frame (raising :class:`FrameError`), or record it and go on.
    progress : bool, optional
        Progress bar on stderr; default: only when stderr is a TTY.

    Returns
    -------
    RunSummary
        With ``on_error="skip"`` the caller decides the exit status from ``summary.failed``.
    """
    if on_error not in ("stop", "skip"):
        raise ParameterError(f"on_error must be 'stop' or 'skip', got {on_error!r}")
    tasks = list(tasks)
    ids = [t.frame_id for t in tasks]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise ParameterError(f"two inputs map to the same frame id: {', '.join(dup[:5])}")
    t0 = time.perf_counter()
    for folder in {Path(p).parent for t in tasks for p in t.outputs}:
        remove_stale_temporaries(folder, recursive=False)
    results: dict[str, FrameResult] = {}
    todo = []
    for t in tasks:
        if not overwrite and _complete(t):
            results[t.frame_id] = FrameResult(t.frame_id, True, skipped=True)
        else:
            todo.append(t)
    if results:
        log.info("%d of %d frame(s) already done, skipping them", len(results), len(tasks))
    executor = executor or SerialExecutor()
    show = sys.stderr.isatty() if progress is None else progress
    bar = None
    if show and todo:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), desc=desc, unit="frame", file=sys.stderr, leave=False)
    try:
        for res in executor.map(_Guarded(fn, debug), todo):
            results[res.frame_id] = res
            if bar is not None:
                bar.update(1)
            if not res.ok:
                if on_error == "stop":
                    raise FrameError(f"frame {res.frame_id}: {res.error}")
                log.warning("frame %s failed: %s", res.frame_id, res.error)
    finally:
        if bar is not None:
            bar.close()
    return RunSummary([results[i] for i in ids if i in results], time.perf_counter() - t0)


def check_output_dir(out_dir: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> Path:
    """Validate an output folder before a batch starts.

    Refuses a path that is an existing file, a folder that cannot be created or written,
    and an output folder inside an input folder (outputs would be read back as inputs on
    the next run). Creates the folder.
    """
    out = Path(out_dir).resolve()
    if out.exists() and not out.is_dir():
        raise OutputError(f"output {out_dir} is a file, expected a folder")
    for inp in inputs:
        ip = Path(inp).resolve()
        if ip.is_dir() and (out == ip or ip in out.parents):
            raise OutputError(f"output folder {out_dir} is inside the input folder {inp}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create output folder {out_dir}: {exc.strerror or exc}") from exc
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"output folder {out_dir} is not writable")
    return Path(out_dir)
