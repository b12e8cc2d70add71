"""The manifest read a batch at a time (:class:`ManifestBatches`, issue 28): the rows, types and
refusals of :func:`read_manifest`, memory flat in the rows; row groups on write; ``dataset
verify`` over a manifest of several row groups reports as before."""

from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import sparsetools.io.dataset as dataset_io
import sparsetools.io.manifest_stream as manifest_stream
import sparsetools.io.manifest_writer as manifest_writer
from _cli import one_line_error, run
from sparsetools.errors import FormatError, ParameterError
from sparsetools.io.dataset import (
    MANIFEST_NAME,
    MANIFEST_ROW_GROUP,
    MANIFEST_SCHEMA,
    METADATA_VERSION_KEY,
    SCHEMA_VERSION,
    V2_COLUMNS,
    ManifestRow,
    read_manifest,
)
from sparsetools.io.manifest_stream import ManifestBatches
from sparsetools.io.manifest_writer import write_manifest
from sparsetools.pipeline.dataset import verify_dataset
from test_dataset import build, make_inputs


def make_row(i: int, **kw) -> ManifestRow:
    """A tiny sample ``i`` (files that need not exist: only the manifest is read)."""
    seq, frame = f"seq{i % 7}", f"{i:06d}"
    values = {
        "id": f"{seq}/{frame}", "sequence": seq, "frame": frame, "split": "train",
        "width": 4, "height": 2, "rgb_path": f"rgb/{seq}/{frame}.png",
        "sparse_path": f"sparse/{seq}/{frame}.png", "sparse_parquet": "sparse/part-00000.parquet",
        "sparse_row": i, "n_sparse": 1, "density": 1 / 8, "rgb_sha256": f"{i:064x}",
        "frame_index": i // 7,
    }  # fmt: skip
    values.update(kw)
    return ManifestRow.from_dict(values)


def write_rows(path: Path, n: int, **replace) -> Path:
    """A manifest of ``n`` rows; ``replace`` maps a row number to fields to change."""
    rows = [make_row(i, **replace.get(f"r{i}", {})) for i in range(n)]
    write_manifest(path, ManifestRow.to_table(rows), info={"tool": "test"})
    return path


def write_raw(path: Path, table: pa.Table, *, group: int = MANIFEST_ROW_GROUP, **meta) -> Path:
    """``table`` written as it is (no check) in row groups of ``group`` rows, its metadata
    updated with ``meta`` (key -> bytes)."""
    new = dict(table.schema.metadata or {})
    new.update({k.encode(): v for k, v in meta.items()})
    table = table.replace_schema_metadata(new)
    pq.write_table(table, path, compression="zstd", row_group_size=group)
    return path


def set_value(table: pa.Table, column: str, row: int, value) -> pa.Table:
    """``table`` with one cell changed (the column's type kept; ``None`` for null)."""
    values = table.column(column).to_pylist()
    values[row] = value
    i = table.schema.get_field_index(column)
    field = table.schema.field(i).with_nullable(True)  # a null where a writer would refuse one
    return table.set_column(i, field, pa.array(values, field.type))


def streamed(path: Path, batch_rows: int) -> tuple[pa.Table, list[int]]:
    batches = list(ManifestBatches(path, batch_rows=batch_rows))
    return pa.concat_tables(batches), [b.num_rows for b in batches]


@pytest.fixture(scope="module")
def big(tmp_path_factory) -> Path:
    """9,000 rows: row groups of 4096, 4096 and 808."""
    return write_rows(tmp_path_factory.mktemp("big") / MANIFEST_NAME, 9000)


def refusal(fn) -> str:
    with pytest.raises(FormatError) as e:
        fn()
    return str(e.value)


# -- the rows ------------------------------------------------------------------------------------
@pytest.mark.parametrize("batch_rows", [MANIFEST_ROW_GROUP, 1000, 700, 20_000])
def test_batches_are_the_rows_and_types_of_read_manifest(big, batch_rows):
    assert pq.ParquetFile(big).metadata.num_row_groups == 3
    table, info = read_manifest(big)
    manifest = ManifestBatches(big, batch_rows=batch_rows)
    assert manifest.num_rows == 9000 and manifest.info == info
    got, sizes = streamed(big, batch_rows)
    assert sum(sizes) == 9000 and max(sizes) <= batch_rows
    assert got.equals(table) and got.schema.equals(table.schema, check_metadata=True)
    # again: the same rows (each iteration reads the file afresh)
    assert pa.concat_tables(list(manifest)).equals(table)


def test_batches_of_an_older_manifest_and_optional_columns(tmp_path):
    """The columns a version-1 manifest lacks, and the optional ones its writer left out, are
    null in each batch as in read_manifest's table; a column filled only in the last batch is
    typed in every batch."""
    path = write_rows(tmp_path / "a.parquet", 3000, r2999={"camera": "image_02"})
    table, _ = read_manifest(path)
    old = write_raw(
        tmp_path / "v1.parquet", table.drop_columns([*V2_COLUMNS, "camera"]),
        **{METADATA_VERSION_KEY.decode(): b"1"},
    )  # fmt: skip
    for p in (path, old):
        want, info = read_manifest(p)
        got, _ = streamed(p, 1000)
        assert got.equals(want) and got.schema.equals(want.schema, check_metadata=True)
        assert ManifestBatches(p).info == info
    assert info["schema_version"] == 1 and got.column("frame_index").null_count == 3000


def test_an_empty_manifest_yields_nothing(tmp_path):
    path = write_rows(tmp_path / MANIFEST_NAME, 0)
    manifest = ManifestBatches(path)
    assert manifest.num_rows == 0 and list(manifest) == []
    assert manifest.info == read_manifest(path)[1]
    with pytest.raises(ParameterError):
        ManifestBatches(path, batch_rows=0)


# -- refusals ------------------------------------------------------------------------------------
def _duplicate_late(table):  # an id of the first row group again in the last
    return set_value(table, "id", 8500, table.column("id")[3].as_py()), {}


def _bad_path_late(table):
    return set_value(table, "gt_path", 8999, "../../etc/passwd"), {}


def _newer_version(table):
    return table, {METADATA_VERSION_KEY.decode(): str(SCHEMA_VERSION + 1).encode()}


def _null_required_late(table):
    return set_value(table, "n_sparse", 8400, None), {}


def _bad_root_name_late(table):
    table = set_value(table, "rgb_root", 8100, "../up")
    return set_value(set_value(table, "rgb_size", 8100, 1), "rgb_mtime_ns", 8100, 1), {}


def _wrong_type(table):
    i = table.schema.get_field_index("width")
    return table.set_column(i, "width", pa.array([[1]] * table.num_rows)), {}


def _negative_late(table):
    return set_value(table, "n_sparse", 8888, -1), {}


def _corrupt_info(table):
    return table, {dataset_io.METADATA_INFO_KEY.decode(): b"{not json"}


@pytest.mark.parametrize(
    "corrupt",
    [_duplicate_late, _bad_path_late, _newer_version, _null_required_late, _bad_root_name_late,
     _wrong_type, _negative_late, _corrupt_info],
)  # fmt: skip
@pytest.mark.parametrize("batch_rows", [MANIFEST_ROW_GROUP, 1000])
def test_the_stream_refuses_what_read_manifest_refuses(big, tmp_path, corrupt, batch_rows):
    table = read_manifest(big)[0]
    if corrupt is _bad_root_name_late:  # a version-3 manifest: the reference columns kept
        table = set_value(table, "rgb_root", 0, "rgb")
        table = set_value(set_value(table, "rgb_size", 0, 1), "rgb_mtime_ns", 0, 1)
    table, meta = corrupt(table)
    path = write_raw(tmp_path / MANIFEST_NAME, table, **meta)
    want = refusal(lambda: read_manifest(path))
    assert refusal(lambda: streamed(path, batch_rows)) == want


def test_duplicates_are_refused_after_the_last_batch(big, tmp_path):
    """A duplicate is known at the end: every batch is yielded, then the stream raises,
    naming the ids as read_manifest does."""
    table = read_manifest(big)[0]
    first = table.column("id")[10].as_py()
    second = table.column("id")[4500].as_py()
    table = set_value(set_value(table, "id", 8999, first), "id", 6000, second)
    path = write_raw(tmp_path / MANIFEST_NAME, table)
    want = refusal(lambda: read_manifest(path))
    assert want == f"{path}: duplicate sample id(s) {', '.join(sorted([first, second]))}"
    seen = 0
    with pytest.raises(FormatError) as e:
        for batch in ManifestBatches(path, batch_rows=1000):
            seen += batch.num_rows
    assert seen == 9000 and str(e.value) == want


def test_a_hash_clash_refuses_nothing(big, tmp_path, monkeypatch):
    """Every id given one hash: distinct ids still pass (the exact second pass finds no
    duplicate), true duplicates are still named as read_manifest names them."""
    monkeypatch.setattr(manifest_stream, "key_hash", lambda key: 7)
    got, _ = streamed(big, 1000)
    assert got.num_rows == 9000 and got.equals(read_manifest(big)[0])
    table = read_manifest(big)[0]
    table = set_value(table, "id", 8000, table.column("id")[5].as_py())
    path = write_raw(tmp_path / MANIFEST_NAME, table)
    want = refusal(lambda: read_manifest(path))
    assert "duplicate sample id(s)" in want
    assert refusal(lambda: streamed(path, 1000)) == want


def test_two_null_ids_are_null_values_not_a_crash(big, tmp_path):
    table = set_value(set_value(read_manifest(big)[0], "id", 1, None), "id", 2, None)
    path = write_raw(tmp_path / MANIFEST_NAME, table)
    want = f"{path}: column id holds empty (null) values"
    assert refusal(lambda: read_manifest(path)) == want
    assert refusal(lambda: streamed(path, 1000)) == want


# -- writing -------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [1, 100, MANIFEST_ROW_GROUP])
def test_a_manifest_of_one_row_group_is_written_as_before(tmp_path, n):
    """Up to MANIFEST_ROW_GROUP rows, the file is byte for byte what a plain pq.write_table of
    the table (the columns, types and metadata of the schema version; no row group size) wrote
    before: digests of datasets built before hold."""
    path = write_rows(tmp_path / MANIFEST_NAME, n)
    assert pq.ParquetFile(path).num_row_groups == 1
    table = ManifestRow.to_table([make_row(i) for i in range(n)])
    table = table.select(MANIFEST_SCHEMA.names).cast(MANIFEST_SCHEMA)
    table = table.drop_columns(["rgb_root", "rgb_size", "rgb_mtime_ns"])  # nothing referenced
    meta = {b"sparsetools.schema_version": b"2", b"sparsetools.dataset": b'{"tool": "test"}'}
    pq.write_table(table.replace_schema_metadata(meta), tmp_path / "before.parquet",
                   compression="zstd")  # fmt: skip
    assert path.read_bytes() == (tmp_path / "before.parquet").read_bytes()


def test_a_larger_manifest_is_written_in_row_groups(tmp_path):
    path = write_rows(tmp_path / MANIFEST_NAME, MANIFEST_ROW_GROUP + 1)
    meta = pq.ParquetFile(path).metadata
    assert [meta.row_group(i).num_rows for i in range(meta.num_row_groups)] == [
        MANIFEST_ROW_GROUP, 1
    ]  # fmt: skip


# -- memory --------------------------------------------------------------------------------------
def _peak(fn) -> int:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_the_stream_holds_a_batch_not_the_manifest(tmp_path):
    """tracemalloc peak (Python objects: ids, paths, hashes) of reading 20,000 rows a batch
    of 1024 at a time is well under read_manifest's."""
    path = write_rows(tmp_path / MANIFEST_NAME, 20_000)
    small = write_rows(tmp_path / "small.parquet", 10)
    read_manifest(small)  # imports and caches: not measured
    list(ManifestBatches(small))

    def stream():
        for _ in ManifestBatches(path, batch_rows=1024):
            pass

    whole = _peak(lambda: read_manifest(path))
    batched = _peak(stream)
    assert batched < 0.5 * whole, (batched, whole)


# -- dataset verify ------------------------------------------------------------------------------
def _damage(out: Path) -> None:
    (out / "rgb" / "seqA" / "000001.png").unlink()
    (out / "sparse" / "seqB" / "000002.png").write_bytes(b"not a png")
    (out / "gt" / "seqC" / "000000.png").write_bytes(b"")


def test_verify_over_row_groups_reports_as_over_one(tmp_path, monkeypatch):
    """The manifest rewritten in row groups of 2 rows (5 groups) and verify read in chunks of
    1, 2, 4 and its default: the same report (problems, warnings, their order, samples)."""
    from sparsetools.pipeline.dataset import verify

    inputs = make_inputs(tmp_path / "in")
    out = tmp_path / "ds"
    build(inputs, out)
    _damage(out)
    before = verify_dataset(out).to_dict()
    assert before["samples"] == 9 and len(before["problems"]) >= 3
    assert pq.ParquetFile(out / MANIFEST_NAME).metadata.num_row_groups == 1

    table, info = read_manifest(out / MANIFEST_NAME)
    info.pop("schema_version")
    monkeypatch.setattr(manifest_writer, "MANIFEST_ROW_GROUP", 2)
    write_manifest(out / MANIFEST_NAME, table, info=info)
    assert pq.ParquetFile(out / MANIFEST_NAME).metadata.num_row_groups == 5
    for chunk in (1, 2, 4, verify._VERIFY_CHUNK):
        monkeypatch.setattr(verify, "_VERIFY_CHUNK", chunk)
        for threads in (1, 3):
            assert verify_dataset(out, threads=threads).to_dict() == before
    r = run("dataset", "verify", out, "--json")
    assert r.exit_code == 1 and json.loads(r.stdout) == before


def test_verify_refuses_a_late_duplicate_as_read_manifest(tmp_path, monkeypatch):
    """A duplicate id in the last row group: verify raises read_manifest's one-line error
    (after checking files), and the command exits non-zero with that line."""
    from sparsetools.pipeline.dataset import verify

    inputs = make_inputs(tmp_path / "in")
    out = tmp_path / "ds"
    build(inputs, out)
    path = out / MANIFEST_NAME
    table, _ = read_manifest(path)
    first = table.column("id")[0].as_py()
    write_raw(path, set_value(table, "id", table.num_rows - 1, first), group=2)
    want = refusal(lambda: read_manifest(path))
    assert want == f"{path}: duplicate sample id(s) {first}"
    monkeypatch.setattr(verify, "_VERIFY_CHUNK", 2)
    assert refusal(lambda: verify_dataset(out)) == want
    assert want in one_line_error(run("dataset", "verify", out))
