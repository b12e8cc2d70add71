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
import errno
import hashlib
import json
import os
import stat
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import FormatError, OutputError
from .atomic import atomic_path
from .containment import remove_output

__all__ = [
    "HASH_LIMIT",
    "RECORD_DIR",
    "FileIdentity",
    "FrameJournal",
    "FrameRecord",
    "OutputIdentity",
    "RunRecord",
    "check_record_dir",
    "file_identity",
    "file_record_path",
    "hold_lock",
    "iter_frame_records",
    "output_identity",
    "output_unchanged",
    "read_file_record",
    "read_frame_records",
    "read_run_record",
    "recorded_outputs",
    "remove_empty_record_dir",
    "unchanged_since",
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
        """From a record's ``[path, size, mtime_ns, sha256]`` (types checked: a record is
        untrusted input)."""
        path, size, mtime, sha = item
        if not (isinstance(path, str) and _is_int(size) and _is_int(mtime)
                and (sha is None or isinstance(sha, str))):  # fmt: skip
            raise TypeError("not a file identity")
        return cls(path, int(size), int(mtime), sha)

    def same_file(self, other: FileIdentity) -> bool:
        """Unchanged: same size and (same mtime, or the same recorded hash)."""
        if self.path != other.path or self.size != other.size:
            return False
        if self.mtime_ns == other.mtime_ns:
            return True
        return self.sha256 is not None and self.sha256 == other.sha256


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


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


def unchanged_since(before: FileIdentity, path: str | os.PathLike) -> bool:
    """Whether ``path`` is still the file ``before`` identified (one ``stat`` when it is):
    an input changed while its frame ran is caught by comparing this after the frame."""
    if before.size == 0 and before.mtime_ns == 0 and before.sha256 is not None:
        now = file_identity(path)  # a folder of calibration files: its files' identities
        return now.sha256 == before.sha256
    try:
        st = os.stat(path)
    except OSError:
        return before.size == -1
    if st.st_size != before.size:
        return False
    if st.st_mtime_ns == before.mtime_ns:
        return True
    return before.sha256 is not None and file_identity(path).sha256 == before.sha256


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
class OutputIdentity:
    """What identifies an output as the one a run wrote: its size, modification time and a
    digest of its bytes (a truncated or damaged output no longer matches): SHA-256, 64 hex
    digits; records of versions before 0.3 hold BLAKE2b-128, 32 hex digits, and are checked
    with it (:func:`output_unchanged`)."""

    size: int
    mtime_ns: int
    digest: str

    def to_list(self) -> list:
        return [self.size, self.mtime_ns, self.digest]

    @classmethod
    def from_list(cls, item) -> OutputIdentity:
        size, mtime, digest = item
        if not (_is_int(size) and _is_int(mtime) and isinstance(digest, str)):
            raise TypeError("not an output identity")
        return cls(int(size), int(mtime), digest)


#: Hex length of an output digest -> how it is computed: SHA-256 (shared with the dataset
#: manifest's file hashes, so a written output is hashed once), and the BLAKE2b-128 of records
#: written before 0.3, so that their folders still resume.
_DIGESTS = {64: hashlib.sha256, 32: lambda: hashlib.blake2b(digest_size=16)}


def output_identity(path: str | os.PathLike, *, digest_hex_len: int = 64) -> OutputIdentity | None:
    """The identity of an output file (None when it is not a regular file); its digest of the
    kind ``digest_hex_len`` names (64: SHA-256; 32: the BLAKE2b-128 of earlier records)."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            return None
        h = _DIGESTS[digest_hex_len]()
        while chunk := os.read(fd, 1 << 20):
            h.update(chunk)
    finally:
        os.close(fd)
    return OutputIdentity(int(st.st_size), int(st.st_mtime_ns), h.hexdigest())


def output_unchanged(path: str | os.PathLike, recorded: OutputIdentity) -> bool:
    """The output is the one recorded: same size, and the same mtime or the same digest."""
    try:
        st = os.lstat(path)
    except OSError:
        return False
    if not stat.S_ISREG(st.st_mode) or st.st_size != recorded.size:
        return False
    if st.st_mtime_ns == recorded.mtime_ns:
        return True
    if len(recorded.digest) not in _DIGESTS:
        return False
    now = output_identity(path, digest_hex_len=len(recorded.digest))
    return now is not None and now.digest == recorded.digest


def remove_unchanged_outputs(
    root: str | os.PathLike, outputs: Mapping[str, str | os.PathLike],
    recorded: Mapping[str, OutputIdentity],
) -> int:  # fmt: skip
    """Delete each output (role -> path) that is still the file recorded for its role, inside
    ``root`` and reached through no link; one changed since is left. Returns how many went."""
    n = 0
    for role, ident in recorded.items():
        p = outputs.get(role)
        if p is not None and output_unchanged(p, ident):
            n += remove_output(root, p)
    return n


@dataclass(frozen=True)
class FrameRecord:
    """One frame of a folder: its outputs by role (paths relative to the folder), their
    identities (what was written), its inputs' identities and its statistics."""

    key: str
    outputs: Mapping[str, str]
    inputs: tuple[FileIdentity, ...] = ()
    stats: Mapping = field(default_factory=dict)
    output_ids: Mapping[str, OutputIdentity] = field(default_factory=dict)

    def to_line(self) -> str:
        d = {
            "key": self.key,
            "outputs": dict(self.outputs),
            "inputs": [i.to_list() for i in self.inputs],
            "stats": dict(self.stats),
        }
        if self.output_ids:
            d["output_ids"] = {k: v.to_list() for k, v in self.output_ids.items()}
        return json.dumps(d, sort_keys=True, default=_json_number)

    @classmethod
    def from_line(cls, line: str) -> FrameRecord:
        """A record line (every field's type checked: ValueError/TypeError when one is off)."""
        d = json.loads(line)
        if not isinstance(d, dict) or not isinstance(d.get("key"), str):
            raise TypeError("not a frame record")
        outputs = d.get("outputs")
        if not isinstance(outputs, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in outputs.items()
        ):
            raise TypeError("outputs are not role -> path strings")
        inputs = d.get("inputs", [])
        if not isinstance(inputs, list):
            raise TypeError("inputs are not a list")
        ids = d.get("output_ids", {})
        if not isinstance(ids, dict):
            raise TypeError("output identities are not a mapping")
        stats = d.get("stats")
        return cls(
            d["key"],
            dict(outputs),
            tuple(FileIdentity.from_list(i) for i in inputs),
            stats if isinstance(stats, dict) else {},
            {str(k): OutputIdentity.from_list(v) for k, v in ids.items()},
        )


def _json_number(o):
    if hasattr(o, "item"):  # numpy scalars in per-frame statistics
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _dir(out: str | os.PathLike) -> Path:
    return Path(out) / RECORD_DIR


#: Largest run record read (bytes): a real one is a few KiB.
MAX_RUN_RECORD_BYTES = 1 << 20
#: Largest line of a frame journal read (bytes).
MAX_FRAME_LINE_BYTES = 1 << 20
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def check_record_dir(out: str | os.PathLike) -> Path:
    """``OUT/.sparsetools`` when it is a real folder or absent; a link (or anything else) in
    its place is refused: the record is never read or written through a link."""
    d = _dir(out)
    try:
        st = os.lstat(d)
    except FileNotFoundError:
        return d
    except OSError as exc:
        raise OutputError(f"cannot read {d}: {exc.strerror or exc}") from exc
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise OutputError(
            f"{d} is not a folder sparsetools made (a symbolic link or a file): remove it or "
            "use another -o"
        )
    return d


def _open_record(path: Path):
    """A record file opened for reading without following a link (None when absent)."""
    check_record_dir(path.parent.parent)
    try:
        fd = os.open(path, os.O_RDONLY | _NOFOLLOW)
    except FileNotFoundError:
        return None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise FormatError(f"{path} is a symbolic link, not a record: use --overwrite") from exc
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc}); use --overwrite") from exc
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise FormatError(f"{path} is not a regular file, not a record: use --overwrite")
    return os.fdopen(fd, "rb")


def read_run_record(out: str | os.PathLike) -> RunRecord | None:
    """The folder's :class:`RunRecord`, or None when it has none.

    Raises
    ------
    FormatError
        The record exists but cannot be read, is too large, or a field has the wrong type.
    """
    path = _dir(out) / RUN_FILE
    fh = _open_record(path)
    if fh is None:
        return None
    try:
        with fh:
            data = fh.read(MAX_RUN_RECORD_BYTES + 1)
        if len(data) > MAX_RUN_RECORD_BYTES:
            raise ValueError(f"larger than {MAX_RUN_RECORD_BYTES} bytes")
        d = json.loads(data.decode("utf-8"))
        if not isinstance(d, dict) or not isinstance(d.get("settings"), dict):
            raise ValueError("not a run record")
        if not (isinstance(d.get("command"), str) and isinstance(d.get("version"), str)):
            raise ValueError("command and version are not strings")
        return RunRecord(d["command"], d["version"], d["settings"])
    except (OSError, UnicodeDecodeError, ValueError, KeyError, RecursionError) as exc:
        why = "nested too deeply" if isinstance(exc, RecursionError) else exc
        raise FormatError(
            f"{path}: unreadable record of what made {out} ({why}); use --overwrite"
        ) from exc


def write_run_record(out: str | os.PathLike, record: RunRecord) -> None:
    check_record_dir(out)
    with atomic_path(_dir(out) / RUN_FILE) as tmp:
        tmp.write_text(json.dumps(record.to_dict(), indent=1, sort_keys=True) + "\n", "utf-8")


def iter_frame_records(out: str | os.PathLike) -> Iterator[FrameRecord]:
    """The frame records of a folder's journal, in file order (a damaged, oversized or
    mistyped line is skipped: that frame is recomputed)."""
    path = _dir(out) / FRAMES_FILE
    fh = _open_record(path)
    if fh is None:
        return
    with fh:
        while line := fh.readline(MAX_FRAME_LINE_BYTES + 1):
            if len(line) > MAX_FRAME_LINE_BYTES:
                while line and not line.endswith(b"\n"):  # the rest of an oversized line
                    line = fh.readline(MAX_FRAME_LINE_BYTES + 1)
                continue
            if not line.strip():
                continue
            try:
                yield FrameRecord.from_line(line.decode("utf-8"))
            except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
                continue  # a line cut short by a crash (or edited): that frame is recomputed


def read_frame_records(out: str | os.PathLike) -> dict[str, FrameRecord]:
    """Frame records by key (the last line of a key wins; a damaged line is skipped)."""
    records: dict[str, FrameRecord] = {}
    try:
        for rec in iter_frame_records(out):
            records[rec.key] = rec
    except OSError as exc:
        raise FormatError(
            f"{_dir(out) / FRAMES_FILE}: cannot read ({exc.strerror or exc}); use --overwrite"
        ) from exc
    return records


def write_frame_records(out: str | os.PathLike, records: Mapping[str, FrameRecord]) -> None:
    """Rewrite ``frames.jsonl`` atomically with ``records`` sorted by key."""
    check_record_dir(out)
    path = _dir(out) / FRAMES_FILE
    if not records:
        if os.path.islink(path) or os.path.isfile(path):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        return
    with atomic_path(path) as tmp:
        tmp.write_text("".join(records[k].to_line() + "\n" for k in sorted(records)), "utf-8")


class FrameJournal:
    """Appends frame records to ``frames.jsonl`` as frames complete (one writer: the parent;
    the journal is opened without following a link)."""

    def __init__(self, out: str | os.PathLike):
        self.path = _dir(out) / FRAMES_FILE
        self._fh = None

    def __enter__(self) -> FrameJournal:
        check_record_dir(self.path.parent.parent)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
        try:
            fd = os.open(self.path, flags, 0o666)
        except OSError as exc:
            raise OutputError(
                f"{self.path}: cannot write the record ({exc.strerror or exc}): a symbolic link "
                "or an unwritable file in its place; use --overwrite or another -o"
            ) from exc
        self._fh = os.fdopen(fd, "a", encoding="utf-8")
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

    d = check_record_dir(out)
    try:
        d.mkdir(parents=True, exist_ok=True)
        check_record_dir(out)  # a link made in between is refused too
        fd = os.open(d / LOCK_FILE, os.O_RDWR | os.O_CREAT | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0),
                     0o666)  # fmt: skip
        fh = os.fdopen(fd, "a+")
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
    outputs ``<role>@<frame key>``. The journal is read a line at a time and only each key's
    outputs are held (the last line of a key wins), not its records.
    """
    try:
        check_record_dir(folder)
    except OutputError:
        return None  # a link in place of the record: no record to trust
    if not (_dir(folder) / RUN_FILE).is_file():
        return None
    outputs: dict[str, tuple[tuple[str, str], ...]] = {}
    try:
        for rec in iter_frame_records(folder):
            outputs[rec.key] = tuple(rec.outputs.items())
    except OSError:
        return None  # an unreadable journal: no record to trust (as a damaged one)
    roles = {r.partition("@")[0] for items in outputs.values() for r, _ in items}
    if role is None:
        if len(roles) != 1:
            return None
        role = next(iter(roles))
    from .containment import contained_record_path

    out = {}
    for k, items in outputs.items():
        for r, rel in items:
            base, _, key = r.partition("@")
            path = contained_record_path(folder, rel)  # never a file outside the folder
            if base == role and path is not None:
                out[key or k] = path
    return out


def remove_empty_record_dir(out: str | os.PathLike, *, run_record: bool = False) -> None:
    """Remove what a run that wrote nothing left in ``OUT/.sparsetools``: the lock (and, with
    ``run_record``, its run record and an empty journal); the folder too when it is empty."""
    d = _dir(out)
    try:
        check_record_dir(out)
    except OutputError:
        return  # not ours to clean
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
