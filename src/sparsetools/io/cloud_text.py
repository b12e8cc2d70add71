"""What the PCD and PLY readers and writers share: typed parsing of ascii columns, and the
writing of a text header followed by float32 rows."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .atomic import atomic_path

__all__ = ["parse_ascii_values", "write_header_and_rows"]


def parse_ascii_values(cells: np.ndarray, target: np.dtype) -> np.ndarray:
    """Numbers written as text (an array of ``bytes``) as ``target``'s type, exactly.

    Floats go through float64; integers through int64 / uint64 and must fit ``target``.

    Raises
    ------
    ValueError
        A cell is not a number of that kind, or an integer beyond ``target``'s range.
    """
    if target.kind == "f":
        return cells.astype(np.float64).astype(target)
    values = cells.astype(np.int64 if target.kind == "i" else np.uint64)
    if (values != values.astype(target)).any():
        raise ValueError(f"value beyond its {target} type")
    return values.astype(target)


def write_header_and_rows(
    path: str | os.PathLike, header: str, points: np.ndarray, names: list[str], *, overwrite: bool
) -> None:
    """Write ``header`` (ascii) then ``points`` as little-endian float32 rows, atomically.

    ``names`` (one per column, distinct) is checked against ``points``' columns first.
    """
    c = points.shape[1]
    if len(names) != c or len(set(names)) != c:
        raise FormatError(f"{path}: {c} columns need {c} distinct field names, got {names}")
    with atomic_path(Path(path), overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(np.ascontiguousarray(points, dtype="<f4").tobytes())
