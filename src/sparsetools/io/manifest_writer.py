"""Writing ``manifest.parquet``: a whole table (:func:`write_manifest`) or a row group at a
time (:class:`ManifestWriter`: a build of a million frames never holds its rows). Both go
through the writer, so a manifest written either way is the same file, byte for byte.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from .atomic import atomic_path
from .dataset import (
    BASE_SCHEMA_VERSION,
    MANIFEST_ROW_GROUP,
    MANIFEST_SCHEMA,
    METADATA_INFO_KEY,
    METADATA_VERSION_KEY,
    OPTIONAL_PATH_COLUMNS,
    OPTIONAL_SCHEMA,
    PATH_COLUMNS,
    REFERENCE_COLUMNS,
    SCHEMA_VERSION,
    check_relative_path,
)
from .dataset_refs import check_root_name

__all__ = ["ManifestWriter", "manifest_schema", "write_manifest"]


def manifest_schema(*, optional: Iterable[str] = (), referenced: bool = True) -> pa.Schema:
    """The columns a manifest is written with: :data:`MANIFEST_SCHEMA` (without the reference
    columns when no row references its image: the version-2 manifest of before, column for
    column), then the columns of :data:`OPTIONAL_SCHEMA` named in ``optional``, in its order."""
    wanted = set(optional)
    fields = [f for f in MANIFEST_SCHEMA if referenced or f.name not in REFERENCE_COLUMNS]
    return pa.schema([*fields, *(f for f in OPTIONAL_SCHEMA if f.name in wanted)])


class ManifestWriter:
    """``manifest.parquet`` written in row groups, renamed into place on :meth:`close`.

    Parameters
    ----------
    path : path-like
        The manifest; nothing appears there until :meth:`close` (a temporary file next to it
        is removed by :meth:`abort`, or by the next run when the process dies).
    optional : iterable of str
        The columns of :data:`OPTIONAL_SCHEMA` some row holds a value in (the others are not
        written: a dataset without them is byte for byte as before).
    referenced : bool
        Some row references its image in place (``rgb_root``): schema version 3; else the
        version-2 manifest without the reference columns.
    info : dict, optional
        The build information stored (as JSON) in the key-value metadata.

    Every table given to :meth:`write` has its path columns checked with
    :func:`check_relative_path` and its root names with ``check_root_name`` first.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        optional: Iterable[str] = (),
        referenced: bool = False,
        info: dict | None = None,
    ) -> None:
        version = SCHEMA_VERSION if referenced else BASE_SCHEMA_VERSION
        meta = {
            METADATA_VERSION_KEY: str(version).encode(),
            METADATA_INFO_KEY: json.dumps(info or {}, sort_keys=True).encode(),
        }
        self.schema = manifest_schema(optional=optional, referenced=referenced).with_metadata(meta)
        self._referenced = referenced
        self._paths = [*PATH_COLUMNS, *(c for c in OPTIONAL_PATH_COLUMNS if c in self.schema.names)]
        self._atomic = atomic_path(Path(path))
        tmp = self._atomic.__enter__()
        try:
            self._writer = pq.ParquetWriter(tmp, self.schema, compression="zstd")
        except BaseException as exc:
            self._atomic.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self.rows = 0

    def write(self, table: pa.Table) -> None:
        """Append rows (a table with at least the writer's columns; others are ignored)."""
        if self._referenced or "rgb_root" not in table.column_names:
            roots = table.column("rgb_root") if "rgb_root" in table.column_names else None
        else:
            roots = table.column("rgb_root")
            if roots.null_count < table.num_rows:
                raise ValueError("a row references its image but the writer was made without")
        for col in self._paths:
            for rel in table.column(col).to_pylist():
                if rel is not None:
                    check_relative_path(rel, what=col)
        if roots is not None:
            for name in roots.to_pylist():
                if name is not None:
                    check_root_name(name, what="rgb_root")
        table = table.select(self.schema.names).cast(self.schema)
        self._writer.write_table(table, row_group_size=MANIFEST_ROW_GROUP)
        self.rows += table.num_rows

    def close(self) -> None:
        """Finish the file and rename it onto the manifest."""
        self._writer.close()
        self._atomic.__exit__(None, None, None)

    def abort(self) -> None:
        """Drop what was written; the manifest in place (if any) is untouched."""
        self._writer.close()
        exc = RuntimeError("manifest not finished")
        try:
            self._atomic.__exit__(RuntimeError, exc, None)
        except RuntimeError:
            pass

    def __enter__(self) -> ManifestWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_manifest(path: str | os.PathLike, table: pa.Table, *, info: dict | None = None) -> None:
    """Write a manifest table atomically, with the schema version in the key-value metadata.

    Every path column is checked with :func:`check_relative_path` first. The columns of
    :data:`OPTIONAL_SCHEMA` are written only when some row holds a value in them; the
    reference columns (and schema version 3) only when some row references its image. Rows
    are written in row groups of :data:`MANIFEST_ROW_GROUP` (what
    :class:`~.manifest_stream.ManifestBatches` decodes at a time).
    """
    optional = [
        f.name
        for f in OPTIONAL_SCHEMA
        if f.name in table.column_names and table.column(f.name).null_count < table.num_rows
    ]
    referenced = table.column("rgb_root").null_count < table.num_rows
    with ManifestWriter(path, optional=optional, referenced=referenced, info=info) as writer:
        writer.write(table)
