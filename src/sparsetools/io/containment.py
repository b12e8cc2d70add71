"""Containment: nothing outside an output folder is ever written or deleted.

Every path that a command writes or deletes in its output folder ``-o`` -- its outputs, its
record, the paths its own records, journals and manifests name -- goes through this module
first. A path is *contained* when it is relative (or absolute inside the folder), holds no
``..``, and no existing part of it below the folder is a symbolic link (so nothing is written
through a link into another folder, whatever a record or an attacker placed there). The
folder itself may be a link: it is what the user chose.

Deletion is stricter still: :func:`remove_output` removes only a regular file (never a link,
a folder or a device) at a contained path.
"""

from __future__ import annotations

import contextlib
import os
import stat
from pathlib import Path, PurePosixPath

from ..errors import OutputError

__all__ = ["ContainedPaths", "check_contained", "contained_record_path", "remove_output"]


def _components(root: str, path: str) -> list[str] | None:
    """The parts of ``path`` below ``root`` (both absolute, normalised), or None outside."""
    rel = os.path.relpath(path, root)
    if rel == ".":
        return []
    parts = rel.split(os.sep)
    if parts[0] == ".." or os.path.isabs(rel):
        return None
    return parts


class ContainedPaths:
    """Checks paths against one output folder, remembering the folders already checked (a
    batch writes thousands of files into a few folders: one ``lstat`` per new folder).

    Parameters
    ----------
    root : path-like
        The output folder (``-o``); it may itself be a link.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = os.path.abspath(root)
        self._dirs_ok: set[str] = {self.root}

    def check(self, path: str | os.PathLike, *, what: str = "output") -> Path:
        """``path`` when it is contained in the folder; else :class:`OutputError`.

        An existing final part must be a regular file (or, for ``what="folder"``, a folder),
        not a link.
        """
        full = os.path.abspath(path)
        parts = _components(self.root, full)
        if parts is None:
            raise OutputError(
                f"{path} is outside the output folder {self.root}: sparsetools writes and "
                "deletes only inside -o"
            )
        current = self.root
        for i, part in enumerate(parts):
            current = os.path.join(current, part)
            last = i == len(parts) - 1
            if not last and current in self._dirs_ok:
                continue
            try:
                st = os.lstat(current)
            except FileNotFoundError:
                for rest in parts[i + 1 :]:  # below a missing folder nothing exists yet
                    current = os.path.join(current, rest)
                break
            except OSError as exc:
                raise OutputError(f"cannot check {current}: {exc.strerror or exc}") from exc
            if stat.S_ISLNK(st.st_mode):
                raise OutputError(
                    f"{current} is a symbolic link: sparsetools writes nothing through links "
                    "inside its output folder (remove the link or use another -o)"
                )
            if not last:
                if not stat.S_ISDIR(st.st_mode):
                    raise OutputError(f"{current} is in the way of {full}: it is not a folder")
                self._dirs_ok.add(current)
            elif what == "folder":
                if not stat.S_ISDIR(st.st_mode):
                    raise OutputError(f"{current} exists and is not a folder")
                self._dirs_ok.add(current)
            elif not stat.S_ISREG(st.st_mode):
                raise OutputError(f"{current} exists and is not a regular file")
        return Path(full)


def check_contained(
    root: str | os.PathLike, path: str | os.PathLike, *, what: str = "output"
) -> Path:
    """One path against one folder (:meth:`ContainedPaths.check`)."""
    return ContainedPaths(root).check(path, what=what)


def contained_record_path(root: str | os.PathLike, rel: str) -> Path | None:
    """The path a record names (POSIX, relative to ``root``), or None when the record is not to
    be trusted with it: not a string, absolute, with ``..``, empty or hidden parts, a NUL."""
    if not isinstance(rel, str) or not rel or "\x00" in rel or "\\" in rel:
        return None
    pure = PurePosixPath(rel)
    if pure.is_absolute() or any(p in ("", ".", "..") for p in pure.parts):
        return None
    return Path(root, *pure.parts)


def remove_output(root: str | os.PathLike, path: str | os.PathLike) -> bool:
    """Delete ``path`` when it is a regular file contained in ``root`` (never a link, a folder
    or anything outside); return whether a file was removed."""
    try:
        full = check_contained(root, path)
    except OutputError:
        return False
    try:
        st = os.lstat(full)
    except OSError:
        return False
    if not stat.S_ISREG(st.st_mode):
        return False
    with contextlib.suppress(FileNotFoundError):
        os.unlink(full)
        return True
    return False
