"""Raw files a dataset references in place (``--store reference``): root names, resolving a
reference inside its root, and the identity check (:mod:`sparsetools.io.dataset` uses them;
the layout is there and in docs/dataset.md, "Reference mode")."""

from __future__ import annotations

import os
import re
from pathlib import Path

from ..errors import FormatError

__all__ = ["check_root_name", "reference_unchanged", "resolve_reference"]

# -- references: raw files kept in place (--store reference) -----------------------------------------
_ROOT_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


def check_root_name(name: str, *, what: str = "root") -> str:
    """A root's name (``rgb``, ``kitti``): letters, digits, ``_ . -``, not starting with
    ``.`` or ``-``, at most 64 characters; else :class:`FormatError`."""
    if not isinstance(name, str) or not _ROOT_NAME.match(name):
        raise FormatError(f"{what}: {name!r} is not a root name (letters, digits, _ . -)")
    return name


def resolve_reference(root: str | os.PathLike, rel: str, *, name: str, sample: str = "") -> Path:
    """The file a reference names: ``root / rel``, refused (:class:`FormatError`, one line)
    when ``rel`` is absolute, holds ``..`` or a symbolic link takes it outside ``root``.

    A manifest is untrusted input: its references may only reach files inside their root
    (:func:`sparsetools.io.containment.contained_record_path`, then the real path checked).
    """
    from .containment import contained_record_path

    who = f"sample '{sample}': " if sample else ""
    path = contained_record_path(root, rel)
    if path is None:
        raise FormatError(
            f"{who}reference {rel!r} of root '{name}' is not a plain relative path "
            "(absolute paths and '..' are refused)"
        )
    real_root = os.path.realpath(root)
    real = os.path.realpath(path)
    if not real.startswith(real_root.rstrip(os.sep) + os.sep):
        raise FormatError(
            f"{who}reference {rel!r} resolves outside its root '{name}' ({root}): "
            "a symbolic link leaving the root is refused"
        )
    return path


def reference_unchanged(row, st: os.stat_result, sha256: str | None = None) -> bool:
    """Whether the referenced image of ``row`` (a :class:`~sparsetools.io.dataset.ManifestRow`)
    is still the file the build recorded, by the rule of the
    provenance record (:meth:`sparsetools.io.provenance.FileIdentity.same_file`): same size
    and (same modification time, or, for a file of at most ``HASH_LIMIT`` bytes, the same
    SHA-256). ``sha256``: the file's hash now, when the caller has it (small files)."""
    from .provenance import HASH_LIMIT

    if int(st.st_size) != row.rgb_size:
        return False
    if int(st.st_mtime_ns) == row.rgb_mtime_ns:
        return True
    return row.rgb_size <= HASH_LIMIT and sha256 is not None and sha256 == row.rgb_sha256
