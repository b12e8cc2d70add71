"""A folder's frame journal by key, without holding it in memory.

The journal (``OUT/.sparsetools/frames.jsonl``, :mod:`.provenance`) has one line per frame
and may have a million of them. :class:`FrameIndex` reads it once and keeps, per frame, the
64-bit hash of its key and the offset of its last valid line (16 bytes), and reads a frame's
record back from its line when it is asked for; :func:`compact_journal` rewrites the journal,
sorted by key, from the lines of the previous runs and of this one, one line in memory at a
time (plus the keys, for the sort).

Two keys with one hash (a chance of about 1e-10 for a million frames) leave one of the two
frames without a record: it is recomputed, never given another frame's record (a record is
used only when the key on its line is the key asked for).
"""

from __future__ import annotations

import contextlib
import os
from array import array
from collections.abc import Iterable, Iterator

import numpy as np

from .atomic import atomic_path
from .provenance import (
    FRAMES_FILE,
    MAX_FRAME_LINE_BYTES,
    FrameRecord,
    _dir,
    _open_record,
    check_record_dir,
)

__all__ = ["FrameIndex", "compact_journal", "key_hash"]


def key_hash(key: str) -> int:
    """The 64-bit hash the index keeps of a frame key (this process's ``hash``: never
    written anywhere)."""
    return hash(key)


def _scan(fh, start: int) -> Iterator[tuple[int, FrameRecord]]:
    """(offset, record) of every valid line from ``start`` on (an oversized, blank, damaged or
    mistyped line is skipped: that frame is recomputed)."""
    fh.seek(start)
    offset = start
    while line := fh.readline(MAX_FRAME_LINE_BYTES + 1):
        here = offset
        offset += len(line)
        if len(line) > MAX_FRAME_LINE_BYTES:
            while line and not line.endswith(b"\n"):  # the rest of an oversized line
                line = fh.readline(MAX_FRAME_LINE_BYTES + 1)
                offset += len(line)
            continue
        if not line.strip():
            continue
        try:
            yield here, FrameRecord.from_line(line.decode("utf-8"))
        except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
            continue  # a line cut short by a crash (or edited)


def _last_per_key(hashes: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique hashes and, for each, the offset of its last line (lines in file order)."""
    if hashes.size == 0:
        return hashes, offsets
    order = np.argsort(hashes, kind="stable")  # equal hashes keep file order
    h, o = hashes[order], offsets[order]
    last = np.ones(h.size, dtype=bool)
    last[:-1] = h[1:] != h[:-1]
    return h[last], o[last]


class FrameIndex:
    """Key -> record of a folder's journal, 16 bytes per frame in memory.

    Parameters
    ----------
    out : path-like
        The output folder (its record folder is checked not to be a link).
    present : bool
        False: the folder has no record; the index is empty and reads nothing.

    Attributes
    ----------
    end : int
        Size of the journal when it was read: lines appended later start there.
    """

    def __init__(self, out: str | os.PathLike, *, present: bool = True):
        self.path = _dir(out) / FRAMES_FILE
        self._fh = _open_record(self.path) if present else None
        hashes, offsets = array("q"), array("q")
        self.end = 0
        if self._fh is not None:
            for off, rec in _scan(self._fh, 0):
                hashes.append(key_hash(rec.key))
                offsets.append(off)
            self.end = self._fh.seek(0, os.SEEK_END)
        self.hashes, self.offsets = _last_per_key(
            np.frombuffer(hashes, dtype=np.int64), np.frombuffer(offsets, dtype=np.int64)
        )

    def __len__(self) -> int:
        return int(self.hashes.size)

    def _read(self, offset: int) -> FrameRecord | None:
        self._fh.seek(offset)
        line = self._fh.readline(MAX_FRAME_LINE_BYTES + 1)
        try:
            return FrameRecord.from_line(line.decode("utf-8"))
        except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
            return None

    def get(self, key: str) -> FrameRecord | None:
        """The record of ``key`` (its last valid line), or None."""
        if not self.hashes.size:
            return None
        h = key_hash(key)
        i = int(np.searchsorted(self.hashes, h))
        if i == self.hashes.size or self.hashes[i] != h:
            return None
        rec = self._read(int(self.offsets[i]))
        return rec if rec is not None and rec.key == key else None

    def records_except(self, hashes: np.ndarray) -> Iterator[FrameRecord]:
        """The records whose key hash is not in ``hashes`` (frames another run made)."""
        yield from self._records(~np.isin(self.hashes, hashes))

    def records_in(self, hashes: np.ndarray) -> Iterator[FrameRecord]:
        """The records whose key hash is in ``hashes``, in key-hash order."""
        yield from self._records(np.isin(self.hashes, hashes))

    def _records(self, which: np.ndarray) -> Iterator[FrameRecord]:
        for off in self.offsets[which]:
            rec = self._read(int(off))
            if rec is not None:
                yield rec

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def compact_journal(
    out: str | os.PathLike,
    index: FrameIndex,
    *,
    keep_old: bool,
    dropped: Iterable[str] = (),
) -> None:
    """Rewrite the journal sorted by key: every frame's last valid line, old or new.

    Parameters
    ----------
    out : path-like
    index : FrameIndex
        Of the journal as it was before this run appended to it (lines from ``index.end`` on
        are this run's).
    keep_old : bool
        False (``--overwrite``): only this run's lines are kept.
    dropped : iterable of str
        Frames whose older records are dropped (failed now: recomputed on the next run).
    """
    check_record_dir(out)
    path = _dir(out) / FRAMES_FILE
    fh = _open_record(path)
    if fh is None:
        return
    with fh:
        new_h, new_o = array("q"), array("q")
        for off, rec in _scan(fh, index.end):
            new_h.append(key_hash(rec.key))
            new_o.append(off)
        gone = np.fromiter((key_hash(k) for k in dropped), dtype=np.int64)
        old_h, old_o = (index.hashes, index.offsets) if keep_old else (np.empty(0, np.int64),) * 2
        keep = ~np.isin(old_h, gone)
        hashes, offsets = _last_per_key(
            np.concatenate([old_h[keep], np.frombuffer(new_h, dtype=np.int64)]),
            np.concatenate([old_o[keep], np.frombuffer(new_o, dtype=np.int64)]),
        )
        del hashes
        # the old lines are in the file as it was: ``index`` read it, and this run only appended.
        # Every offset kept is a line the scan found valid: it is copied as it is (one parse
        # per line, for its key; the last line of a file may lack its newline)
        keys = []
        for off in offsets.tolist():
            fh.seek(off)
            rec = _parse(fh.readline(MAX_FRAME_LINE_BYTES + 1))
            keys.append(rec.key if rec is not None else None)
        order = sorted((i for i, k in enumerate(keys) if k is not None), key=keys.__getitem__)
        del keys
        if not order:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
            return
        with atomic_path(path) as tmp, open(tmp, "wb") as dst:
            for i in order:
                fh.seek(int(offsets[i]))
                line = fh.readline(MAX_FRAME_LINE_BYTES + 1)
                dst.write(line if line.endswith(b"\n") else line + b"\n")


def _parse(line: bytes) -> FrameRecord | None:
    try:
        return FrameRecord.from_line(line.decode("utf-8"))
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
        return None
