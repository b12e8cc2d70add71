"""PCD files (the Point Cloud Library's format, v0.7), read and written without Open3D.

A PCD file is a text header (``FIELDS``, ``SIZE``, ``TYPE``, ``COUNT``, ``WIDTH``, ``HEIGHT``,
``POINTS``, ``DATA``) and a body in one of three layouts:

- ``ascii``: one point per line, ``sum(COUNT)`` numbers each;
- ``binary``: one packed little-endian record per point;
- ``binary_compressed``: two uint32 (compressed, uncompressed size) and an LZF stream that
  expands to the fields one after another (all x, then all y, ...), not point by point.

Every header value is checked against the file before a byte of the body is read: a count the
file cannot hold, a repeated field name or an unknown type is a :class:`FormatError`, never a
huge allocation or a short read.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .cloud_text import parse_ascii_values, write_header_and_rows

__all__ = ["PcdHeader", "parse_pcd_header", "pcd_dtype", "read_pcd", "read_pcd_header", "write_pcd"]

#: Field names PCL writes as padding (``_``): no data, skipped when reading.
PADDING_FIELD = "_"

_CODES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
          ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}  # fmt: skip


def pcd_dtype(fields, sizes, types, counts=None) -> np.dtype:
    """The packed little-endian record of one point (a field of COUNT > 1 is a sub-array)."""
    counts = [1] * len(fields) if counts is None else counts
    try:
        return np.dtype(
            [
                (f, "<" + _CODES[(t.upper(), int(s))], (int(c),)) if int(c) > 1
                else (f, "<" + _CODES[(t.upper(), int(s))])
                for f, s, t, c in zip(fields, sizes, types, counts, strict=True)
            ]
        )  # fmt: skip
    except (KeyError, ValueError, TypeError) as exc:
        raise FormatError(f"PCD field types not understood: {exc}") from exc


def parse_pcd_header(data: bytes, path: Path) -> tuple[dict[str, list[str]], int]:
    """The header's lines as ``{KEY: [values]}`` and the offset of the body (after ``DATA``)."""
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise FormatError(f"{path}: PCD header has no DATA line (truncated or not a PCD)")
        try:
            line = data[pos:end].decode("ascii").strip()
        except UnicodeDecodeError as exc:
            raise FormatError(f"{path}: not a PCD file (binary data in the header)") from exc
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, pos
        if len(header) > 32:
            raise FormatError(f"{path}: not a PCD file (no DATA line in the header)")


@dataclass(frozen=True)
class PcdHeader:
    """A checked PCD header.

    Attributes
    ----------
    fields, sizes, types, counts : tuple
        Per field: name, bytes per value (1, 2, 4, 8), ``F``/``I``/``U``, values per point.
    points : int
        WIDTH x HEIGHT.
    data : str
        ``ascii``, ``binary`` or ``binary_compressed``.
    offset : int
        Byte offset of the body in the file.
    """

    fields: tuple[str, ...]
    sizes: tuple[int, ...]
    types: tuple[str, ...]
    counts: tuple[int, ...]
    points: int
    data: str
    offset: int

    @property
    def dtype(self) -> np.dtype:
        return pcd_dtype(self.fields, self.sizes, self.types, self.counts)


def read_pcd_header(data: bytes, path: Path) -> PcdHeader:
    """Parse and check a PCD header against the file's bytes (see the module docstring)."""
    header, offset = parse_pcd_header(data, path)
    try:
        fields = tuple(header["FIELDS"])
        sizes = tuple(int(v) for v in header["SIZE"])
        types = tuple(t.upper() for t in header["TYPE"])
        counts = tuple(int(v) for v in header.get("COUNT", ["1"] * len(fields)))
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        points = int(header["POINTS"][0]) if "POINTS" in header else width * height
        kind = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as exc:
        raise FormatError(
            f"{path}: PCD header misses or garbles FIELDS/SIZE/TYPE/WIDTH/HEIGHT/DATA"
        ) from exc
    if (
        not fields
        or not len(fields) == len(sizes) == len(types) == len(counts)
        or any((t, s) not in _CODES for t, s in zip(types, sizes, strict=True))
        or any(not 1 <= c <= 4096 for c in counts)
    ):
        raise FormatError(f"{path}: PCD header has inconsistent FIELDS/SIZE/TYPE/COUNT")
    if len(set(fields)) != len(fields):
        raise FormatError(
            f"{path}: PCD header repeats a field name (PCL's '_' padding fields included): "
            "which column is which is ambiguous"
        )
    if not {"x", "y", "z"} <= set(fields):
        raise FormatError(f"{path}: PCD has no x, y, z fields")
    if min(width, height, points) < 0 or points != width * height:
        raise FormatError(f"{path}: PCD header: POINTS {points} != WIDTH {width} x HEIGHT {height}")
    row = sum(v * c for v, c in zip(sizes, counts, strict=True))
    body = len(data) - offset
    if kind == "binary":
        if points * row > body:
            raise FormatError(
                f"{path}: truncated: {points} points of {row} bytes declared, {body} bytes held"
            )
    elif kind == "binary_compressed":
        if body < 8:
            raise FormatError(f"{path}: truncated compressed PCD data")
        packed, unpacked = struct.unpack("<II", data[offset : offset + 8])
        if unpacked != points * row or packed > body - 8:
            raise FormatError(f"{path}: compressed PCD sizes do not match the header")
    elif kind == "ascii":
        if points > data.count(b"\n", offset) + 1:
            raise FormatError(f"{path}: truncated: {points} points declared, fewer lines held")
    else:
        raise FormatError(f"{path}: PCD DATA '{kind}' unsupported")
    return PcdHeader(fields, sizes, types, counts, points, kind, offset)


def read_pcd(path: str | os.PathLike, data: bytes | None = None) -> tuple[np.ndarray, PcdHeader]:
    """Read a PCD file's points as a structured array, one field per PCD field.

    Parameters
    ----------
    path : path-like
    data : bytes, optional
        The file's bytes when already read.

    Returns
    -------
    records : (N,) structured array
        Fields named, typed and shaped as in the header (a field of COUNT c is a (c,)
        sub-array), PCL's ``_`` padding fields left out.
    header : PcdHeader

    Raises
    ------
    FormatError
        Missing, truncated or corrupt file, or a header the body does not match.
    """
    path = Path(path)
    if data is None:
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    h = read_pcd_header(data, path)
    dtype = h.dtype
    if h.data == "binary":
        rec = np.frombuffer(data, dtype=dtype, count=h.points, offset=h.offset)
    elif h.data == "binary_compressed":
        rec = _read_compressed(data, h, dtype, path)
    else:
        rec = _read_ascii(data, h, dtype, path)
    keep = [f for f in h.fields if f != PADDING_FIELD]
    if len(keep) != len(h.fields):
        rec = rec[keep]
    return rec, h


def _read_compressed(data: bytes, h: PcdHeader, dtype: np.dtype, path: Path) -> np.ndarray:
    from .lzf import lzf_decompress

    packed, unpacked = struct.unpack("<II", data[h.offset : h.offset + 8])
    start = h.offset + 8
    raw = lzf_decompress(data[start : start + packed], unpacked, source=str(path))
    rec = np.empty(h.points, dtype=dtype)
    at = 0
    for name in h.fields:  # the fields one after another (a loop over fields, not points)
        sub = dtype[name]
        nbytes = sub.itemsize * h.points
        rec[name] = np.frombuffer(raw, dtype=sub, count=h.points, offset=at)
        at += nbytes
    return rec


def _read_ascii(data: bytes, h: PcdHeader, dtype: np.dtype, path: Path) -> np.ndarray:
    per_point = sum(h.counts)
    tokens = data[h.offset :].split()
    if len(tokens) != h.points * per_point:
        raise FormatError(
            f"{path}: ascii PCD holds {len(tokens)} values, the header declares "
            f"{h.points} points x {per_point}"
        )
    table = np.array(tokens, dtype=bytes).reshape(h.points, per_point)
    rec = np.empty(h.points, dtype=dtype)
    col = 0
    for name, count in zip(h.fields, h.counts, strict=True):
        target = dtype[name].base
        cells = table[:, col : col + count]
        col += count
        try:
            if name in ("rgb", "rgba") and target.kind != "f":  # PCL may write these as floats
                values = cells.astype(np.float64).astype(np.uint32).astype(target)
            else:
                values = parse_ascii_values(cells, target)
        except (ValueError, OverflowError) as exc:
            raise FormatError(f"{path}: ascii PCD field {name!r}: {exc}") from exc
        rec[name] = values if count > 1 else values[:, 0]
    return rec


def write_pcd(
    path: str | os.PathLike,
    points: np.ndarray,
    names: list[str],
    *,
    overwrite: bool = True,
) -> None:
    """Write (N, C) float32 columns as a binary PCD v0.7, atomically.

    Parameters
    ----------
    path : path-like
    points : (N, C) float32
        Columns in the order of ``names``.
    names : list of str
        One field name per column, x, y, z first.
    overwrite : bool
        Replace an existing file (the toolkit's own outputs only; see ``atomic_path``).

    The header is the one Open3D writes (``VIEWPOINT 0 0 0 1 0 0 0``, ``HEIGHT 1``), so a
    cloud of x, y, z (and intensity) is the same file byte for byte.
    """
    n, c = np.shape(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(names)}\nSIZE {' '.join(['4'] * c)}\nTYPE {' '.join(['F'] * c)}\n"
        f"COUNT {' '.join(['1'] * c)}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {n}\nDATA binary\n"
    )
    write_header_and_rows(path, header, points, names, overwrite=overwrite)
