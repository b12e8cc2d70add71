"""``manifest.parquet`` read and checked a batch of rows at a time (issue 28: ``dataset verify``
of a million samples never holds the manifest).

:class:`ManifestBatches` yields what :func:`~sparsetools.io.dataset.read_manifest` returns, a
row group at a time, through the same checks (one implementation, in :mod:`.dataset`).
"""

from __future__ import annotations

import os
from array import array
from collections.abc import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..errors import FormatError
from ..validate import check_int_range
from .dataset import (
    MANIFEST_ROW_GROUP,
    _check_manifest_values,
    _check_roots,
    _conform_manifest,
    _duplicate_ids,
    _duplicates_message,
    _manifest_file,
    _manifest_header,
    _unreadable,
)
from .frame_index import key_hash

__all__ = ["ManifestBatches"]


class ManifestBatches:
    """``manifest.parquet`` read and checked a batch of rows at a time: memory flat in its rows.

    Opening reads the file's metadata and checks it as :func:`~.dataset.read_manifest` does
    (schema version, columns and their types, build information). Iterating yields the rows
    in file order as tables of at most ``batch_rows`` rows, each typed and checked exactly
    as :func:`~.dataset.read_manifest` types and checks the whole table; it may be iterated
    again (the file is read afresh).

    The one check over all rows, that no sample id occurs twice, can only be made at the
    end: it raises after the last batch was yielded. A caller must therefore run the
    iteration to its end before trusting what it did with the rows. What it keeps meanwhile
    is an 8-byte hash of each id (:func:`~.frame_index.key_hash`); only when two hashes are
    equal is the id column read again to name the ids that occur twice (two ids with one
    hash refuse nothing).

    Parameters
    ----------
    path : path-like
        The manifest file (``DATASET/manifest.parquet``).
    batch_rows : int, optional
        Most rows per yielded table; default: a row group of :func:`~.manifest_writer.write_manifest`.

    Attributes
    ----------
    path : Path
    batch_rows : int
    info : dict
        ``schema_version`` plus the build information, as :func:`~.dataset.read_manifest`
        returns it.
    num_rows : int
        Rows (samples) of the manifest, from its Parquet metadata.

    Raises
    ------
    FormatError
        Opening: as :func:`~.dataset.read_manifest` for the file, its metadata and its
        columns. Iterating: a batch :func:`~.dataset.read_manifest` would refuse (a null in a
        required column, a path that could leave the dataset...), a file that cannot be
        read; after the last batch, ``{path}: duplicate sample id(s) a, b``.
    """

    def __init__(self, path: str | os.PathLike, *, batch_rows: int = MANIFEST_ROW_GROUP):
        self.batch_rows = check_int_range(batch_rows, "batch_rows", low=1)
        self.path = _manifest_file(path)
        with self._open() as pf:
            schema = pf.schema_arrow
            self.num_rows: int = pf.metadata.num_rows
        self._version, self.info, self._meta = _manifest_header(schema, self.path)
        # the column types, checked before any row is read (and for a manifest without rows)
        _conform_manifest(schema.empty_table(), self.path, version=self._version, meta=self._meta)
        _check_roots(self.info, self.path)

    def __iter__(self) -> Iterator[pa.Table]:
        hashes = array("q")
        with self._open() as pf:
            for batch in self._batches(pf, columns=None):
                table = pa.Table.from_batches([batch])
                table = _conform_manifest(table, self.path, version=self._version, meta=self._meta)
                _check_manifest_values(table, self.path)
                hashes.extend(key_hash(i) for i in table.column("id").to_pylist())
                yield table
        self._check_unique(hashes)

    def _open(self) -> pq.ParquetFile:
        try:
            return pq.ParquetFile(self.path)
        except (pa.ArrowException, OSError) as exc:
            raise _unreadable(self.path, exc) from exc

    def _batches(
        self, pf: pq.ParquetFile, *, columns: list[str] | None
    ) -> Iterator[pa.RecordBatch]:
        """The file's record batches, a read error as :class:`FormatError`."""
        batches = pf.iter_batches(batch_size=self.batch_rows, columns=columns)
        while True:
            try:
                batch = next(batches, None)
            except (pa.ArrowException, OSError) as exc:
                raise _unreadable(self.path, exc) from exc
            if batch is None:
                return
            yield batch

    def _check_unique(self, hashes: array) -> None:
        """Refuse ids that occur twice, given the hashes of all ids (file order)."""
        if len(hashes) < 2:
            return
        h = np.sort(np.frombuffer(hashes, dtype=np.int64))
        clash = set(h[1:][h[1:] == h[:-1]].tolist())
        if not clash:
            return
        # a second pass, over the ids column only, keeps just the ids of the equal hashes
        found = []
        with self._open() as pf:
            for batch in self._batches(pf, columns=["id"]):
                ids = batch.column(0).cast(pa.string()).to_pylist()
                found.extend(i for i in ids if key_hash(i) in clash)
        dup = _duplicate_ids(found)
        if dup:
            raise FormatError(_duplicates_message(self.path, dup))
