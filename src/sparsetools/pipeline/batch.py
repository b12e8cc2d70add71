"""How a batch runs (:class:`Batch`) and what it did (:class:`RunSummary`): the same two
types for every command.

``Batch`` holds the options every batch command shares (``--workers``, ``--executor``,
``--dask-scheduler``, ``--overwrite``, ``--on-error``, progress, ``--debug``);
the command line builds one from :func:`sparsetools.cli.options.batch_options` and every
``run_*`` function takes it. ``RunSummary`` is what every ``run_*`` returns: per-frame
results in task order plus the command's own totals.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..validate import check_choice, check_int_range

__all__ = ["EXECUTORS", "ON_ERROR", "Batch", "FrameResult", "RunSummary"]

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
        """The executor for ``n_tasks`` tasks, its workers capped (see :func:`usable_workers`)."""
        from .executors import make_executor, usable_workers

        workers = usable_workers(self.workers, n_tasks, cap_cpus=self.scheduler is None)
        return make_executor(self.executor, workers=workers, scheduler=self.scheduler)


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


@dataclass
class RunSummary:
    """What a batch did: per-frame results in task order, and the command's totals.

    ``as_dict()`` is what the command line prints: ``frames``, ``processed``,
    ``skipped_existing`` (up to date), ``recomputed`` (inputs changed), ``failed``, then the
    command's ``totals``, ``output``, ``seconds`` and ``failures``.
    """

    command: str = ""
    output: Path | None = None
    results: list[FrameResult] = field(default_factory=list)
    seconds: float = 0.0
    totals: dict[str, Any] = field(default_factory=dict)
    removed_stale: int = 0
    #: the run replaced the folder's results (``--overwrite``)
    overwrite: bool = False
    #: frames done whose inputs changed while they ran: not recorded (recomputed next time)
    inputs_changed: list[str] = field(default_factory=list)

    @property
    def done(self) -> list[FrameResult]:
        return [r for r in self.results if r.ok and not r.skipped]

    @property
    def resumed(self) -> list[FrameResult]:
        return [r for r in self.results if r.skipped]

    @property
    def failed(self) -> list[FrameResult]:
        return [r for r in self.results if not r.ok]

    @property
    def recomputed(self) -> list[FrameResult]:
        return [r for r in self.results if r.recomputed]

    @property
    def ok(self) -> list[FrameResult]:
        """Frames done in this run or up to date (with the statistics of their record)."""
        return [r for r in self.results if r.ok]

    def total(self, key: str) -> float:
        """Sum of a numeric per-frame statistic over the frames of the run, those done now
        and those up to date (their statistics come from the folder's record)."""
        return sum(r.stats.get(key, 0) for r in self.ok)

    def counts(self) -> dict:
        return {
            "frames": len(self.results),
            "processed": len(self.done),
            "skipped_existing": len(self.resumed),
            "recomputed": len(self.recomputed),
            "failed": len(self.failed),
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
