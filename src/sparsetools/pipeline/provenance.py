"""Make-like resume: an output is up to date when the same command, with the same settings
and sparsetools version, made it from inputs that have not changed.

On every run into a folder (:class:`OutputFolder`):

- the folder's record (:mod:`sparsetools.io.provenance`) is read; a folder made by another
  command, version or settings is refused with a one-line error naming the first setting
  that differs (``out holds depth maps made with --max-depth 80, not 20: use --overwrite or
  another -o``);
- each frame is then up to date (skipped), new, or recomputed because one of its inputs
  changed (size, mtime, or the hash of a small file) or one of its outputs is missing;
- outputs that exist but are in no record (a foreign file, an older sparsetools) are refused
  unless ``--overwrite``;
- ``--overwrite`` recomputes every frame and removes the outputs the folder's record lists
  for frames this run does not make (so the folder holds one run's settings); files the
  record does not list are never touched.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import FormatError, OutputError
from ..io.containment import ContainedPaths, contained_record_path, remove_output
from ..io.frame_index import FrameIndex, compact_journal
from ..io.provenance import (
    RECORD_DIR,
    FileIdentity,
    FrameJournal,
    FrameRecord,
    RunRecord,
    check_record_dir,
    file_identity,
    hold_lock,
    output_identity,
    output_unchanged,
    read_frame_records,
    read_run_record,
    remove_empty_record_dir,
    remove_unchanged_outputs,
    unchanged_since,
    write_frame_records,
    write_run_record,
)

__all__ = [
    "COMPATIBLE_VERSIONS",
    "OutputFolder",
    "Plan",
    "check_made_by",
    "clear_recorded",
    "settings_dict",
    "settings_difference",
]

log = logging.getLogger(__name__)


def _normalise(value):
    return json.loads(json.dumps(value, default=_json_default, sort_keys=True))


def _json_default(o):
    if dataclasses.is_dataclass(o):
        return settings_dict(o)
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, (set, frozenset)):
        return sorted(o)
    raise TypeError(f"setting of type {type(o).__name__} is not JSON serialisable")


def settings_dict(settings) -> dict:
    """JSON-normalised settings of a dataclass (or mapping), comparable with a record's copy.

    A dataclass field with ``metadata={"provenance": False}`` is left out (it does not change
    what is computed); one with ``metadata={"omit_default": True}`` (an option added after
    0.2.0) is left out while it holds its default, so older folders made without it resume.
    """
    if settings is None:
        return {}
    if dataclasses.is_dataclass(settings):
        items = {
            f.name: getattr(settings, f.name)
            for f in dataclasses.fields(settings)
            if f.metadata.get("provenance", True)
            and not (f.metadata.get("omit_default") and getattr(settings, f.name) == f.default)
        }
    else:
        items = dict(settings)
    return _normalise(items)


def option_names(settings) -> dict[str, str]:
    """Setting name -> command-line option (field metadata ``option``, else ``--name``)."""
    names = {}
    if dataclasses.is_dataclass(settings):
        for f in dataclasses.fields(settings):
            opt = f.metadata.get("option")
            if opt:
                names[f.name] = opt
    return names


def _show(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return f"{value:g}" if math.isfinite(value) else str(value)
    if isinstance(value, list):
        return ",".join(_show(v) for v in value) or "(empty)"
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True)
    return str(value)


def settings_difference(
    old: Mapping, new: Mapping, names: Mapping[str, str] | None = None, *, _path: str = ""
) -> tuple[str, str, str] | None:
    """(option, old value, new value) of the first setting that differs, or None; a value
    is None where that side does not record the setting at all.

    ``names`` maps a setting to the option that sets it; a setting inside a mapping setting
    is named by its dotted path (``params.sweeps``: the option of a route that records its
    options in ``params``), else by the mapping's option and its key (``--params sweeps``).
    """
    names = names or {}
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if a == b:
            continue
        path = f"{_path}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            inner = settings_difference(a, b, names, _path=f"{path}.")
            if inner is not None:
                return inner
        # A setting one side does not record (an option left at its default that is recorded
        # only when given) is shown as None: "made without --gt-method".
        return (_option_name(path, names), None if key not in old else _show(a),
                None if key not in new else _show(b))  # fmt: skip
    return None


def _option_name(path: str, names: Mapping[str, str]) -> str:
    if path in names:
        return names[path]
    parent, _, key = path.rpartition(".")
    if parent:
        return f"{_option_name(parent, names)} {key.replace('_', '-')}"
    return "--" + key.replace("_", "-")


#: Versions whose outputs this version writes byte for byte from the same settings (checked by
#: tests/test_compat_v020.py): their folders resume; a record of any other version is refused.
COMPATIBLE_VERSIONS = frozenset({__version__, "0.2.0"})


def check_made_by(
    record: RunRecord,
    *,
    command: str,
    settings: Mapping,
    names: Mapping[str, str],
    noun: str,
    place,
    remedy: str = "use --overwrite or another -o",
) -> None:
    """Refuse outputs that another command, other settings or an incompatible sparsetools
    version made: the one refusal of every kind of output (a folder, a tree, a file).

    Raises
    ------
    OutputError
        Naming what differs: the command, the first setting (as its option), the version.
    """
    if record.command != command:
        raise OutputError(
            f"{place} holds the output of `sparsetools {record.command}`, not `{command}`: "
            "use another -o (or --overwrite to replace it)"
        )
    diff = settings_difference(record.settings, settings, names)
    if diff is not None:
        opt, a, b = diff
        if a is None:
            made = f"made without {opt}, not with {opt} {b}"
        elif b is None:
            made = f"made with {opt} {a}, not without it"
        else:
            made = f"made with {opt} {a}, not {b}"
        raise OutputError(f"{place} holds {noun} {made}: {remedy}")
    if record.version not in COMPATIBLE_VERSIONS:
        raise OutputError(
            f"{place} holds {noun} made by sparsetools {record.version}, this is "
            f"{__version__}: {remedy}"
        )


def clear_recorded(folder: str | os.PathLike) -> int:
    """Remove what a folder's record says a run wrote there (regular files inside the folder
    only), its record, and the folders left empty; return how many files were removed.

    For a command's sub-output a rerun no longer makes (``accumulate``'s ``icp/`` after
    ``--overwrite`` with poses from files): files the record does not list are never
    touched.
    """
    folder = Path(folder)
    try:
        check_record_dir(folder)
    except OutputError:
        return 0
    if read_run_record(folder) is None:
        return 0
    n = 0
    with hold_lock(folder):
        for rec in read_frame_records(folder).values():
            for rel in rec.outputs.values():
                p = contained_record_path(folder, rel)
                if p is not None and remove_output(folder, p):
                    n += 1
                    _remove_empty_parents(p.parent, folder)
        write_frame_records(folder, {})
    remove_empty_record_dir(folder, run_record=True)
    with contextlib.suppress(OSError):
        folder.rmdir()
    return n


def _remove_empty_parents(d: Path, root: Path) -> None:
    root = Path(os.path.abspath(root))
    d = Path(os.path.abspath(d))
    while d != root and root in d.parents:
        try:
            d.rmdir()
        except OSError:
            return
        d = d.parent


@dataclasses.dataclass
class Plan:
    """Tasks of a run by state: to compute (new or recomputed) and up to date."""

    todo: list
    up_to_date: list
    recomputed: set[str]
    stats: dict[str, dict] = dataclasses.field(default_factory=dict)


class OutputFolder:
    """The resume rule of one output folder (use as a context manager: it holds the lock).

    Memory is O(1) per frame (issue 28): the folder's journal is read through a
    :class:`~sparsetools.io.frame_index.FrameIndex` (16 bytes per frame), records are appended
    as frames complete and never held, and the journal is compacted at the end by
    :func:`~sparsetools.io.frame_index.compact_journal` one line at a time. A run uses it in
    three steps: :meth:`check_task` for every task (before anything is written), :meth:`begin`
    once, then :meth:`plan` for each chunk of tasks as it runs them.

    Parameters
    ----------
    out : path-like
    command : str
        ``project``, ``beams``, ... (recorded, and compared on the next run).
    settings : dataclass or mapping
        What changes the results (compared on the next run).
    noun : str
        What the folder holds, for messages (``depth maps``).
    overwrite : bool
    """

    #: Input identities kept for reuse (a calibration every frame shares is read once per
    #: this many distinct inputs).
    IDENTITY_CACHE = 4096

    def __init__(
        self,
        out,
        command: str,
        settings,
        *,
        noun: str = "results",
        overwrite: bool = False,
        options: Mapping[str, str] | None = None,
    ):
        self.out = Path(out)
        self.command = command
        self.settings = settings_dict(settings)
        self.names = {**option_names(settings), **(options or {})}
        self.noun = noun
        self.overwrite = overwrite
        self.index: FrameIndex | None = None
        self.dropped: set[str] = set()
        self.recorded = 0
        self._identity_cache: dict[str, FileIdentity] = {}
        self._folders: dict[str, str] = {}  # resolved input folders, for file_identity
        self._out_prefix = os.path.join(os.path.abspath(self.out), "")
        self._contained = ContainedPaths(self.out)
        self._absent_dirs: set[str] = set()  # output folders missing when the tasks were checked
        self._lock = None
        self._journal = None
        self.removed_stale = 0
        self.removed_failed = [0, 0]  # outputs and frames, of failed frames' earlier runs
        self._started = False
        self._had_record = False
        self._run_written = False
        self._shared: list[Path] = []
        self._foreign: list = []
        self._foreign_count = 0
        self._wrote_unrecorded = False
        #: tasks planned and not recorded yet -> their inputs' identities before they ran
        self._pending: dict[str, tuple] = {}
        self.inputs_changed: set[str] = set()

    # -- opening: lock and settings check --------------------------------------------------
    def __enter__(self) -> OutputFolder:
        self._fresh_lock = not (self.out / RECORD_DIR / "lock").exists()
        self._lock = hold_lock(self.out)
        self._lock.__enter__()
        try:
            self._check_record()
        except BaseException:
            self._lock.__exit__(None, None, None)
            if self._fresh_lock:
                remove_empty_record_dir(self.out)  # a refused run leaves no lock file behind
            raise
        return self

    def _check_record(self) -> None:
        old = read_run_record(self.out)
        if old is not None and not self.overwrite:
            check_made_by(old, command=self.command, settings=self.settings, names=self.names,
                          noun=self.noun, place=self.out)  # fmt: skip
        self._had_record = old is not None
        try:
            self.index = FrameIndex(self.out, present=old is not None)
        except OSError as exc:
            raise FormatError(
                f"{self.out / RECORD_DIR}: cannot read the frame record ({exc.strerror or exc}); "
                "use --overwrite"
            ) from exc

    def __exit__(self, *exc) -> None:
        if self.removed_failed[0]:
            log.warning("removed %d output(s) that an earlier run made of %d frame(s) failing now",
                        *self.removed_failed)  # fmt: skip
        try:
            if self._journal is not None:
                self._journal.__exit__(*exc)
                self._journal = None
            if self._started and (self.overwrite or self.recorded or self.dropped):
                compact_journal(self.out, self.index, keep_old=not self.overwrite,
                                dropped=self.dropped)  # fmt: skip
        finally:
            if self.index is not None:
                self.index.close()
            self._lock.__exit__(*exc)
            wrote = (
                self.recorded
                or self._wrote_unrecorded
                or any(os.path.lexists(p) for t, _ in self._pending.values()
                       for p in t.outputs.values())
                or any(p.exists() for p in self._shared)
            )  # fmt: skip
            if not self._had_record and not wrote:
                remove_empty_record_dir(self.out, run_record=True)
            elif not self._started and self._fresh_lock:
                remove_empty_record_dir(self.out)

    # -- planning --------------------------------------------------------------------------
    def identity(self, path: str | os.PathLike) -> FileIdentity:
        key = os.fspath(path)
        ident = self._identity_cache.get(key)
        if ident is None:
            ident = file_identity(path, folders=self._folders)
            if len(self._identity_cache) >= self.IDENTITY_CACHE:
                self._identity_cache.clear()
            self._identity_cache[key] = ident
        return ident

    def _rel(self, path: Path) -> str:
        """``path`` relative to the folder (POSIX separators), or absolute when outside it."""
        full = os.path.abspath(path)
        if full.startswith(self._out_prefix):
            return full[len(self._out_prefix) :].replace(os.sep, "/")
        return "." if full == self._out_prefix[:-1] else full

    def check_task(self, task) -> None:
        """Before anything is written: every output of ``task`` is contained in the folder (no
        link on the way, :mod:`sparsetools.io.containment`); in a folder without a record,
        an existing output is noted as foreign (refused by :meth:`begin`)."""
        existing = None
        for p in task.outputs.values():
            full = os.path.abspath(p)
            parent = os.path.dirname(full)
            if parent in self._absent_dirs and full.startswith(self._out_prefix):
                continue  # below a folder that does not exist yet: nothing there or in the way
            self._contained.check(full)
            if not os.path.lexists(parent):
                self._absent_dirs.add(parent)
            elif existing is None and os.path.exists(full):
                existing = p
        if not self._had_record and not self.overwrite:
            if existing is not None:
                self._foreign_count += 1
                if len(self._foreign) < 1:
                    self._foreign.append(existing)

    def begin(self, *, shared: Iterable = (), this_run: np.ndarray | None = None) -> None:
        """Once every task is checked: refuse foreign outputs, remove (``--overwrite``) the
        recorded outputs of frames this run does not make, write the run's record.

        Parameters
        ----------
        shared : iterable of path-like
            Files the run writes besides the frames' own.
        this_run : (N,) int64
            :func:`~sparsetools.io.frame_index.key_hash` of every frame id of the run.
        """
        self._shared = [Path(p) for p in shared]
        for p in self._shared:
            self._contained.check(p)
        foreign = list(self._foreign)
        count = self._foreign_count
        if not self._had_record and not self.overwrite:
            found = [p for p in self._shared if p.exists()]
            foreign = found + foreign
            count += len(found)
        if foreign:
            more = f" (and {count - 1} more)" if count > 1 else ""
            raise OutputError(
                f"{foreign[0]} exists{more} but {self.out} has no record of what made it "
                "(another tool or an older sparsetools): use --overwrite or another -o"
            )
        if self.overwrite:
            ids = np.empty(0, np.int64) if this_run is None else this_run
            self._remove_stale(ids)
        # Nothing refused: the folder is this run's. Its record is written before any output,
        # so an interrupted run resumes; a run that wrote nothing removes it again.
        self._started = True
        self._write_run()

    def plan(self, tasks: Iterable, complete=None) -> Plan:
        """Split a chunk of ``tasks`` (each checked by :meth:`check_task`, after
        :meth:`begin`) into what to compute and what is up to date.

        A frame is up to date when its record names the same outputs, its inputs are
        unchanged and its outputs are complete (``complete(task) -> bool``, default: every
        output file exists) and, where they exist, the very files recorded (same size and
        mtime, or digest).
        """
        todo, fresh, recomputed = [], [], set()
        stats: dict[str, dict] = {}
        is_complete = complete or (lambda t: all(Path(p).is_file() for p in t.outputs.values()))
        for t in tasks:
            rec = None if self.overwrite else self.index.get(t.frame_id)
            inputs_now = self._take_inputs(t)
            if rec is None:
                todo.append(t)
                continue
            outputs_same = rec.outputs == {r: self._rel(p) for r, p in t.outputs.items()}
            inputs_same = len(inputs_now) == len(rec.inputs) and all(
                a.same_file(b) for a, b in zip(rec.inputs, inputs_now, strict=True)
            )
            if outputs_same and inputs_same and is_complete(t) and self._outputs_intact(t, rec):
                fresh.append(t)
                stats[t.frame_id] = dict(rec.stats)
                self._pending.pop(t.frame_id, None)
                if not rec.output_ids or any(
                    a != b for a, b in zip(rec.inputs, inputs_now, strict=True)
                ):
                    # touched but equal by hash, or a record without output identities (0.2):
                    # refresh it so the next run is cheap and checks the outputs
                    ids = {r: i for r, p in t.outputs.items() if (i := output_identity(p))}
                    self._append(self._record(t, inputs_now, rec.stats, ids))
                continue
            if not inputs_same:
                recomputed.add(t.frame_id)
            todo.append(t)
        return Plan(todo, fresh, recomputed, stats)

    def _take_inputs(self, task) -> tuple[FileIdentity, ...]:
        """The identities of ``task``'s inputs now, before it runs (checked again after)."""
        ids = tuple(self.identity(p) for p in task.sources)
        self._pending[task.frame_id] = (task, ids)
        return ids

    @staticmethod
    def _outputs_intact(task, rec: FrameRecord) -> bool:
        """Every recorded output that exists is the file that was written (a truncated or
        edited one is not: the frame is recomputed)."""
        for role, ident in rec.output_ids.items():
            p = task.outputs.get(role)
            if p is not None and os.path.lexists(p) and not output_unchanged(p, ident):
                return False
        return True

    def _write_run(self) -> None:
        if not self._run_written:
            write_run_record(self.out, RunRecord(self.command, __version__, self.settings))
            self._run_written = True

    def _remove_stale(self, this_run: np.ndarray) -> None:
        """With --overwrite: remove the recorded outputs of frames this run does not make;
        only regular files inside the folder (a record naming anything else is ignored)."""
        n = frames = 0
        for rec in self.index.records_except(this_run):
            frames += 1
            for rel in rec.outputs.values():
                p = contained_record_path(self.out, rel)
                if p is not None and remove_output(self.out, p):
                    n += 1
        if n:
            log.warning(
                "--overwrite: removed %d output(s) of %d frame(s) of the previous run", n, frames
            )
        self.removed_stale = n

    # -- recording -------------------------------------------------------------------------
    def _record(self, task, inputs, stats=None, output_ids=None) -> FrameRecord:
        # Timings (``t_*``) describe one run, not the frame: they are not recorded, so the
        # record of a resumed run equals that of an uninterrupted one.
        kept = {k: v for k, v in (stats or {}).items() if not str(k).startswith("t_")}
        if inputs is None:
            inputs = tuple(self.identity(p) for p in task.sources)
        return FrameRecord(
            task.frame_id,
            {role: self._rel(p) for role, p in task.outputs.items()},
            inputs,
            kept,
            dict(output_ids or {}),
        )

    def _append(self, rec: FrameRecord) -> None:
        self._write_run()
        if self._journal is None:
            self._journal = FrameJournal(self.out).__enter__()
        self._journal.append(rec)
        self.recorded += 1

    def record_done(self, task, stats=None, output_ids=None) -> None:
        """Record a frame whose outputs are all in place (with its statistics and the
        identities of its outputs); a frame whose inputs changed while it ran is not
        recorded (it is recomputed on the next run)."""
        _, before = self._pending.get(task.frame_id, (None, None))
        if before is not None and not all(
            unchanged_since(b, p) for b, p in zip(before, task.sources, strict=True)
        ):
            log.warning(
                "frame %s: an input changed while the frame ran: not recorded, it is "
                "recomputed on the next run", task.frame_id,
            )  # fmt: skip
            self.inputs_changed.add(task.frame_id)
            self._drop(task)  # its outputs are this run's: they stay, unrecorded
            return
        self._pending.pop(task.frame_id, None)
        self._append(self._record(task, before, stats, output_ids))

    def record_failed(self, task, written: Mapping | None = None) -> None:
        """A failed frame keeps no record (it is recomputed on the next run), nor the outputs
        written for it that are still those files: an earlier run's (a fresh run has none)
        and, ``written`` (role -> identity), those its failed attempt wrote before it failed.
        An output changed since it was written is someone's: it stays."""
        rec = self.index.get(task.frame_id) if self.index is not None else None
        n = remove_unchanged_outputs(self.out, task.outputs, rec.output_ids) if rec else 0
        self.removed_failed[0] += n
        self.removed_failed[1] += n > 0
        remove_unchanged_outputs(self.out, task.outputs, written or {})
        self._drop(task)

    def _drop(self, task) -> None:
        """No record for ``task``: it is recomputed on the next run."""
        self._pending.pop(task.frame_id, None)
        self.dropped.add(task.frame_id)
        if not self._wrote_unrecorded:
            self._wrote_unrecorded = any(os.path.lexists(p) for p in task.outputs.values())

    def forget_inputs(self, task) -> None:
        """Drop cached identities of ``task``'s inputs (a job that rewrote one of them)."""
        for p in task.sources:
            self._identity_cache.pop(os.fspath(p), None)
