"""PLY files (Stanford polygon format), their vertex element read and written without Open3D.

A PLY file is a text header (``format``, ``element NAME COUNT``, ``property TYPE NAME``, ...,
``end_header``) and a body in ``ascii``, ``binary_little_endian`` or ``binary_big_endian``.
Point clouds are the ``vertex`` element; other elements (faces of a mesh) are skipped. Every
count is checked against the file before the body is read.

Not supported (a one-line :class:`FormatError` each): list properties in the vertex element,
and, in binary files, an element with list properties stored before the vertices (their rows
have no fixed size, so the vertices' offset is unknown without walking them).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .cloud_text import parse_ascii_values, write_header_and_rows

__all__ = ["PlyElement", "PlyHeader", "read_ply_header", "read_ply_vertices", "write_ply"]

_TYPES = {
    "char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "i2", "ushort": "u2",
    "int16": "i2", "uint16": "u2", "int": "i4", "uint": "u4", "int32": "i4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip

_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass(frozen=True)
class PlyElement:
    """One ``element`` of a PLY header: its name, row count and properties.

    ``properties`` holds ``(name, type)`` pairs; a list property's type is ``"list"``.
    """

    name: str
    count: int
    properties: tuple[tuple[str, str], ...]
    row_bytes: int  # without lists; lists count their length field only (a lower bound)

    @property
    def has_lists(self) -> bool:
        return any(t == "list" for _, t in self.properties)


@dataclass(frozen=True)
class PlyHeader:
    """A checked PLY header: the body's format, its elements in file order, the body's offset."""

    format: str
    elements: tuple[PlyElement, ...]
    offset: int

    @property
    def vertex(self) -> PlyElement:
        return next(e for e in self.elements if e.name == "vertex")


def read_ply_header(data: bytes, path: Path) -> PlyHeader:
    """Parse and check a PLY header against the file's bytes."""
    end = data.find(b"end_header")
    nl = data.find(b"\n", end) if end >= 0 else -1
    if not data.startswith(b"ply") or nl < 0:
        raise FormatError(f"{path}: not a PLY file (no complete 'ply' ... 'end_header' header)")
    try:
        lines = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not a PLY file (binary data in the header)") from exc
    fmt = None
    raw: list[list] = []  # name, count, bytes per row, properties
    try:
        for line in lines:
            parts = line.split()
            if not parts or parts[0] in ("comment", "obj_info"):
                continue
            if parts[0] == "format" and len(parts) == 3 and parts[2] == "1.0":
                fmt = parts[1]
            elif parts[0] == "element" and len(parts) == 3 and int(parts[2]) >= 0:
                raw.append([parts[1], int(parts[2]), 0, []])
            elif parts[0] == "property" and raw and len(parts) == 5 and parts[1] == "list":
                _TYPES[parts[3]]  # the item type must be known too
                raw[-1][2] += int(_TYPES[parts[2]][1])  # at least the count per row
                raw[-1][3].append((parts[4], "list"))
            elif parts[0] == "property" and raw and len(parts) == 3:
                raw[-1][2] += int(_TYPES[parts[1]][1])
                raw[-1][3].append((parts[2], parts[1]))
            else:
                raise ValueError(line)
    except (ValueError, KeyError) as exc:
        raise FormatError(f"{path}: PLY header line not understood: {str(exc)[:60]!r}") from exc
    if fmt not in _FORMATS:
        raise FormatError(f"{path}: PLY header has no valid 'format' line")
    elements = tuple(PlyElement(n, c, tuple(p), b) for n, c, b, p in raw)
    if any(len({p for p, _ in e.properties}) != len(e.properties) for e in elements) or len(
        {e.name for e in elements}
    ) != len(elements):
        raise FormatError(f"{path}: PLY header repeats an element or property name")
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None or not {"x", "y", "z"} <= {p for p, _ in vertex.properties}:
        raise FormatError(f"{path}: PLY has no vertex element with x, y, z")
    body = len(data) - nl - 1
    if fmt == "ascii":
        if sum(e.count for e in elements) > data.count(b"\n", nl + 1) + 1:
            raise FormatError(f"{path}: truncated: the header declares more rows than held")
    elif sum(e.count * max(e.row_bytes, 1) for e in elements) > body:
        raise FormatError(f"{path}: truncated: the header declares more data than held")
    return PlyHeader(fmt, elements, nl + 1)


def read_ply_vertices(
    path: str | os.PathLike, data: bytes | None = None
) -> tuple[np.ndarray, PlyHeader]:
    """Read a PLY file's vertices as a structured array, one field per vertex property.

    Parameters
    ----------
    path : path-like
    data : bytes, optional
        The file's bytes when already read.

    Returns
    -------
    records : (N,) structured array
        The vertex properties with their names and types, in header order.
    header : PlyHeader

    Raises
    ------
    FormatError
        Missing, truncated or corrupt file, or an unsupported layout (module docstring).
    """
    path = Path(path)
    if data is None:
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    h = read_ply_header(data, path)
    vertex = h.vertex
    if vertex.has_lists:
        raise FormatError(f"{path}: PLY vertex element holds list properties (unsupported)")
    order = _FORMATS[h.format] or "<"
    dtype = np.dtype([(p, order + _TYPES[t]) for p, t in vertex.properties])
    before = h.elements[: h.elements.index(vertex)]
    if h.format == "ascii":
        return _read_ascii(data, h, before, dtype, path), h
    if any(e.has_lists and e.count for e in before):
        raise FormatError(
            f"{path}: binary PLY with a list element before the vertices (unsupported)"
        )
    offset = h.offset + sum(e.count * e.row_bytes for e in before)
    if offset + vertex.count * dtype.itemsize > len(data):
        raise FormatError(f"{path}: truncated: the vertex data runs past the end of the file")
    rec = np.frombuffer(data, dtype=dtype, count=vertex.count, offset=offset)
    return rec.astype(dtype.newbyteorder("=")), h


def _read_ascii(data, h: PlyHeader, before, dtype: np.dtype, path: Path) -> np.ndarray:
    skip = sum(e.count for e in before)
    n = h.vertex.count
    lines = data[h.offset :].split(b"\n", skip + n)
    if len(lines) < skip + n:
        raise FormatError(f"{path}: truncated: fewer rows than the header declares")
    tokens = b" ".join(lines[skip : skip + n]).split()
    width = len(dtype.names)
    if len(tokens) != n * width:
        raise FormatError(
            f"{path}: ascii PLY vertices hold {len(tokens)} values, the header declares "
            f"{n} x {width}"
        )
    table = np.array(tokens, dtype=bytes).reshape(n, width)
    rec = np.empty(n, dtype=dtype.newbyteorder("="))
    for i, name in enumerate(dtype.names):
        target = rec.dtype[name]
        try:
            rec[name] = parse_ascii_values(table[:, i], target)
        except (ValueError, OverflowError) as exc:
            raise FormatError(f"{path}: ascii PLY property {name!r}: {exc}") from exc
    return rec


def write_ply(
    path: str | os.PathLike,
    points: np.ndarray,
    names: list[str],
    *,
    overwrite: bool = True,
) -> None:
    """Write (N, C) float32 columns as a binary little-endian PLY of one ``vertex`` element.

    Parameters
    ----------
    path : path-like
    points : (N, C) float32
        Columns in the order of ``names``.
    names : list of str
        One property name per column, x, y, z first.
    overwrite : bool
        Replace an existing file (the toolkit's own outputs only; see ``atomic_path``).
    """
    n, _ = np.shape(points)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment Created by sparsetools\n"
        f"element vertex {n}\n" + "".join(f"property float {p}\n" for p in names) + "end_header\n"
    )
    write_header_and_rows(path, header, points, names, overwrite=overwrite)
