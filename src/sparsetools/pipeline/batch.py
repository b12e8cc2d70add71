"""How a batch runs (:class:`Batch`) and what it did (:class:`RunSummary`): the same two
types for every command.

``Batch`` holds the options every batch command shares (``--workers``, ``--executor``,
``--dask-scheduler``, ``--overwrite``, ``--on-error``, progress, ``--debug``);
the command line builds one from :func:`sparsetools.cli.options.batch_options` and every
``run_*`` function takes it. ``RunSummary`` is what every ``run_*`` returns: per-frame
results in task order plus the command's own totals.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from array import array
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from ..validate import check_choice, check_int_range

__all__ = ["EXECUTORS", "ON_ERROR", "Batch", "FrameResult", "ResultLog", "RunSummary"]

EXECUTORS = ("local", "dask")
ON_ERROR = ("stop", "skip")


@dataclass(frozen=True)
class Batch:
    """Options of how a batch runs; none of them changes what is computed.

    Attributes
    ----------
    workers : int
        Frames processed in parallel (capped by the frames and the CPUs available).
    executor : {"local", "dask"}
    scheduler : str, optional
        Dask scheduler address (default: a local cluster).
    overwrite : bool
        Recompute every frame and replace the folder's results (never files it did not write).
    on_error : {"stop", "skip"}
        Stop at the first failed frame, or record it and go on.
    progress : bool, optional
        Progress bar on stderr; None: only when stderr is a terminal.
    debug : bool
        Keep the traceback of a failed frame (shown by the command line).
    """

    workers: int = 1
    executor: str = "local"
    scheduler: str | None = None
    overwrite: bool = False
    on_error: str = "stop"
    progress: bool | None = None
    debug: bool = False

    def __post_init__(self) -> None:
        check_int_range(self.workers, "workers", low=1)
        check_choice(self.executor, "executor", EXECUTORS)
        check_choice(self.on_error, "on_error", ON_ERROR)

    @property
    def show_progress(self) -> bool:
        return sys.stderr.isatty() if self.progress is None else bool(self.progress)

    def make_executor(self, n_tasks: int):
        """The executor for at most ``n_tasks`` tasks, taken lazily from the iterable given to
        its ``map``; its workers capped (see :func:`usable_workers`)."""
        from .executors import make_executor, usable_workers

        workers = usable_workers(self.workers, n_tasks, cap_cpus=self.scheduler is None)
        return make_executor(self.executor, workers=workers, scheduler=self.scheduler,
                             n_items=n_tasks)  # fmt: skip


@dataclass
class FrameResult:
    """What one task did: ``ok``, its statistics, or its error (one line; with ``debug`` the
    traceback follows in ``detail``)."""

    frame_id: str
    ok: bool
    stats: dict = field(default_factory=dict)
    error: str = ""
    skipped: bool = False
    recomputed: bool = False
    detail: str = ""
    #: identity of each output the job wrote (role -> OutputIdentity), taken where it ran
    output_ids: dict = field(default_factory=dict)


class ResultLog:
    """Per-frame results of a run, read back in task order; O(1) memory per frame.

    A result is kept as one JSON line in an unnamed temporary file (``O_TMPFILE`` where the
    system has it) in a folder the run owns (the output folder's record folder), which
    disappears when the log is closed or collected; without a folder the lines are kept in
    memory. Per frame the log holds 9 bytes (its line's offset and its state).

    Parameters
    ----------
    n : int
        Task positions (results are added by position, in any order).
    folder : path-like, optional
        Where the temporary file goes.
    """

    _STATES: ClassVar[dict[str, int]] = {"none": 0, "done": 1, "resumed": 2, "failed": 3}

    def __init__(self, n: int = 0, folder: str | os.PathLike | None = None):
        self._offsets = array("q", [-1]) * n
        self._state = bytearray(n)  # bit 0-1: state, bit 2: recomputed
        self._lines: list[bytes] | None = None
        self._fh = None
        self._end = 0
        if folder is not None:
            self._fh = tempfile.TemporaryFile(dir=folder)
        else:
            self._lines = []

    def add(self, position: int, result: FrameResult) -> None:
        line = json.dumps(
            [result.frame_id, result.ok, result.skipped, result.recomputed, result.stats,
             result.error, result.detail], default=_json_value,
        ).encode() + b"\n"  # fmt: skip
        if self._lines is not None:
            self._offsets[position] = len(self._lines)
            self._lines.append(line)
        else:
            self._fh.seek(self._end)
            self._fh.write(line)
            self._offsets[position] = self._end
            self._end += len(line)
        state = 3 if not result.ok else 2 if result.skipped else 1
        self._state[position] = state | (4 if result.recomputed else 0)

    def count(self, state: str) -> int:
        if state == "recomputed":
            return sum(1 for b in self._state if b & 4)
        code = self._STATES[state]
        return sum(1 for b in self._state if b & 3 == code)

    def __iter__(self) -> Iterator[FrameResult]:
        return self.select(lambda code: code != 0)

    def select(self, keep) -> Iterator[FrameResult]:
        """Results in task order whose state code (1 done, 2 up to date, 3 failed, +4 when
        recomputed) passes ``keep``."""
        if self._fh is not None:
            self._fh.flush()
        for pos, code in enumerate(self._state):
            if not code or not keep(code):
                continue
            off = self._offsets[pos]
            if self._lines is not None:
                line = self._lines[off]
            else:
                self._fh.seek(off)
                line = self._fh.readline()
            fid, ok, skipped, recomputed, stats, error, detail = json.loads(line)
            yield FrameResult(fid, ok, stats, error, skipped, recomputed, detail)

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
            self._lines = []
            self._offsets = array("q")
            self._state = bytearray()


def _json_value(o):
    if hasattr(o, "item"):  # numpy scalars in statistics
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


@dataclass
class RunSummary:
    """What a batch did: per-frame results in task order, and the command's totals.

    ``as_dict()`` is what the command line prints: ``frames``, ``processed``,
    ``skipped_existing`` (up to date), ``recomputed`` (inputs changed), ``failed``, then the
    command's ``totals``, ``output``, ``seconds`` and ``failures``.

    The per-frame results live in a :class:`ResultLog` (on disk for a run into an output
    folder), so a run over a million frames holds none of them in memory: ``iter_ok()``
    streams them; ``results``, ``done``, ``ok``, ... are lists read from the log when asked.
    """

    command: str = ""
    output: Path | None = None
    seconds: float = 0.0
    totals: dict[str, Any] = field(default_factory=dict)
    removed_stale: int = 0
    #: the run replaced the folder's results (``--overwrite``)
    overwrite: bool = False
    #: frames done whose inputs changed while they ran: not recorded (recomputed next time)
    inputs_changed: list[str] = field(default_factory=list)
    log: ResultLog = field(default_factory=ResultLog, repr=False)

    @property
    def results(self) -> list[FrameResult]:
        return list(self.log)

    @results.setter
    def results(self, results: list[FrameResult]) -> None:
        self.log = ResultLog(len(results))
        for i, r in enumerate(results):
            self.log.add(i, r)

    def iter_ok(self) -> Iterator[FrameResult]:
        """Frames done in this run or up to date, in task order, read one at a time."""
        return self.log.select(lambda code: code & 3 in (1, 2))

    @property
    def done(self) -> list[FrameResult]:
        return list(self.log.select(lambda code: code & 3 == 1))

    @property
    def resumed(self) -> list[FrameResult]:
        return list(self.log.select(lambda code: code & 3 == 2))

    @property
    def failed(self) -> list[FrameResult]:
        return list(self.log.select(lambda code: code & 3 == 3))

    @property
    def recomputed(self) -> list[FrameResult]:
        return list(self.log.select(lambda code: bool(code & 4)))

    @property
    def ok(self) -> list[FrameResult]:
        """Frames done in this run or up to date (with the statistics of their record)."""
        return list(self.iter_ok())

    def total(self, key: str) -> float:
        """Sum of a numeric per-frame statistic over the frames of the run, those done now
        and those up to date (their statistics come from the folder's record)."""
        return sum(r.stats.get(key, 0) for r in self.iter_ok())

    def counts(self) -> dict:
        return {
            "frames": self.log.count("done") + self.log.count("resumed") + self.log.count("failed"),
            "processed": self.log.count("done"),
            "skipped_existing": self.log.count("resumed"),
            "recomputed": self.log.count("recomputed"),
            "failed": self.log.count("failed"),
        }

    def as_dict(self) -> dict:
        out = self.counts()
        out.update(self.totals)
        if self.removed_stale:
            out["removed_stale"] = self.removed_stale
        if self.inputs_changed:
            out["inputs_changed_during_run"] = list(self.inputs_changed)
        if self.output is not None:
            out.setdefault("output", str(self.output))
        out["seconds"] = round(self.seconds, 3)
        out["failures"] = {r.frame_id: r.error for r in self.failed}
        return out

    def with_totals(self, totals: Mapping[str, Any]) -> RunSummary:
        self.totals.update(totals)
        return self
