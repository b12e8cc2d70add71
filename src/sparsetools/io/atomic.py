"""Atomic file writes: write to a temporary name in the same folder, then rename.

A reader never sees a half-written file and an interrupted run leaves no partial output
(only a ``.tmp-*`` file that the next run removes), so "the output exists" means "it is complete".
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import hashlib
import itertools
import os
from collections.abc import Iterator
from pathlib import Path

from ..errors import OutputError

__all__ = [
    "TMP_PREFIX",
    "atomic_path",
    "atomic_write_bytes",
    "recording_writes",
    "remove_stale_temporaries",
]

TMP_PREFIX = ".tmp-sparsetools-"

#: Where :func:`atomic_write_bytes` notes what it wrote, inside :func:`recording_writes`.
_written: contextvars.ContextVar[dict | None] = contextvars.ContextVar("written", default=None)


@contextlib.contextmanager
def recording_writes() -> Iterator[dict[str, tuple[int, str]]]:
    """Within the block, :func:`atomic_write_bytes` notes each file it writes: path (as
    given, ``os.fspath``) -> (size in bytes, SHA-256 hex digest of the bytes written).

    The frame runner takes an output's identity from here instead of reading the file back
    (``provenance.output_identity`` digests the same way): one ``stat`` instead of an
    ``open`` and a read of every byte."""
    token = _written.set({})
    try:
        yield _written.get()
    finally:
        _written.reset(token)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` when the block succeeds.

    Parameters
    ----------
    path : path-like
        Final destination.
    overwrite : bool
        When False and ``path`` exists, raise :class:`OutputError` before anything is written.

    The temporary file keeps the last suffix of ``path`` so writers that choose the format
    by suffix (OpenCV, Open3D) still work; its name is short whatever ``path``'s is. On any
    exception the temporary file is removed.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise OutputError(f"{path} exists (use --overwrite to replace it)")
    parent = path.parent
    name, fd = _open_temporary(parent, path.suffix)
    os.close(fd)
    tmp = Path(name)
    try:
        try:
            yield tmp
            try:
                size = os.stat(tmp).st_size
            except FileNotFoundError:
                size = None
            if size is None or (size == 0 and not _allow_empty(path)):
                raise OutputError(f"writing {path} produced no data")
            os.replace(tmp, path)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise OutputError(f"no space left on device while writing {path}") from exc
            if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENAMETOOLONG):
                raise OutputError(f"cannot write {path}: {exc.strerror}") from exc
            raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


_names = itertools.count()


def _open_temporary(parent: Path, suffix: str) -> tuple[str, int]:
    """Create an empty, unique temporary file in ``parent`` (made when missing): its name and
    a file descriptor open for writing.

    The name is the prefix, this process's id, a counter and random hex (so two processes,
    or a forked child and its parent, never collide); ``O_EXCL`` makes the creation fail
    rather than reuse a name. Mode ``0o666`` gives outputs the usual permissions after the
    umask (``mkstemp`` would make them 0600). Two system calls in the common case, against
    about ten for ``mkdir(exist_ok)`` + ``mkstemp`` + ``chmod``: per-frame writes are many.
    """
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    for attempt in range(100):
        name = os.path.join(
            parent, f"{TMP_PREFIX}{os.getpid()}-{next(_names)}-{os.urandom(3).hex()}{suffix}"
        )
        try:
            return name, os.open(name, flags, 0o666)
        except FileExistsError:
            continue
        except FileNotFoundError:
            if attempt:
                raise OutputError(f"cannot create output folder {parent}") from None
            _make_folder(parent)
        except PermissionError as exc:
            raise OutputError(f"output folder {parent} is not writable") from exc
        except NotADirectoryError as exc:
            raise OutputError(
                f"cannot create output folder {parent}: a file is in the way"
            ) from exc
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise OutputError(f"no space left on device while writing into {parent}") from exc
            raise OutputError(f"cannot write into {parent}: {exc.strerror or exc}") from exc
    raise OutputError(f"cannot create a temporary file in {parent}")  # pragma: no cover


def atomic_write_bytes(
    path: str | os.PathLike,
    data: bytes | memoryview,
    *,
    overwrite: bool = True,
    sha256: str | None = None,
) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then rename).

    The same guarantees as :func:`atomic_path` (and the same one-line errors for a full disk
    or a read-only folder; ``overwrite`` False: an existing ``path`` is refused before
    anything is written), with the temporary file written through the descriptor that
    created it: one ``open`` per output instead of two, which matters for writers of many
    small files (``dataset build`` stores four per frame, ``project`` two).

    ``sha256``: the hex SHA-256 of ``data`` when the caller has already computed it (a
    dataset's manifest records it): inside :func:`recording_writes` it is noted as is
    instead of hashing the bytes a second time.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise OutputError(f"{path} exists (use --overwrite to replace it)")
    if not len(data) and not _allow_empty(path):
        raise OutputError(f"writing {path} produced no data")
    name, fd = _open_temporary(path.parent, path.suffix)
    try:
        try:
            whole = view = memoryview(data).cast("B")
            while view:
                view = view[os.write(fd, view) :]
            os.close(fd)
            fd = -1
            os.replace(name, path)
            written = _written.get()
            if written is not None:
                digest = sha256 or hashlib.sha256(whole).hexdigest()
                written[os.fspath(path)] = (len(whole), digest)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise OutputError(f"no space left on device while writing {path}") from exc
            if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENAMETOOLONG):
                raise OutputError(f"cannot write {path}: {exc.strerror}") from exc
            raise
    except BaseException:
        if fd >= 0:
            os.close(fd)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(name)
        raise


def _make_folder(parent: Path) -> None:
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError) as exc:
        raise OutputError(f"cannot create output folder {parent}: a file is in the way") from exc
    except PermissionError as exc:
        raise OutputError(f"cannot create output folder {parent}: permission denied") from exc


def _allow_empty(path: Path) -> bool:
    # A KITTI .bin of an empty cloud is legitimately zero bytes.
    return path.suffix in {".bin", ".txt", ".csv"}


def remove_stale_temporaries(folder: str | os.PathLike, *, recursive: bool = True) -> int:
    """Delete temporary files left by an interrupted run in ``folder`` (and below, when
    ``recursive``); return how many."""
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    n = 0
    for tmp in (folder.rglob if recursive else folder.glob)(TMP_PREFIX + "*"):
        with contextlib.suppress(OSError):
            tmp.unlink()
            n += 1
    return n
