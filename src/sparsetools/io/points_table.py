"""Sparse points as Parquet tables: one row per frame, ``u``/``v``/``depth`` as list columns.

Two directions: :func:`read_points_table` reads a user's points table (an input of
``dataset build --sparse TABLE.parquet``), :func:`sparse_part_table` builds one
``sparse/part-*.parquet`` table of a dataset (:data:`~sparsetools.io.dataset.PART_SCHEMA`)
from per-frame arrays without a Python loop over points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError
from .dataset import PART_SCHEMA, brief_error
from .sources import FrameKey

__all__ = ["read_points_table", "sparse_part_table"]

#: Suffixes a frame id may carry in a points table (``0000000005.png`` is frame ``0000000005``).
DEPTH_SUFFIXES = (".png", ".npy")


def read_points_table(path: Path) -> dict[FrameKey, tuple]:
    """A Parquet table of sparse points (one row per frame) -> key -> (u, v, depth, h, w)."""
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except Exception as exc:
        raise FormatError(
            f"{path}: cannot read the sparse-points table ({brief_error(exc)})"
        ) from exc
    id_col = next(
        (c for c in ("id", "frame_id", "stem", "frame", "name") if c in table.column_names), None
    )
    if id_col is None or not {"u", "v", "depth"} <= set(table.column_names):
        raise FormatError(f"{path}: a sparse-points table needs an id column and u, v, depth lists")
    ids = [str(x) for x in table.column(id_col).to_pylist()]
    hs = table.column("height").to_pylist() if "height" in table.column_names else [None] * len(ids)
    ws = table.column("width").to_pylist() if "width" in table.column_names else [None] * len(ids)
    cols = {}
    for name in ("u", "v", "depth"):
        arr = table.column(name).combine_chunks()
        cols[name] = (arr.offsets.to_numpy(), arr.values.to_numpy(zero_copy_only=False))
    out: dict[FrameKey, tuple] = {}
    for i, fid in enumerate(ids):
        if Path(fid).suffix.lower() in DEPTH_SUFFIXES:
            fid = fid[: -len(Path(fid).suffix)]
        try:
            key = FrameKey.parse(fid)
        except ParameterError as exc:
            raise FormatError(f"{path}: {exc}") from exc
        if key in out:
            raise FormatError(f"{path}: frame '{key}' appears twice")
        u, v, d = (vals[off[i] : off[i + 1]] for off, vals in cols.values())
        out[key] = (np.asarray(u), np.asarray(v), np.asarray(d), hs[i], ws[i])
    return out


def sparse_part_table(ids: list[str], points: list[tuple], sizes: list[tuple[int, int]]):
    """A :data:`PART_SCHEMA` table from per-frame (u, v, depth) arrays (no per-point Python)."""
    import pyarrow as pa

    lengths = np.array([len(p[0]) for p in points], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    if offsets[-1] > np.iinfo(np.int32).max:
        raise ParameterError("too many points for one part: lower frames_per_part")
    offsets = pa.array(offsets.astype(np.int32))

    def column(i, dtype, type_):
        values = (
            np.concatenate([np.asarray(p[i], dtype) for p in points])
            if points
            else np.zeros(0, dtype)
        )
        return pa.ListArray.from_arrays(offsets, pa.array(values, type=type_))

    return pa.table(
        {
            "id": pa.array(ids, pa.string()),
            "u": column(0, np.uint16, pa.uint16()),
            "v": column(1, np.uint16, pa.uint16()),
            "depth": column(2, np.float32, pa.float32()),
            "height": pa.array([h for h, _ in sizes], pa.int32()),
            "width": pa.array([w for _, w in sizes], pa.int32()),
        },
        schema=PART_SCHEMA,
    )
