"""Parts of a dataset: the sparse points of its samples (``sparse/part-*.parquet``,
:data:`~sparsetools.io.dataset.PART_SCHEMA`) and their stored sensor points
(``points/part-*.parquet``, :data:`~sparsetools.io.dataset.POINTS_SCHEMA`), written atomically
and read back with their columns checked."""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..errors import FormatError
from .atomic import atomic_path
from .dataset import PART_SCHEMA, POINTS_SCHEMA, brief_error

__all__ = [
    "part_rows",
    "points_part_table",
    "read_points_part",
    "read_sparse_part",
    "write_points_part",
    "write_sparse_part",
]


def write_sparse_part(
    path: str | os.PathLike, table: pa.Table, *, row_group_size: int = 32
) -> None:
    """Write a sparse-points part (:data:`PART_SCHEMA`, zstd) atomically."""
    table = table.cast(PART_SCHEMA)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd", row_group_size=row_group_size)


def read_sparse_part(path: str | os.PathLike) -> pa.Table:
    """Read a whole sparse-points part, checking its columns."""
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        raise FormatError(f"{path}: cannot read the sparse part ({brief_error(exc)})") from exc
    missing = [n for n in PART_SCHEMA.names if n not in table.column_names]
    if missing:
        raise FormatError(f"{path}: sparse part lacks column(s) {', '.join(missing)}")
    try:
        table = table.select(PART_SCHEMA.names).cast(PART_SCHEMA)
        table.validate(full=True)
        return table
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
        raise FormatError(
            f"{path}: sparse part columns have unexpected types ({brief_error(exc)})"
        ) from exc


def part_rows(
    table: pa.Table,
) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray, int, int]]:
    """Iterate ``(id, u, v, depth, height, width)`` over a part table without Python per point."""
    ids = table.column("id").to_pylist()
    heights = table.column("height").to_numpy()
    widths = table.column("width").to_numpy()
    cols = []
    for name in ("u", "v", "depth"):
        arr = table.column(name).combine_chunks()
        cols.append((arr.offsets.to_numpy(), arr.values.to_numpy(zero_copy_only=False)))
    for i, fid in enumerate(ids):
        u, v, d = (vals[off[i] : off[i + 1]] for off, vals in cols)
        yield fid, u, v, d, int(heights[i]), int(widths[i])


def points_part_table(ids, clouds, sizes) -> pa.Table:
    """A points part (:data:`POINTS_SCHEMA`) from per-sample ``(xyz (N, 3) float64, ring (N,)
    int or None)`` and ``(height, width)``."""
    cols = {"id": list(ids), "x": [], "y": [], "z": [], "ring": [], "height": [], "width": []}
    for (xyz, ring), (h, w) in zip(clouds, sizes, strict=True):
        xyz = np.asarray(xyz, dtype=np.float64)
        for i, name in enumerate("xyz"):
            cols[name].append(xyz[:, i])
        cols["ring"].append(None if ring is None else np.asarray(ring, dtype=np.int16))
        cols["height"].append(int(h))
        cols["width"].append(int(w))
    arrays = [pa.array(cols[f.name], type=f.type) for f in POINTS_SCHEMA]
    return pa.Table.from_arrays(arrays, schema=POINTS_SCHEMA)


def write_points_part(path: str | os.PathLike, table: pa.Table) -> None:
    """Write a points part (:data:`POINTS_SCHEMA`, zstd, row groups of 8 samples) atomically."""
    table = table.cast(POINTS_SCHEMA)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd", row_group_size=8)


def read_points_part(path: str | os.PathLike) -> pa.Table:
    """Read a whole points part, checking its columns."""
    try:
        table = pq.read_table(path)
        missing = [n for n in POINTS_SCHEMA.names if n not in table.column_names]
        if missing:
            raise FormatError(f"{path}: points part lacks column(s) {', '.join(missing)}")
        table = table.select(POINTS_SCHEMA.names).cast(POINTS_SCHEMA)
        table.validate(full=True)
        return table
    except (pa.ArrowException, OSError) as exc:
        raise FormatError(f"{path}: cannot read the points part ({brief_error(exc)})") from exc
