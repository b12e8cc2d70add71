"""Issue 28: ``dataset build`` keeps O(1) per frame in memory, and streaming changes nothing.

The merge of the staged frames writes the manifest a row group at a time (io/manifest_writer):
the manifest equals the one written whole, whatever the row-group size, for a new dataset, an
extended one and an overwritten one; the runner takes the identity of what a frame wrote from
the bytes written (io/atomic.recording_writes) and it equals the files read back; the merge's
memory grows by well under a kilobyte per frame.
"""

from __future__ import annotations

import json
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from sparsetools.errors import FormatError
from sparsetools.io.dataset import (
    FULL_SCHEMA,
    MANIFEST_NAME,
    ManifestRow,
    read_manifest,
)
from sparsetools.io.manifest_writer import ManifestWriter, write_manifest
from sparsetools.io.provenance import iter_frame_records, output_identity
from sparsetools.pipeline.dataset import merge
from sparsetools.pipeline.dataset.staged import write_record
from sparsetools.pipeline.dataset.staging import STAGING
from test_dataset import build, make_inputs


def _small_groups(monkeypatch, rows: int) -> None:
    import sparsetools.io.manifest_writer as mw

    monkeypatch.setattr(merge, "MANIFEST_ROW_GROUP", rows)
    monkeypatch.setattr(mw, "MANIFEST_ROW_GROUP", rows)


def _table(ds: Path) -> pa.Table:
    return read_manifest(ds / MANIFEST_NAME)[0]


def _parts(ds: Path) -> dict[str, bytes]:
    return {p.relative_to(ds).as_posix(): p.read_bytes() for p in ds.glob("*/part-*.parquet")}


@pytest.mark.parametrize("rows", [1, 4, 7])
def test_manifest_in_row_groups_equals_the_manifest_written_whole(tmp_path, monkeypatch, rows):
    """New, extended and overwritten datasets: the same rows, splits, parts and frame indices
    with row groups of 1, 4 or 7 rows as with the default (one group for 12 frames)."""
    first = make_inputs(tmp_path / "a", sequences=("s1", "s2", "s3"), frames=4)
    more = make_inputs(tmp_path / "b", sequences=("s3", "s4"), frames=3, seed=1)
    results = {}
    for name in ("whole", "groups"):
        if name == "groups":
            _small_groups(monkeypatch, rows)
        ds = tmp_path / f"ds_{name}"
        steps = [build(first, ds, frames_per_part=5)]
        steps.append(build(more, ds, frames_per_part=5))  # extends s3's frames, adds s4
        after_extend = _table(ds), _parts(ds)
        steps.append(build(more, ds, frames_per_part=5, overwrite=True))  # this run only
        results[name] = (steps, after_extend, (_table(ds), _parts(ds)))
        if name == "groups":
            assert pq.ParquetFile(ds / MANIFEST_NAME).num_row_groups == -(-6 // rows)
    whole, groups = results["whole"], results["groups"]
    for a, b in zip(whole[0], groups[0], strict=True):
        for key in ("samples", "sequences", "splits", "new_parts"):
            assert a[key] == b[key]
    for (ta, pa_), (tb, pb) in ((whole[1], groups[1]), (whole[2], groups[2])):
        assert ta.equals(tb)
        assert pa_ == pb  # the parts, byte for byte
    extended = whole[1][0]
    assert extended.num_rows == 12 + 6 - 3  # s3's three frames rebuilt, not doubled
    assert extended.column("id").to_pylist() == sorted(extended.column("id").to_pylist())


def test_manifest_writer_gives_write_manifests_bytes(tmp_path):
    rows = [
        ManifestRow.from_dict({"id": f"s/{i}", "sequence": "s", "frame": str(i), "split": "train",
                               "width": 4, "height": 3, "rgb_path": f"rgb/s/{i}.png",
                               "n_sparse": i, "density": i / 12, "rgb_sha256": "0" * 64,
                               "frame_index": i, "camera": "image_02" if i == 2 else None})
        for i in range(5)
    ]  # fmt: skip
    table = ManifestRow.to_table(rows)
    write_manifest(tmp_path / "a.parquet", table, info={"x": 1})
    with ManifestWriter(tmp_path / "b.parquet", optional=["camera"], info={"x": 1}) as w:
        w.write(table.slice(0, 2))
        w.write(table.slice(2))
    assert pq.ParquetFile(tmp_path / "b.parquet").num_row_groups == 2
    assert read_manifest(tmp_path / "a.parquet")[0].equals(read_manifest(tmp_path / "b.parquet")[0])
    with ManifestWriter(tmp_path / "c.parquet", optional=["camera"], info={"x": 1}) as w:
        w.write(table)
    assert (tmp_path / "a.parquet").read_bytes() == (tmp_path / "c.parquet").read_bytes()


def test_an_unfinished_manifest_leaves_the_old_one(tmp_path):
    rows = [ManifestRow.from_dict({"id": "s/0", "sequence": "s", "frame": "0", "width": 4,
                                   "height": 3, "rgb_path": "rgb/s/0.png", "n_sparse": 0,
                                   "density": 0.0, "rgb_sha256": "0" * 64})]  # fmt: skip
    path = tmp_path / MANIFEST_NAME
    write_manifest(path, ManifestRow.to_table(rows))
    before = path.read_bytes()
    bad = ManifestRow.to_table([ManifestRow.from_dict({**rows[0].to_dict(), "rgb_path": "../x"})])
    with pytest.raises(FormatError), ManifestWriter(path) as w:
        w.write(bad)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [MANIFEST_NAME]  # no temporary left


def test_a_staged_record_naming_another_sample_is_refused(tmp_path):
    inputs = make_inputs(tmp_path / "in", sequences=("s1",), frames=2)
    ds = tmp_path / "ds"
    build(inputs, ds)
    manifest = (ds / MANIFEST_NAME).read_bytes()
    row = ManifestRow.from_table(_table(ds).slice(0, 1))[0]
    fake = ds / STAGING / "s1" / "000001.rec"  # a record under one frame's name ...
    fake.parent.mkdir(parents=True)
    write_record(fake, row.to_dict(), None)  # ... holding the row of another (s1/000000)
    with pytest.raises(FormatError, match="corrupt staging record") as err:
        merge.merge_staged(ds, fractions={"train": 1.0}, seed=0, assignment=None, info={},
                           frames_per_part=10)  # fmt: skip
    assert "\n" not in str(err.value)
    assert (ds / MANIFEST_NAME).read_bytes() == manifest


@pytest.mark.parametrize("workers", [1, 2])
def test_recorded_output_identities_equal_the_files_read_back(tmp_path, workers):
    inputs = make_inputs(tmp_path / "in", sequences=("s1", "s2"), frames=2)
    ds = tmp_path / "ds"
    build(inputs, ds, workers=workers)
    records = list(iter_frame_records(ds))
    assert len(records) == 4
    checked = 0
    for rec in records:
        for role, rel in rec.outputs.items():
            path = ds / rel
            if role == "staged":  # merged into the manifest, then deleted
                assert not path.exists()
                continue
            assert rec.output_ids[role] == output_identity(path)
            checked += 1
    assert checked == 4 * 4  # rgb, sparse PNG, gt, confidence per frame


def _stage(ds: Path, n: int) -> None:
    """``n`` staging records of tiny frames (points included), as a build leaves them."""
    rng = np.random.default_rng(0)
    for i in range(n):
        seq, frame = f"seq{i % 17:02d}", f"{i:07d}"
        u = rng.integers(0, 64, 30).astype(np.uint16)
        v = rng.integers(0, 32, 30).astype(np.uint16)
        d = rng.uniform(1, 80, 30).astype(np.float32)
        row = {"id": f"{seq}/{frame}", "sequence": seq, "frame": frame, "width": 64,
               "height": 32, "rgb_path": f"rgb/{seq}/{frame}.png", "n_sparse": 30,
               "density": 30 / 2048, "rgb_sha256": f"{i:064x}",
               "generation_params": json.dumps({"inputs": {"rgb": f"{seq}/{frame}.png"}})}  # fmt: skip
        write_record(ds / STAGING / seq / f"{frame}.rec", row, (u, v, d))


def _merge_peak(tmp_path: Path, n: int) -> int:
    ds = tmp_path / f"ds{n}"
    _stage(ds, n)
    tracemalloc.start()
    try:
        merge.merge_staged(ds, fractions={"train": 0.8, "val": 0.1, "test": 0.1}, seed=0,
                           assignment=None, info={}, frames_per_part=100)  # fmt: skip
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    table = _table(ds)
    assert table.num_rows == n
    assert set(table.column("split").to_pylist()) <= {"train", "val", "test"}
    return peak


def test_merge_memory_grows_by_well_under_a_kilobyte_per_frame(tmp_path, monkeypatch):
    # equal row groups for both sizes, so only what is held per frame differs; the merge of
    # before (every row a ManifestRow, twice, then a dict per row for the table) held ~4 KB
    _small_groups(monkeypatch, 256)
    small, large = _merge_peak(tmp_path, 600), _merge_peak(tmp_path, 3000)
    per_frame = (large - small) / 2400
    assert per_frame < 1000, f"{per_frame:.0f} bytes per frame"


def test_rows_as_a_table_of_every_column_is_the_full_schema():
    assert ManifestRow.to_table([], every_column=True).schema.equals(FULL_SCHEMA)
    row = ManifestRow.from_dict({"id": "s/0", "sequence": "s", "frame": "0", "width": 4,
                                 "height": 3, "rgb_path": "rgb/s/0.png", "n_sparse": 0,
                                 "density": 0.0, "rgb_sha256": "0" * 64})  # fmt: skip
    assert ManifestRow.to_table([row], every_column=True).schema.equals(FULL_SCHEMA)
    assert "camera" not in ManifestRow.to_table([row]).column_names  # only what a row fills


def test_each_frame_names_its_inputs_relative_to_what_was_given(tmp_path):
    """generation_params["inputs"]: paths inside the folders given, the name of a file given
    (one calibration for every frame); made when a frame is staged from one shared record of
    what was given (issue 28), as each frame's own strings said before."""
    inputs = make_inputs(tmp_path / "in", sequences=("s1",), frames=2)
    shared = tmp_path / "one_calib.json"
    shared.write_text((inputs / "calib" / "s1" / "000000.json").read_text())
    ds = tmp_path / "ds"
    build(inputs, ds)
    row = ManifestRow.from_table(_table(ds).slice(1, 1))[0]
    assert json.loads(row.generation_params)["inputs"] == {
        "calib": "s1/000001.json", "confidence": "s1/000001_conf.png", "gt": "s1/000001.png",
        "rgb": "s1/000001.png", "sparse": "s1/000001.npy",
    }  # fmt: skip
    build(inputs, tmp_path / "ds2", calib=shared, gt=None, confidence=None)
    row = ManifestRow.from_table(_table(tmp_path / "ds2").slice(0, 1))[0]
    assert json.loads(row.generation_params)["inputs"] == {
        "calib": "one_calib.json",
        "rgb": "s1/000000.png",
        "sparse": "s1/000000.npy",
    }


def test_project_records_the_identity_of_what_it_wrote(tmp_path):
    """``project`` writes its PNG and calibration through atomic_write_bytes: the journal's
    identities (taken from the bytes written, not read back) equal the files read back, and
    a rerun finds the frame up to date."""
    sys.path.insert(0, str(Path(__file__).parent / "robustness"))
    from cli_helpers import invoke
    from corpus_builder import good_frame

    f = good_frame(tmp_path / "in")
    out = tmp_path / "out"
    args = ["project", f["cloud"], "--calib", f["calib"], "--image", f["image"], "-o", out]
    assert invoke(args).exit_code == 0
    (rec,) = iter_frame_records(out)
    assert set(rec.output_ids) == set(rec.outputs) == {"depth", "calib"}
    for role, rel in rec.outputs.items():
        assert rec.output_ids[role] == output_identity(out / rel)
    again = invoke(args)
    assert again.exit_code == 0 and "skipped existing  1" in again.output


def test_parts_that_lose_rows_keep_every_other_rows_points(tmp_path, monkeypatch):
    """Restaging some frames rewrites the sparse and points parts they were in with the
    other rows (`_kept_rows`): every row still reads the points it was staged with, and no
    part is left that no row refers to."""
    from sparsetools.io.dataset_reader import DatasetReader
    from sparsetools.pipeline.dataset.staging import POINTS_SUFFIX

    monkeypatch.setattr(merge, "POINTS_PER_PART", 2)
    ds = tmp_path / "ds"
    rng = np.random.default_rng(3)
    truth = {}

    def stage(n: int, which: range, offset: float) -> None:
        _stage(ds, n)  # the rows and sparse points (seeded: the same for a frame each time)
        for i in range(n):
            fid = f"seq{i % 17:02d}/{i:07d}"
            rec = ds / STAGING / f"{fid}.rec"
            if i not in which:
                rec.unlink()
                continue
            cloud = np.column_stack([rng.uniform(1, 9, (5, 3)) + offset, np.arange(5)])
            np.save(ds / STAGING / f"{fid}{POINTS_SUFFIX}", cloud)
            truth[fid] = cloud

    def do_merge() -> None:
        merge.merge_staged(ds, fractions={"train": 1.0}, seed=0, assignment=None, info={},
                           frames_per_part=3)  # fmt: skip

    stage(7, range(7), 0.0)
    do_merge()
    sparse_before = {fid: DatasetReader(ds).sparse_points(fid) for fid in truth}
    stage(7, range(2, 4), 100.0)  # two frames rebuilt: their parts lose a row each
    do_merge()
    reader = DatasetReader(ds)
    assert len(reader) == 7
    for fid, cloud in truth.items():
        xyz, ring = reader.points(fid)
        assert np.array_equal(xyz, cloud[:, :3]) and np.array_equal(ring, cloud[:, 3])
        for a, b in zip(reader.sparse_points(fid), sparse_before[fid], strict=True):
            assert np.array_equal(a, b)
    rows = [reader.row(i) for i in range(len(reader))]
    for kind, column in (("sparse", "sparse_parquet"), ("points", "points_parquet")):
        on_disk = {f"{kind}/{p.name}" for p in (ds / kind).glob("part-*.parquet")}
        assert on_disk == {getattr(r, column) for r in rows}


def test_the_merge_reads_each_staged_entry_twice(tmp_path, monkeypatch):
    """Once for the columns it decides on, once as its row group and points part are written
    (the points part used to read it a third time); the result is unchanged (the parts and
    manifest equal those of row groups that do not line up with the parts, above)."""
    reads = []
    real = merge.read_staged_entry

    def counted(folder, at):
        reads.append(at.id)
        return real(folder, at)

    monkeypatch.setattr(merge, "read_staged_entry", counted)
    _small_groups(monkeypatch, 4)
    src = make_inputs(tmp_path / "a", sequences=("s1", "s2", "s3"), frames=3)
    ds = tmp_path / "ds"
    build(src, ds, frames_per_part=5)
    ids = _table(ds).column("id").to_pylist()
    assert len(ids) == 9
    assert sorted(reads) == sorted(ids * 2)
    reader_parts = sorted(_parts(ds))
    assert reader_parts == [f"sparse/part-0000{i}.parquet" for i in range(2)]  # 5 + 4 frames


def test_a_record_file_swapped_during_the_merge_is_refused(tmp_path, monkeypatch):
    """The merge reads a staged record twice; a record file of an earlier version that names
    another sample (or lost its points) by the second read is refused, no manifest written."""
    ds = tmp_path / "ds"
    _stage(ds, 3)
    real = merge.read_staged
    seen = []

    def swapped(path):
        row, pts = real(path)
        seen.append(row.id)
        if len(seen) > 3:  # the second read: another sample's record now
            row = ManifestRow.from_dict({**row.to_dict(), "id": "seq00/9999999"})
        return row, pts

    monkeypatch.setattr(merge, "read_staged", swapped)
    with pytest.raises(FormatError, match="changed during the merge"):
        merge.merge_staged(ds, fractions={"train": 1.0}, seed=0, assignment=None, info={},
                           frames_per_part=100)  # fmt: skip
    assert not (ds / MANIFEST_NAME).exists()
