"""Atomic file writes: write to a temporary name in the same folder, then rename.

A reader never sees a half-written file and an interrupted run leaves no partial output
(only a ``.tmp-*`` file that the next run removes), so "the output exists" means "it is complete".
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from ..errors import OutputError

__all__ = ["TMP_PREFIX", "atomic_path", "remove_stale_temporaries"]

TMP_PREFIX = ".tmp-sparsetools-"


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` when the block succeeds.

    Parameters
    ----------
    path : path-like
        Final destination.
    overwrite : bool
        When False and ``path`` exists, raise :class:`OutputError` before anything is written.

    The temporary file keeps the suffix of ``path`` so writers that choose the format by
    suffix (OpenCV, Open3D) still work. On any exception the temporary file is removed.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputError(f"{path} exists (use --overwrite to replace it)")
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError) as exc:
        raise OutputError(f"cannot create output folder {parent}: a file is in the way") from exc
    except PermissionError as exc:
        raise OutputError(f"cannot create output folder {parent}: permission denied") from exc
    try:
        fd, tmp_name = tempfile.mkstemp(
            prefix=TMP_PREFIX, suffix="".join(path.suffixes), dir=parent
        )
    except PermissionError as exc:
        raise OutputError(f"output folder {parent} is not writable") from exc
    except OSError as exc:
        raise OutputError(f"cannot write into {parent}: {exc.strerror or exc}") from exc
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        try:
            yield tmp
            if not tmp.exists() or (tmp.stat().st_size == 0 and not _allow_empty(path)):
                raise OutputError(f"writing {path} produced no data")
            # mkstemp creates 0600 files; give outputs the usual permissions (0666 & ~umask).
            os.chmod(tmp, 0o666 & ~_umask())
            os.replace(tmp, path)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise OutputError(f"no space left on device while writing {path}") from exc
            if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
                raise OutputError(f"cannot write {path}: {exc.strerror}") from exc
            raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


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
