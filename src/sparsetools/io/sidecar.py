"""Untrusted input files read within bounds, and JSON documents with typed fields.

:func:`read_regular_file` reads an input file that must be a regular file (a device, a FIFO
or a link to ``/dev/zero`` would block or be read until memory runs out) of at most
``max_bytes``. :func:`read_json_document` is the one reader of a JSON file the toolkit does
not trust (a nuScenes table, a record sidecar, a pipeline's ``steps.json``) on top of it:
nested at most :data:`MAX_JSON_DEPTH` levels (tables: as deep as the parser goes), every
failure one :class:`FormatError` naming the file. :func:`check_field` /
:func:`check_fields` check fields' kinds and :func:`field_error` words a field of the wrong
kind the same way everywhere (``FILE: record 3: 'timestamp' must be a finite number, got str
'abc'``).

Record sidecars are the JSON objects written beside each output of ``lowlight-synth`` and
``defocus-synth`` (``OUT/records/<sequence>/<frame>.json``), read back to rebuild their
manifests (:func:`read_sidecar`, :func:`read_record_sidecar`: opened without following a
link, like every record in -o).
"""

from __future__ import annotations

import errno
import json
import math
import os
import stat
from pathlib import Path

from ..errors import FormatError

__all__ = [
    "MAX_JSON_DEPTH",
    "MAX_SIDECAR_BYTES",
    "check_field",
    "check_fields",
    "check_manifest_row",
    "check_same_types",
    "field_error",
    "json_depth_exceeds",
    "read_json_document",
    "read_record_sidecar",
    "read_regular_file",
    "read_sidecar",
]

#: Largest sidecar read (bytes): a real one is a few KiB.
MAX_SIDECAR_BYTES = 1 << 20
#: Deepest nesting of arrays and objects accepted in a JSON document (the toolkit's own
#: documents and the nuScenes tables are at most 4 deep).
MAX_JSON_DEPTH = 64
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)


def json_depth_exceeds(value, limit: int = MAX_JSON_DEPTH) -> bool:
    """Whether a parsed JSON ``value`` nests lists / objects deeper than ``limit`` (walked
    without recursion)."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (list, dict)):
            if depth > limit:
                return True
            children = item.values() if isinstance(item, dict) else item
            stack.extend((c, depth + 1) for c in children if isinstance(c, (list, dict)))
    return False


def read_regular_file(
    path: str | os.PathLike,
    *,
    what: str,
    max_bytes: int,
    follow_links: bool = True,
    hint: str = "",
) -> bytes:
    """The bytes of an input file that must be a regular file of at most ``max_bytes``.

    The file is opened without blocking (a FIFO would wait for a writer forever) and checked
    on its open descriptor: a folder, a device (``/dev/zero`` reads forever), a pipe or a
    socket is refused, and so is a symbolic link when ``follow_links`` is False. At most
    ``max_bytes + 1`` bytes are read, so a file growing meanwhile stays bounded.

    Raises
    ------
    FileNotFoundError
        The file does not exist (the caller says what a missing file means).
    FormatError
        Anything else, naming the file and ``what`` it should be; ``hint`` ends the message.
    """
    path = Path(path)
    flags = os.O_RDONLY | _NONBLOCK | (0 if follow_links else _NOFOLLOW)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise
    except OSError as exc:
        if exc.errno == errno.ELOOP and not follow_links:
            raise FormatError(f"{path} is a symbolic link, not a {what}{hint}") from exc
        if exc.errno == errno.EISDIR:
            raise FormatError(f"{path}: is a folder, not a {what}{hint}") from exc
        raise FormatError(f"{path}: cannot read the {what} ({exc.strerror or exc}){hint}") from exc
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise FormatError(f"{path}: is a folder, not a {what}{hint}")
        if not stat.S_ISREG(st.st_mode):
            raise FormatError(
                f"{path}: not a regular file (a device or a pipe?), not a {what}{hint}"
            )
        if st.st_size > max_bytes:
            raise FormatError(
                f"{path}: {st.st_size} bytes, more than a {what} holds (limit {max_bytes}){hint}"
            )
        with os.fdopen(fd, "rb", closefd=False) as fh:
            # What fstat says plus one byte: a read of ``max_bytes + 1`` would reserve that
            # much (4 GiB for a depth map's limit) for every small file. A file that grew
            # since is read on in 1 MiB pieces, still never past ``max_bytes + 1``.
            parts = [fh.read(min(st.st_size, max_bytes) + 1)]
            got = len(parts[0])
            while st.st_size < got <= max_bytes:
                piece = fh.read(min(1 << 20, max_bytes + 1 - got))
                if not piece:
                    break
                parts.append(piece)
                got += len(piece)
            data = parts[0] if len(parts) == 1 else b"".join(parts)
    except OSError as exc:
        raise FormatError(f"{path}: cannot read the {what} ({exc.strerror or exc}){hint}") from exc
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise FormatError(f"{path}: more than a {what} holds (limit {max_bytes} bytes){hint}")
    return data


def read_json_document(
    path: str | os.PathLike,
    *,
    what: str,
    max_bytes: int,
    follow_links: bool = True,
    max_depth: int | None = MAX_JSON_DEPTH,
    hint: str = "",
):
    """The JSON value of a file, read within bounds.

    Parameters
    ----------
    path : path-like
    what : str
        What the file is, for messages ("nuScenes table", "record sidecar").
    max_bytes : int
        Largest file read; a larger one is refused before it is read.
    follow_links : bool
        False: a symbolic link in place of the file is refused (records inside ``-o``).
    max_depth : int, optional
        Deepest nesting accepted (walked after parsing; None: only the parser's own limit of
        about 1000 levels, for large tables whose typed fields are checked anyway).
    hint : str
        Appended to every message (``"; rerun with --overwrite"``).

    Raises
    ------
    FileNotFoundError
        The file does not exist (the caller says what a missing file means).
    FormatError
        Not a regular file, larger than ``max_bytes``, not UTF-8 JSON, or nested deeper
        than ``max_depth`` (or than the parser can go).
    """
    path = Path(path)
    data = read_regular_file(path, what=what, max_bytes=max_bytes, follow_links=follow_links,
                             hint=hint)  # fmt: skip
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not a {what} (not UTF-8 text){hint}") from exc
    try:
        value = json.loads(text)
    except RecursionError as exc:  # Python's parser recurses: ~1000 levels
        raise FormatError(f"{path}: not a {what} (JSON nested too deeply){hint}") from exc
    except json.JSONDecodeError as exc:
        raise FormatError(f"{path}: not valid JSON ({exc}){hint}") from exc
    if max_depth is not None and json_depth_exceeds(value, max_depth):
        raise FormatError(
            f"{path}: not a {what} (JSON nested deeper than {max_depth} levels){hint}"
        )
    return value


# -- typed fields ------------------------------------------------------------------------------

#: Names of the kinds :func:`check_field` knows, as messages say them.
_KINDS = {
    "str": "a string",
    "bool": "true or false",
    "int": "an integer",
    "count": "an integer >= 0",
    "number": "a finite number",
}


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def field_error(where: str, field: str, want: str, value) -> FormatError:
    """``WHERE: 'FIELD' must be WANT, got TYPE VALUE`` (one line)."""
    return FormatError(f"{where}: '{field}' must be {want}, got {type(value).__name__} "
                       f"{_short(value)}")  # fmt: skip


def _is_number(value) -> bool:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an integer beyond a double
        return False


def check_field(value, kind: str, where: str, field: str, *, length: int | None = None):
    """``value`` when it is of ``kind``; else :func:`field_error`.

    ``kind``: ``str``, ``bool``, ``int`` (not a bool), ``count`` (an int >= 0), ``number``
    (an int or a finite float, not a bool) or ``vector`` (a list of ``length`` numbers).
    """
    if kind == "vector":
        ok = (
            isinstance(value, list)
            and (length is None or len(value) == length)
            and all(_is_number(v) for v in value)
        )
        if not ok:
            n = "" if length is None else f"{length} "
            raise field_error(where, field, f"a list of {n}finite numbers", value)
        return value
    ok = {
        "str": lambda v: isinstance(v, str),
        "bool": lambda v: isinstance(v, bool),
        "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
        "count": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
        "number": _is_number,
    }[kind](value)
    if not ok:
        raise field_error(where, field, _KINDS[kind], value)
    return value


def _json_kind(value) -> str:
    import numpy as np

    if value is None:
        return "null"
    if isinstance(value, (bool, np.bool_)):
        return "bool"
    if isinstance(value, (int, np.integer)):
        return "int"
    if isinstance(value, (float, np.floating)):
        return "float"
    if isinstance(value, str):
        return "str"
    if isinstance(value, (list, tuple)):
        return "list"
    if isinstance(value, dict):
        return "dict"
    return type(value).__name__


_KIND_WORDS = {"null": "null", "bool": "true or false", "int": "an integer", "float": "a number",
               "str": "a string", "list": "a list", "dict": "an object"}  # fmt: skip


def check_same_types(value, typed, where: str, field: str) -> None:
    """Refuse a parsed JSON ``value`` whose fields have other JSON types than ``typed``, the
    same document as the typed record made of it writes it (``record.to_dict()``).

    A typed record's reader converts (``int("375")``, ``float(True)``): this finds what it
    converted, field by field (an integer stands for a number; keys only one side has are
    not compared). The message names the field's path (``record.noise.seed``).
    """
    stack = [(value, typed, field)]
    while stack:
        v, t, name = stack.pop()
        kv, kt = _json_kind(v), _json_kind(t)
        if kv != kt and not (kv == "int" and kt == "float"):
            raise field_error(where, name, _KIND_WORDS.get(kt, kt), v)
        if kt == "dict":
            stack.extend((v[k], t[k], f"{name}.{k}") for k in t if k in v)
        elif kt == "list":
            if len(v) != len(t):
                raise FormatError(f"{where}: '{name}' holds {len(v)} items, its record {len(t)}")
            stack.extend((a, b, f"{name}[{i}]") for i, (a, b) in enumerate(zip(v, t, strict=True)))


def check_fields(doc: dict, kinds: dict[str, str], where: str) -> None:
    """Every field of ``kinds`` present in ``doc`` with its kind (a missing one is named).

    A kind is one of :func:`check_field`'s (``str``, ``int``, ``count``, ``number``...),
    ``dict`` or ``list``; a trailing ``?`` allows null.
    """
    for name, kind in kinds.items():
        nullable = kind.endswith("?")
        kind = kind.rstrip("?")
        if name not in doc:
            raise FormatError(f"{where} lacks '{name}'")
        value = doc[name]
        if value is None and nullable:
            continue
        if kind in ("dict", "list"):
            if not isinstance(value, dict if kind == "dict" else list):
                raise field_error(where, name, _KIND_WORDS[kind], value)
        else:
            check_field(value, kind, where, name)


# -- record sidecars ---------------------------------------------------------------------------


def read_sidecar(path: str | os.PathLike) -> dict:
    """The JSON object of a record sidecar (a regular file, not a link, at most
    :data:`MAX_SIDECAR_BYTES`).

    Raises
    ------
    FormatError
        Missing, a link, unreadable, too large, not JSON, nested too deeply, or not an object.
    """
    path = Path(path)
    hint = "; rerun with --overwrite"
    try:
        side = read_json_document(
            path, what="record sidecar", max_bytes=MAX_SIDECAR_BYTES, follow_links=False,
            hint=hint,
        )  # fmt: skip
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such record sidecar{hint}") from exc
    if not isinstance(side, dict):
        raise FormatError(f"{path}: not a record sidecar (a JSON object){hint}")
    return side


def read_record_sidecar(
    path: str | os.PathLike,
    *,
    fields: dict[str, str],
    expect: dict,
    record_type,
    what: str,
):
    """A record sidecar checked field by field: ``(sidecar dict, typed record)``.

    Parameters
    ----------
    fields : dict
        The sidecar's fields and their kinds (:func:`check_fields`); ``record`` is the typed
        record's dict.
    expect : dict
        Fields whose value is known (``frame_id``, ``output``): a sidecar of another output
        is refused.
    record_type : class
        Has ``from_dict`` (raising :class:`~sparsetools.errors.ParameterError`) and
        ``to_dict``; the record's fields must have the kinds ``to_dict`` writes
        (:func:`check_same_types`).
    what : str
        The record's name for messages ("low-light record").

    Raises
    ------
    FormatError
        Naming the file and the field; every message ends with "rerun with --overwrite".
    """
    from ..errors import ParameterError

    hint = "; rerun with --overwrite"
    side = read_sidecar(path)
    where = str(path)
    try:
        check_fields(side, fields, where)
        for name, want in expect.items():
            if side[name] != want:
                raise FormatError(
                    f"{where}: '{name}' is {_short(side[name])}, not {_short(want)}: the record "
                    "of another output"
                )
        try:
            record = record_type.from_dict(side["record"])
        except (ValueError, TypeError, KeyError, AttributeError, OverflowError) as exc:
            # ParameterError (a ValueError) from the record's own checks; the others from a
            # reader that lets a conversion error through (int(Infinity))
            why = str(exc) if isinstance(exc, ParameterError) else f"{type(exc).__name__}: {exc}"
            raise FormatError(f"{where}: 'record' is not a {what} ({why})") from exc
        check_same_types(side["record"], record.to_dict(), where, "record")
    except FormatError as exc:
        raise FormatError(f"{exc}{hint}") from exc
    return side, record


def check_manifest_row(row: dict, schema, side_path: str | os.PathLike) -> None:
    """Refuse a sidecar's row that the manifest's column types cannot hold (an int beyond
    int32, a string where a number goes...), naming the sidecar."""
    import pyarrow as pa

    try:
        pa.Table.from_pylist([row], schema=schema)
    except (pa.ArrowException, OverflowError, TypeError, ValueError) as exc:
        why = " ".join(str(exc).split())[:200]
        raise FormatError(
            f"{side_path}: a value does not fit the manifest ({why}); rerun with --overwrite"
        ) from exc
