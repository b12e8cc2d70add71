"""The frame runner: one per-frame job over many frames, with make-like resume.

Every batch command is a :class:`BatchJob` run by :func:`run_job`, so a command body reads
*parse -> discover -> run_job -> report*:

- a job is a frozen record of its settings, validated once (in ``__post_init__``), plus what
  the batch fixes before any frame runs (:meth:`BatchJob.planned`: the rings ``beams``
  keeps, the table ``equalize`` applies);
- :meth:`BatchJob.tasks` turns frames (from :mod:`sparsetools.io.sources`) into
  :class:`FrameTask` records: the frame's key, a typed record of its inputs, the outputs it
  writes by role, the input files whose identity decides resume;
- ``job(task)`` processes one frame, writes its outputs itself (atomically) and returns a
  frozen :class:`FrameStats` record;
- :meth:`BatchJob.finish` merges what the frames wrote (a Parquet table, a manifest) and
  returns the command's totals.

:func:`run_job` checks the output folder, builds the tasks and hands them to
:func:`run_frames`, which

- refuses two tasks with one frame id or one output path, and outputs that would replace
  inputs;
- with a :class:`RunSpec`, applies the resume rule of :mod:`.provenance` (up to date frames
  are skipped, frames whose inputs changed recomputed, other settings refused) and records
  each frame as it completes;
- runs the rest on the :class:`~.batch.Batch`'s executor (serial, local processes, Dask),
  with a progress bar on stderr;
- applies the error policy: ``stop`` raises :class:`FrameError` at the first failed frame,
  ``skip`` records it and goes on (the summary lists failures).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import os
import stat
import time
import traceback
from array import array
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np

from ..errors import FrameError, OutputError, ParameterError, SparsetoolsError
from ..io.atomic import recording_writes, remove_stale_temporaries
from ..io.frame_index import key_hash
from ..io.provenance import OutputIdentity, check_record_dir, output_identity
from .batch import Batch, FrameResult, ResultLog, RunSummary
from .provenance import OutputFolder, option_names, settings_dict

__all__ = [
    "BatchJob",
    "FrameStats",
    "FrameTask",
    "RunSpec",
    "TaskStream",
    "check_output_dir",
    "run_frames",
    "run_job",
]

log = logging.getLogger(__name__)

I = TypeVar("I")


@dataclass(frozen=True)
class FrameTask(Generic[I]):
    """One unit of batch work.

    Attributes
    ----------
    key : FrameKey or str
        The frame (``str(key)`` is the frame id: messages, per-frame seeds, records).
    inputs : a frozen dataclass of the job
        What the job needs for this frame (paths, per-frame values); picklable.
    outputs : mapping of role -> Path
        Files the job writes (``{"depth": ..., "calib": ...}``).
    sources : tuple of Path
        Input files whose identity (path, size, mtime, hash) decides whether the frame is up
        to date.
    """

    key: Any
    inputs: I = None
    outputs: Mapping[str, Path] = field(default_factory=dict)
    sources: tuple[Path, ...] = ()

    @functools.cached_property
    def frame_id(self) -> str:
        return str(self.key)

    @functools.cached_property
    def output_paths(self) -> tuple[Path, ...]:
        return tuple(Path(p) for p in self.outputs.values())


@dataclass(frozen=True)
class RunSpec:
    """What makes a folder's results: recorded, and compared on the next run.

    Attributes
    ----------
    command : str
    out_dir : Path
    settings : frozen dataclass (or mapping)
        Everything that changes the results.
    noun : str
        What the folder holds, for messages (``depth maps``).
    options : mapping, optional
        Setting name -> how messages name it, when ``settings`` is a mapping (a dataclass
        names its fields through their ``option`` metadata).
    shared_outputs : tuple of Path
        Files the run writes besides the frames' outputs (a merged table, a manifest): an
        existing one in a folder without a record is refused like a frame's output.
    """

    command: str
    out_dir: Path
    settings: Any = None
    noun: str = "results"
    options: Mapping[str, str] | None = None
    shared_outputs: tuple[Path, ...] = ()


@dataclass(frozen=True)
class FrameStats:
    """What one frame's job measured: a frozen record, one subclass per command.

    Its fields are what the folder's record keeps for the frame (``frames.jsonl``); a field
    holding None is left out of the record. Names starting with ``t_`` are timings of one
    run and are never recorded.
    """

    def to_record(self) -> dict:
        """The statistics as the folder's record stores them (JSON values, None left out)."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            out[f.name] = dict(value) if isinstance(value, Mapping) else value
        return out

    @classmethod
    def from_record(cls, record: Mapping):
        """The statistics of a frame from its record (fields the record lacks take their
        defaults; fields without a default and missing from it make the record unusable)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in record.items() if k in names})


S = TypeVar("S", bound=FrameStats)


class BatchJob(Generic[I]):
    """The shape of every batch command's job (subclass it as a frozen dataclass).

    A job holds its settings (validated once, in ``__post_init__``) and whatever the batch
    fixes before frames run; it is pickled to worker processes, so it holds plain data.

    Class attributes
    ----------------
    command : str
        The command (recorded in the folder, compared on the next run).
    noun : str
        What the folder holds, for messages (``depth maps``).
    stats_type : type of FrameStats
        The per-frame statistics record ``__call__`` returns.

    Subclasses define :meth:`tasks` and :meth:`__call__`; the other methods have defaults.
    """

    command: ClassVar[str] = ""
    noun: ClassVar[str] = "results"
    stats_type: ClassVar[type[FrameStats]] = FrameStats
    #: True when :meth:`tasks` makes each frame's task from that frame alone (the tasks of a
    #: slice of the frames are that slice of the tasks): the runner then makes them a chunk at
    #: a time instead of holding them all (:class:`TaskStream`).
    tasks_per_frame: ClassVar[bool] = False
    #: Fields only the parent process uses (in :meth:`before` and :meth:`finish`): they are
    #: not sent to worker processes with every task.
    parent_only: ClassVar[tuple[str, ...]] = ()

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        for name in self.parent_only:
            state[name] = None
        return state

    # -- what the batch fixes before anything is written --------------------------------------
    def planned(self, frames: list) -> BatchJob[I]:
        """This job with what depends on the whole batch fixed (default: itself).

        Raises for a problem every frame would have, before anything is written."""
        return self

    def tasks(self, frames: list, out_dir: Path) -> list[FrameTask[I]]:
        """One task per frame (or per group of frames), with outputs under ``out_dir``."""
        raise NotImplementedError

    # -- what the folder's record holds ---------------------------------------------------------
    def record(self) -> Mapping:
        """The settings recorded in the folder and compared on the next run."""
        return settings_dict(getattr(self, "settings", None))

    def option_names(self) -> Mapping[str, str]:
        """Recorded setting -> how messages name it (default: the ``option`` metadata of the
        settings record's fields, else ``--name``)."""
        return option_names(getattr(self, "settings", None))

    def shared_outputs(self, out_dir: Path) -> tuple[Path, ...]:
        """Files the run writes besides the frames' own (a merged table, a manifest)."""
        return ()

    def is_complete(self, out_dir: Path) -> Callable[[FrameTask], bool] | None:
        """Whether a task's outputs are complete (None: every output file exists)."""
        return None

    # -- running ----------------------------------------------------------------------------------
    def prepare(self) -> None:
        """Load what every frame uses, once, before a pool forks (optional)."""

    def before(self, out_dir: Path, batch: Batch) -> Mapping | None:
        """Once the folder is checked and before any frame runs: write the shared files the
        frames read, or run a first stage of the command (optional). Returns totals of that
        stage (added after :meth:`finish`'s)."""

    def __call__(self, task: FrameTask[I]) -> FrameStats:
        raise NotImplementedError

    def finish(self, summary: RunSummary, tasks: list[FrameTask[I]], out_dir: Path) -> Mapping:
        """After the frames: merge what they wrote; return the command's totals."""
        return {}

    # -- reading the results ----------------------------------------------------------------------
    def stats(self, summary: RunSummary) -> list:
        """The typed statistics of every frame done now or up to date, in task order."""
        return [self.stats_type.from_record(r.stats) for r in summary.iter_ok()]

    def iter_stats(self, summary: RunSummary) -> Iterator[tuple[FrameResult, FrameStats]]:
        """(result, typed statistics) of every frame done now or up to date, in task order,
        read one at a time (what a :meth:`finish` over a million frames uses)."""
        for r in summary.iter_ok():
            yield r, self.stats_type.from_record(r.stats)


class _Guarded:
    """Picklable wrapper turning exceptions into FrameResult (so one bad frame can't kill a pool)."""

    def __init__(self, fn: Callable[[FrameTask], dict], debug: bool):
        self.fn = fn
        self.debug = debug

    def prepare(self) -> None:
        """The job's ``prepare()`` (optional: loads what every frame needs, before a pool
        forks; see :func:`~.executors.LocalExecutor`)."""
        prepare = getattr(self.fn, "prepare", None)
        if callable(prepare):
            prepare()

    def __call__(self, task: FrameTask) -> FrameResult:
        written: dict = {}
        try:
            with recording_writes() as written:
                stats = self.fn(task) or {}
            if isinstance(stats, FrameStats):
                stats = stats.to_record()
            # what was written, taken where it was written (in parallel, before the parent
            # records it): a later truncation or edit of an output is then noticed
            ids = {role: _identity(p, written) for role, p in task.outputs.items()}
            return FrameResult(task.frame_id, True, stats,
                               output_ids={r: i for r, i in ids.items() if i is not None})  # fmt: skip
        except SparsetoolsError as exc:
            error, detail = " ".join(str(exc).split()), self._traceback()
        except MemoryError:
            error, detail = "out of memory", ""
        except Exception as exc:  # an unexpected bug: keep the traceback for --debug
            msg = " ".join(f"{type(exc).__name__}: {exc}".split())
            error, detail = f"internal error: {msg}", self._traceback()
        # what the failed attempt wrote before it failed (the parent removes it)
        ids = {role: _identity(p, written) for role, p in task.outputs.items()
               if os.fspath(p) in written}  # fmt: skip
        return FrameResult(task.frame_id, False, error=error, detail=detail,
                           output_ids={r: i for r, i in ids.items() if i is not None})  # fmt: skip

    def _traceback(self) -> str:
        return traceback.format_exc() if self.debug else ""


def _identity(path: Path, written: Mapping[str, tuple[int, str]]) -> OutputIdentity | None:
    """An output's identity: from the bytes :func:`atomic_write_bytes` wrote when it wrote
    the file (and the file is still a regular file of that size), else read back."""
    noted = written.get(os.fspath(path))
    if noted is not None:
        try:
            st = os.lstat(path)
        except OSError:
            return None
        if stat.S_ISREG(st.st_mode) and st.st_size == noted[0]:
            return OutputIdentity(int(st.st_size), int(st.st_mtime_ns), noted[1])
    return output_identity(path)


#: Tasks planned (their records read, their inputs' identities taken) at a time.
PLAN_CHUNK = 1024


class TaskStream:
    """A job's tasks made a chunk of frames at a time, each time they are iterated.

    The runner goes over the tasks twice (checks before anything is written, then the run);
    for a job whose tasks are made frame by frame (``BatchJob.tasks_per_frame``) it never
    holds more than ``chunk`` of them.
    """

    def __init__(self, job: BatchJob, frames: list, out_dir: Path, *, chunk: int = PLAN_CHUNK):
        self.job, self.frames, self.out_dir, self.chunk = job, frames, out_dir, chunk

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self):
        for i in range(0, len(self.frames), self.chunk):
            yield from self.job.tasks(self.frames[i : i + self.chunk], self.out_dir)


class _TaskChecks:
    """The checks over every task of a run, 8 bytes per frame id, output and input: two
    tasks with one frame id, two tasks writing one file, an output replacing an input.
    Hashes find the candidates; the messages come from a second, exact pass over those."""

    def __init__(self) -> None:
        self.ids, self.outs, self.owner, self.srcs = array("q"), array("q"), array("q"), array("q")
        self.folders: set[str] = set()
        self.n = 0

    def add(self, task: FrameTask) -> None:
        self.ids.append(key_hash(task.frame_id))
        for p in task.outputs.values():
            full = os.path.abspath(p)
            self.outs.append(hash(full))
            self.owner.append(self.n)
            self.folders.add(os.path.dirname(full))
        for src in task.sources:
            self.srcs.append(hash(os.path.abspath(src)))
        self.n += 1

    def id_hashes(self) -> np.ndarray:
        return np.frombuffer(self.ids, dtype=np.int64)

    def verify(self, tasks: Iterable[FrameTask]) -> None:
        ids = np.sort(self.id_hashes())
        same_id = set(ids[1:][ids[1:] == ids[:-1]].tolist())
        outs = np.frombuffer(self.outs, dtype=np.int64)
        owner = np.frombuffer(self.owner, dtype=np.int64)
        order = np.lexsort((owner, outs))
        h, o = outs[order], owner[order]
        clash = (h[1:] == h[:-1]) & (o[1:] != o[:-1])
        same_out = set(h[1:][clash].tolist())
        replaces = set(outs[np.isin(outs, np.frombuffer(self.srcs, dtype=np.int64))].tolist())
        if same_id or same_out or replaces:
            _check_exactly(tasks, same_id, same_out, replaces)


def _check_exactly(tasks, same_id: set, same_out: set, replaces: set) -> None:
    """The refusals of :class:`_TaskChecks`, in task order, for the candidate hashes only."""
    ids: dict[str, FrameTask] = {}
    for t in tasks:
        if key_hash(t.frame_id) in same_id:
            if t.frame_id in ids:
                raise ParameterError(f"two inputs map to the same frame id: {t.frame_id}")
            ids[t.frame_id] = t
    sources = set()
    if replaces:
        for t in tasks:
            sources.update(k for s in t.sources if hash(k := os.path.abspath(s)) in replaces)
    owner: dict[str, FrameTask] = {}
    for t in tasks:
        for p in t.outputs.values():
            key = os.path.abspath(p)
            h = hash(key)
            if h in same_out:
                if key in owner and owner[key].frame_id != t.frame_id:
                    other = owner[key]
                    raise ParameterError(
                        f"frames {other.frame_id} ({_first_source(other)}) and {t.frame_id} "
                        f"({_first_source(t)}) would both write {p}"
                    )
                owner[key] = t
            if h in replaces and key in sources:
                raise OutputError(f"output {p} would replace an input file: choose another -o")


def _check_tasks(tasks: Iterable[FrameTask]) -> None:
    """Refuse two tasks with one frame id or one output, and an output replacing an input."""
    checks = _TaskChecks()
    for t in tasks:
        checks.add(t)
    checks.verify(tasks)


def _first_source(task: FrameTask) -> str:
    return str(task.sources[0]) if task.sources else task.frame_id


def run_frames(
    fn: Callable[[FrameTask], dict],
    tasks: Iterable[FrameTask],
    *,
    batch: Batch | None = None,
    spec: RunSpec | None = None,
    complete: Callable[[FrameTask], bool] | None = None,
    desc: str | None = None,
    on_done: Callable[[FrameTask, FrameResult], None] | None = None,
    before: Callable[[], None] | None = None,
) -> RunSummary:
    """Run ``fn`` over ``tasks`` with resume, progress and an error policy.

    Memory is O(1) per frame beyond the tasks themselves: the tasks are gone over twice (the
    checks, then the run, ``PLAN_CHUNK`` at a time), results go to the summary's
    :class:`~.batch.ResultLog` and the folder's journal as they come, and only the frames in
    flight are held (issue 28).

    Parameters
    ----------
    fn : callable(FrameTask) -> dict
        Module-level or picklable job; writes its outputs atomically, returns statistics.
    tasks : list or re-iterable of FrameTask (:class:`TaskStream`)
        Iterated twice: once to check them all, once to run them.
    batch : Batch, optional
        Executor, overwrite, error policy, progress, debug. Default: ``Batch()``.
    spec : RunSpec, optional
        Command, output folder and settings: enables the provenance-checked resume of
        :mod:`.provenance`. Without it, a task whose outputs all exist is skipped (unless
        ``batch.overwrite``).
    complete : callable(FrameTask) -> bool, optional
        Whether a task's outputs are complete (default: every output file exists).
    desc : str, optional
        Progress bar label (default: the command).
    on_done : callable(FrameTask, FrameResult), optional
        Called in this process for every finished task (after its record is written).
    before : callable(), optional
        Called once the folder is checked and before any frame runs (write shared files
        the jobs read, such as a backscatter estimate), also when every frame is up to date.

    Returns
    -------
    RunSummary
        With ``on_error="skip"`` the caller decides the exit status from ``summary.failed``.
    """
    batch = batch or Batch()
    if not isinstance(tasks, (list, tuple, TaskStream)):
        tasks = list(tasks)
    t0 = time.perf_counter()
    summary = RunSummary(
        command=spec.command if spec else "",
        output=spec.out_dir if spec else None,
        overwrite=batch.overwrite,
    )
    checks = _TaskChecks()
    if spec is None:
        for t in tasks:
            checks.add(t)
        checks.verify(tasks)
        summary.log = ResultLog(checks.n)
        for folder in checks.folders:
            remove_stale_temporaries(folder, recursive=False)
        if before is not None:
            before()
        done = complete or (lambda t: bool(t.outputs) and all(os.path.isfile(p)
                                                              for p in t.outputs.values()))  # fmt: skip

        def plan(chunk):
            if batch.overwrite:
                return chunk, {}, set()
            todo, fresh = [], {}
            for t in chunk:
                if done(t):
                    fresh[t.frame_id] = {}
                else:
                    todo.append(t)
            return todo, fresh, set()

        _execute(fn, tasks, plan, checks.n, batch, summary, None, desc or "frames", on_done)
    else:
        with OutputFolder(
            spec.out_dir,
            spec.command,
            spec.settings,
            noun=spec.noun,
            overwrite=batch.overwrite,
            options=spec.options,
        ) as folder:
            for t in tasks:
                checks.add(t)
                folder.check_task(t)
            checks.verify(tasks)
            folder.begin(shared=spec.shared_outputs, this_run=checks.id_hashes())
            # under the lock and in checked folders: a run's temporaries are its own
            for d in checks.folders:
                remove_stale_temporaries(d, recursive=False)
            summary.log = ResultLog(checks.n, folder=check_record_dir(spec.out_dir))
            if before is not None:
                before()

            def plan(chunk):
                p = folder.plan(chunk, complete)
                return p.todo, p.stats, p.recomputed

            try:
                _execute(fn, tasks, plan, checks.n, batch, summary, folder,
                         desc or spec.command, on_done)  # fmt: skip
            finally:
                summary.removed_stale = folder.removed_stale
                summary.inputs_changed = sorted(folder.inputs_changed)
    counts = summary.counts()
    if counts["skipped_existing"]:
        log.info("%d of %d frame(s) up to date, skipped", counts["skipped_existing"], checks.n)
    if counts["recomputed"]:
        log.info("%d frame(s) with changed inputs recomputed", counts["recomputed"])
    summary.seconds = time.perf_counter() - t0
    return summary


def _execute(fn, tasks, plan, n, batch, summary, folder, desc, on_done) -> None:
    """Plan ``tasks`` a chunk at a time (``plan(chunk) -> (todo, up to date's statistics,
    recomputed ids)``) and run what is to do on one executor, lazily."""
    inflight: dict[str, tuple[int, FrameTask, bool]] = {}
    log_ = summary.log

    def todo_stream():
        it = iter(enumerate(tasks))
        while chunk := list(itertools.islice(it, PLAN_CHUNK)):
            todo, fresh, recomputed = plan([t for _, t in chunk])
            todo_ids = {t.frame_id for t in todo}
            for pos, t in chunk:
                if t.frame_id in todo_ids:
                    inflight[t.frame_id] = (pos, t, t.frame_id in recomputed)
                    yield t
                elif t.frame_id in fresh:
                    log_.add(pos, FrameResult(t.frame_id, True, stats=fresh[t.frame_id],
                                              skipped=True))  # fmt: skip

    stream = todo_stream()
    first = next(stream, None)
    if first is None:
        return
    executor = batch.make_executor(n)
    bar = None
    if batch.show_progress:
        import sys

        from tqdm import tqdm

        bar = tqdm(total=n, desc=desc, unit="frame", file=sys.stderr, leave=False)
    try:
        for res in executor.map(_Guarded(fn, batch.debug), itertools.chain([first], stream)):
            pos, task, recomputed = inflight.pop(res.frame_id)
            res.recomputed = recomputed
            if folder is not None:
                if res.ok:
                    folder.record_done(task, res.stats, res.output_ids)
                else:
                    folder.record_failed(task, res.output_ids)
            res.output_ids = {}
            log_.add(pos, res)
            if on_done is not None:
                on_done(task, res)
            if bar is not None:
                bar.update(1)
            if not res.ok:
                if batch.on_error == "stop":
                    msg = f"frame {res.frame_id}: {res.error}"
                    raise FrameError(msg + (f"\n{res.detail}" if res.detail else ""))
                log.warning("frame %s failed: %s", res.frame_id, res.error)
    finally:
        if bar is not None:
            bar.close()


def run_job(
    job: BatchJob,
    frames: Iterable,
    out_dir: str | os.PathLike,
    *,
    batch: Batch | None = None,
    inputs: Iterable[str | os.PathLike | None] = (),
    desc: str | None = None,
) -> RunSummary:
    """Run a batch command: the one entry point of every batch job.

    Parameters
    ----------
    job : BatchJob
        Its settings already validated.
    frames : iterable of Frame (or of what the job's :meth:`~BatchJob.tasks` takes)
        From :mod:`sparsetools.io.sources`.
    out_dir : path-like
        Output folder (created). Refused when it is a file, not writable, inside one of
        ``inputs`` (folders), or when an output would replace an input file.
    batch : Batch, optional
        How the batch runs (workers, executor, ``--overwrite``, error policy, progress).
    inputs : iterable of path-like
        The paths the user gave (the output folder may not be inside one of them).
    desc : str, optional
        Progress bar label (default: the command).

    Returns
    -------
    RunSummary
        Per-frame results and the job's totals (:meth:`BatchJob.finish`).
    """
    batch = batch or Batch()
    if not isinstance(frames, Sequence):  # a FrameList stays compact
        frames = list(frames)
    job = job.planned(frames)
    out = check_output_dir(out_dir, [p for p in inputs if p is not None])
    tasks = TaskStream(job, frames, out) if job.tasks_per_frame else job.tasks(frames, out)
    spec = RunSpec(
        job.command,
        out,
        job.record(),
        noun=job.noun,
        options=job.option_names(),
        shared_outputs=tuple(job.shared_outputs(out)),
    )
    stage: dict = {}

    def before() -> None:
        stage.update(job.before(out, batch) or {})

    summary = run_frames(
        job,
        tasks,
        batch=batch,
        spec=spec,
        complete=job.is_complete(out),
        desc=desc or job.command,
        before=before,
    )
    return summary.with_totals({**job.finish(summary, tasks, out), **stage})


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
        if inp is None:
            continue
        ip = Path(inp).resolve()
        if ip.is_dir() and (out == ip or ip in out.parents):
            raise OutputError(f"output folder {out_dir} is inside the input folder {inp}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError as exc:
        raise OutputError(f"cannot create output folder {out_dir}: a file is in the way") from exc
    except OSError as exc:
        raise OutputError(f"cannot create output folder {out_dir}: {exc.strerror or exc}") from exc
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"output folder {out_dir} is not writable")
    return Path(out_dir)
