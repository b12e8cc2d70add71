"""What made an output folder: the on-disk record behind make-like resume.

Every batch command keeps, in its output folder::

    OUT/.sparsetools/run.json       command, sparsetools version and the settings of the run
    OUT/.sparsetools/frames.jsonl   one line per frame: its outputs (by role, relative to OUT)
                                    and the identity of each input (path, size, mtime, hash)
    OUT/.sparsetools/lock           held (flock) while a run writes into OUT

``frames.jsonl`` is appended to as frames complete (a frame's outputs are renamed into place
before its line is written, so a line always describes complete outputs; a line cut short by a
crash is ignored and that frame is simply recomputed) and rewritten atomically, sorted, at the
end of a run. This module only reads and writes that record; the resume rule built on it is
:mod:`sparsetools.pipeline.provenance`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import stat
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import FormatError, OutputError
from .atomic import atomic_path

__all__ = [
    "HASH_LIMIT",
    "RECORD_DIR",
    "FileIdentity",
    "FrameJournal",
    "FrameRecord",
    "RunRecord",
    "file_identity",
    "file_record_path",
    "hold_lock",
    "read_file_record",
    "read_frame_records",
    "read_run_record",
    "recorded_outputs",
    "remove_empty_record_dir",
    "write_file_record",
    "write_frame_records",
    "write_run_record",
]

RECORD_DIR = ".sparsetools"
RUN_FILE = "run.json"
FRAMES_FILE = "frames.jsonl"
LOCK_FILE = "lock"
FORMAT = 1
#: Inputs up to this size (bytes) are also identified by their SHA-256 (calibrations, small
#: tables), so touching or copying them does not force a recomputation.
HASH_LIMIT = 1 << 16


@dataclass(frozen=True)
class FileIdentity:
    """What identifies an input file: path, size, modification time and (small files) hash."""

    path: str
    size: int
    mtime_ns: int
    sha256: str | None = None

    def to_list(self) -> list:
        return [self.path, self.size, self.mtime_ns, self.sha256]

    @classmethod
    def from_list(cls, item) -> FileIdentity:
        path, size, mtime, sha = item
        return cls(str(path), int(size), int(mtime), None if sha is None else str(sha))

    def same_file(self, other: FileIdentity) -> bool:
        """Unchanged: same size and (same mtime, or the same recorded hash)."""
        if self.path != other.path or self.size != other.size:
            return False
        if self.mtime_ns == other.mtime_ns:
            return True
        return self.sha256 is not None and self.sha256 == other.sha256


def file_identity(
    path: str | os.PathLike,
    *,
    hash_limit: int = HASH_LIMIT,
    folders: dict[str, str] | None = None,
) -> FileIdentity:
    """Identity of ``path`` (resolved); a missing file has size -1.

    A folder (a KITTI raw calibration folder) is identified by the identities of the
    calibration files in it, folded into one hash. ``folders`` caches the resolved folders of
    a batch (most inputs share a few): a plain file in a known folder then costs one
    ``lstat``, not one per path component.
    """
    text = os.fspath(path)
    if folders is not None and ".." not in text.replace(os.altsep or os.sep, os.sep).split(os.sep):
        head, name = os.path.split(os.path.abspath(text))
        try:
            st = os.lstat(text)
        except OSError:
            st = None
        if st is not None and stat.S_ISREG(st.st_mode):  # not a link, not a folder
            real = folders.get(head)
            if real is None:
                real = folders[head] = os.path.realpath(head)
            return _regular_identity(os.path.join(real, name), st, hash_limit)
    p = Path(path).resolve()
    try:
        st = p.stat()
    except OSError:
        return FileIdentity(str(p), -1, 0, None)
    if stat.S_ISDIR(st.st_mode):
        h = hashlib.sha256()
        for child in sorted(p.glob("calib_*.txt")):
            ident = file_identity(child, hash_limit=hash_limit)
            h.update(json.dumps(ident.to_list()).encode())
        return FileIdentity(str(p), 0, 0, h.hexdigest())
    return _regular_identity(str(p), st, hash_limit)


def _regular_identity(path: str, st: os.stat_result, hash_limit: int) -> FileIdentity:
    sha = None
    if st.st_size <= hash_limit:
        try:
            with open(path, "rb") as fh:
                sha = hashlib.sha256(fh.read()).hexdigest()
        except OSError:
            sha = None
    return FileIdentity(path, int(st.st_size), int(st.st_mtime_ns), sha)


@dataclass(frozen=True)
class RunRecord:
    """The command, version and settings that made a folder."""

    command: str
    version: str
    settings: Mapping = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "command": self.command,
            "version": self.version,
            "settings": dict(self.settings),
        }


@dataclass(frozen=True)
class FrameRecord:
    """One frame of a folder: its outputs by role (paths relative to the folder) and inputs."""

    key: str
    outputs: Mapping[str, str]
    inputs: tuple[FileIdentity, ...] = ()
    stats: Mapping = field(default_factory=dict)

    def to_line(self) -> str:
        return json.dumps(
            {
                "key": self.key,
                "outputs": dict(self.outputs),
                "inputs": [i.to_list() for i in self.inputs],
                "stats": dict(self.stats),
            },
            sort_keys=True,
            default=_json_number,
        )

    @classmethod
    def from_line(cls, line: str) -> FrameRecord:
        d = json.loads(line)
        return cls(
            str(d["key"]),
            {str(k): str(v) for k, v in d["outputs"].items()},
            tuple(FileIdentity.from_list(i) for i in d.get("inputs", ())),
            d.get("stats") if isinstance(d.get("stats"), dict) else {},
        )


def _json_number(o):
    if hasattr(o, "item"):  # numpy scalars in per-frame statistics
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _dir(out: str | os.PathLike) -> Path:
    return Path(out) / RECORD_DIR


def read_run_record(out: str | os.PathLike) -> RunRecord | None:
    """The folder's :class:`RunRecord`, or None when it has none.

    Raises
    ------
    FormatError
        The record exists but cannot be read.
    """
    path = _dir(out) / RUN_FILE
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(d, dict) or not isinstance(d.get("settings"), dict):
            raise ValueError("not a run record")
        return RunRecord(str(d["command"]), str(d["version"]), d["settings"])
    except (OSError, UnicodeDecodeError, ValueError, KeyError) as exc:
        raise FormatError(
            f"{path}: unreadable record of what made {out} ({exc}); use --overwrite"
        ) from exc


def write_run_record(out: str | os.PathLike, record: RunRecord) -> None:
    with atomic_path(_dir(out) / RUN_FILE) as tmp:
        tmp.write_text(json.dumps(record.to_dict(), indent=1, sort_keys=True) + "\n", "utf-8")


def read_frame_records(out: str | os.PathLike) -> dict[str, FrameRecord]:
    """Frame records by key (the last line of a key wins; a damaged line is skipped)."""
    path = _dir(out) / FRAMES_FILE
    records: dict[str, FrameRecord] = {}
    if not path.is_file():
        return records
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc}); use --overwrite") from exc
    for line in text.splitlines():
        if not line.strip():
            continue
        try:
            rec = FrameRecord.from_line(line)
        except (ValueError, KeyError, TypeError, AttributeError):
            continue  # a line cut short by a crash: that frame is recomputed
        records[rec.key] = rec
    return records


def write_frame_records(out: str | os.PathLike, records: Mapping[str, FrameRecord]) -> None:
    """Rewrite ``frames.jsonl`` atomically with ``records`` sorted by key."""
    path = _dir(out) / FRAMES_FILE
    if not records:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        return
    with atomic_path(path) as tmp:
        tmp.write_text("".join(records[k].to_line() + "\n" for k in sorted(records)), "utf-8")


class FrameJournal:
    """Appends frame records to ``frames.jsonl`` as frames complete (one writer: the parent)."""

    def __init__(self, out: str | os.PathLike):
        self.path = _dir(out) / FRAMES_FILE
        self._fh = None

    def __enter__(self) -> FrameJournal:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "a", encoding="utf-8")
        return self

    def append(self, record: FrameRecord) -> None:
        self._fh.write(record.to_line() + "\n")
        self._fh.flush()

    def __exit__(self, *exc) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


@contextlib.contextmanager
def hold_lock(out: str | os.PathLike) -> Iterator[None]:
    """Hold ``OUT/.sparsetools/lock`` for the block; a second run into OUT is refused.

    The lock is an advisory ``flock``: the kernel drops it when the holding process dies, so
    a killed run never leaves the folder locked.
    """
    import fcntl

    d = _dir(out)
    try:
        d.mkdir(parents=True, exist_ok=True)
        fh = open(d / LOCK_FILE, "a+")
    except OSError as exc:
        raise OutputError(f"cannot write into {out}: {exc.strerror or exc}") from exc
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise OutputError(
                f"another sparsetools run is writing into {out}: wait for it to finish "
                "or use another -o"
            ) from None
        yield
    finally:
        fh.close()


def recorded_outputs(folder: str | os.PathLike, role: str | None = None) -> dict[str, Path] | None:
    """Outputs of one role recorded in ``folder``, by frame key; None when it has no record.

    ``role`` None: the folder's only role (None when it records several, so the caller
    decides). A record whose task covers several frames (``underwater`` segments) names its
    outputs ``<role>@<frame key>``.
    """
    if not (_dir(folder) / RUN_FILE).is_file():
        return None
    try:
        records = read_frame_records(folder)
    except FormatError:
        return None
    roles = {r.partition("@")[0] for rec in records.values() for r in rec.outputs}
    if role is None:
        if len(roles) != 1:
            return None
        role = next(iter(roles))
    root = Path(folder)
    out = {}
    for k, rec in records.items():
        for r, rel in rec.outputs.items():
            base, _, key = r.partition("@")
            if base == role:
                out[key or k] = root / rel
    return out


def remove_empty_record_dir(out: str | os.PathLike, *, run_record: bool = False) -> None:
    """Remove what a run that wrote nothing left in ``OUT/.sparsetools``: the lock (and, with
    ``run_record``, its run record and an empty journal); the folder too when it is empty."""
    d = _dir(out)
    if not d.is_dir():
        return
    names = [LOCK_FILE]
    if run_record:
        names.append(RUN_FILE)
        if (d / FRAMES_FILE).is_file() and not (d / FRAMES_FILE).stat().st_size:
            names.append(FRAMES_FILE)
    for name in names:
        with contextlib.suppress(OSError):
            (d / name).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        d.rmdir()


# -- single output files (viz pictures, eval reports) ----------------------------------------------


def file_record_path(output: str | os.PathLike) -> Path:
    """Where the record of a single output file lives: ``<dir>/.sparsetools/files/<name>.json``."""
    p = Path(output)
    return p.parent / RECORD_DIR / "files" / f"{p.name}.json"


def read_file_record(output: str | os.PathLike) -> tuple[RunRecord, FrameRecord] | None:
    """(run, inputs) record of a single output file, or None (no record, or unreadable)."""
    path = file_record_path(output)
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        run = RunRecord(str(d["command"]), str(d["version"]), dict(d["settings"]))
        frame = FrameRecord.from_line(json.dumps(d["frame"]))
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        return None
    return run, frame


def write_file_record(output: str | os.PathLike, run: RunRecord, frame: FrameRecord) -> None:
    doc = {**run.to_dict(), "frame": json.loads(frame.to_line())}
    with atomic_path(file_record_path(output)) as tmp:
        tmp.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n", encoding="utf-8")
