"""Keep C libraries from printing on the process's stderr.

libpng ("libpng error: Not enough image data"), libjpeg ("Corrupt JPEG data: ...") and RPly
inside Open3D write straight to file descriptor 2, past Python's ``sys.stderr``. Those lines
would break the command line's promise of one ``Error:`` line per failure, so the readers
decode inside :func:`native_stderr_captured` and put the text into their exception (or a log
warning when the file was read after all).

File descriptor 2 belongs to the whole process: while any thread is inside the block it is
pointed at one shared temporary file, and restored when the last thread leaves, so threads
that decode at the same time are not serialised (text written by two of them at once may be
attributed to either).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from collections.abc import Iterator

__all__ = ["native_stderr_captured"]

_lock = threading.Lock()
_users = 0
_saved_fd: int | None = None
#: The file fd 2 points at inside the block, and the process that made it: made once per
#: process (a temporary file costs a file creation, 0.1-1 ms on a busy disk, and decoders
#: run per frame), emptied when it grows past _SINK_MAX while no thread is inside.
_sink = None
_sink_pid = -1
_SINK_MAX = 1 << 16


def _shared_sink():
    """This process's sink (a forked child makes its own: the parent's shares its offset)."""
    global _sink, _sink_pid
    if _sink is None or _sink_pid != os.getpid():
        _sink, _sink_pid = tempfile.TemporaryFile(), os.getpid()
    elif os.fstat(_sink.fileno()).st_size > _SINK_MAX:
        os.ftruncate(_sink.fileno(), 0)
    return _sink


@contextlib.contextmanager
def native_stderr_captured() -> Iterator[list[str]]:
    """Redirect fd 2 for the block; yield a list that holds the captured text afterwards."""
    global _users, _saved_fd
    captured: list[str] = []
    sink = None
    with _lock:
        if _users == 0:
            try:
                sys.stderr.flush()
                new_sink = _shared_sink()
                saved = os.dup(2)
                os.dup2(new_sink.fileno(), 2)
                _saved_fd = saved
                sink = new_sink
            except (OSError, ValueError):  # no usable fd 2 (embedded interpreters)
                sink = None
        elif _saved_fd is not None:
            sink = _sink
        if sink is not None:
            _users += 1
            start = os.lseek(sink.fileno(), 0, os.SEEK_END)
    if sink is None:
        yield captured
        return
    try:
        yield captured
    finally:
        with _lock:
            end = os.lseek(sink.fileno(), 0, os.SEEK_END)
            text = os.pread(sink.fileno(), min(end - start, 4096), start) if end > start else b""
            captured.append(" ".join(text.decode("utf-8", "replace").split()))
            _users -= 1
            if _users == 0:
                os.dup2(_saved_fd, 2)
                os.close(_saved_fd)
                _saved_fd = None
