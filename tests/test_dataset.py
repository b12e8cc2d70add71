"""Dataset build / read / verify: exact round trips, splits by sequence, append, resume, safety."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import json
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from sparsetools.errors import FormatError, FrameError, OutputError, ParameterError
from sparsetools.io.dataset import (
    FULL_SCHEMA,
    MANIFEST_NAME,
    MANIFEST_SCHEMA,
    METADATA_VERSION_KEY,
    ManifestRow,
    check_relative_path,
    read_manifest,
    resolve_in_dataset,
)
from sparsetools.io.dataset_reader import DatasetReader
from sparsetools.io.image import read_depth_png, read_image, write_depth_png, write_image
from sparsetools.io.manifest_writer import write_manifest
from sparsetools.pipeline import Batch
from sparsetools.pipeline.dataset import (
    assign_splits,
    match_split_lines,
    parse_split_fractions,
    read_split_file,
    verify_dataset,
)


def build_dataset(out, *, progress=False, workers=1, overwrite=False, on_error="stop", **kw):
    """``pipeline.dataset.build_dataset`` with the batch options spelt out, summary as a dict."""
    from sparsetools.pipeline.dataset import build_dataset as _build

    batch = Batch(workers=workers, overwrite=overwrite, on_error=on_error, progress=progress)
    return _build(out, batch=batch, **kw).as_dict()


REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
W, H = 40, 24


def sha(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def make_inputs(
    root: Path,
    sequences=("seqA", "seqB", "seqC"),
    frames=3,
    *,
    seed=0,
    sparse_kind="npy",
    conf=True,
    calib=True,
) -> Path:
    """Per-sequence folders of rgb PNG, sparse (.npy float32 or PNG), gt PNG, conf PNG, calib JSON."""
    rng = np.random.default_rng(seed)
    for seq in sequences:
        for f in range(frames):
            key = f"{seq}/{f:06d}"
            write_image(
                root / "rgb" / f"{key}.png", rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
            )
            depth = np.where(rng.random((H, W)) < 0.1, rng.uniform(0.5, 90, (H, W)), 0).astype(
                np.float32
            )
            depth[0, 0] = 3.0  # corner pixel always valid
            if sparse_kind == "npy":
                (root / "sparse" / seq).mkdir(parents=True, exist_ok=True)
                np.save(root / "sparse" / f"{key}.npy", depth)
            else:
                write_depth_png(root / "sparse" / f"{key}.png", depth)
            write_depth_png(root / "gt" / f"{key}.png", rng.uniform(1, 80, (H, W)))
            if conf:
                c = rng.integers(0, 65536, (H, W), dtype=np.uint16)
                import cv2

                (root / "conf" / seq).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / "conf" / f"{key}_conf.png"), c)
            if calib:
                (root / "calib" / seq).mkdir(parents=True, exist_ok=True)
                K = [[50.0 + f, 0, 20.5], [0, 51.0, 12.25], [0, 0, 1]]
                (root / "calib" / f"{key}.json").write_text(
                    json.dumps(
                        {"K": K, "T_cam_from_sensor": np.eye(4).tolist(), "width": W, "height": H}
                    )
                )
    return root


def build(inputs: Path, out: Path, **kw):
    args = {
        "rgb": inputs / "rgb",
        "sparse": inputs / "sparse",
        "gt": inputs / "gt",
        "progress": False,
    }
    if (inputs / "conf").is_dir():
        args["confidence"] = inputs / "conf"
    if (inputs / "calib").is_dir():
        args["calib"] = inputs / "calib"
    args.update(kw)
    return build_dataset(out, **args)


@pytest.fixture
def inputs(tmp_path):
    return make_inputs(tmp_path / "in")


# -- round trips -------------------------------------------------------------------------------------
def test_round_trip_npy_is_bit_exact(inputs, tmp_path):
    out = tmp_path / "ds"
    summary = build(inputs, out)
    assert summary["processed"] == 9 and summary["failed"] == 0 and summary["samples"] == 9
    ds = DatasetReader(out)
    assert len(ds) == 9
    for i in range(len(ds)):
        s = ds.sample(i)
        key = s["id"]
        src = np.load(inputs / "sparse" / f"{key}.npy")
        assert s["sparse"].dtype == np.float32 and s["sparse"].tobytes() == src.tobytes()
        np.testing.assert_array_equal(s["rgb"], read_image(inputs / "rgb" / f"{key}.png"))
        np.testing.assert_array_equal(s["gt"], read_depth_png(inputs / "gt" / f"{key}.png"))
        import cv2

        c = cv2.imread(str(inputs / "conf" / f"{key}_conf.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(s["confidence"], c.astype(np.float32) / 65535)
        f = int(key[-1])
        np.testing.assert_array_equal(
            s["intrinsics"], [[50.0 + f, 0, 20.5], [0, 51.0, 12.25], [0, 0, 1]]
        )
        u, v, d = ds.sparse_points(key)
        assert u.dtype == np.uint16 and v.dtype == np.uint16 and d.dtype == np.float32
        np.testing.assert_array_equal(d, src[v, u])
        assert u.size == np.count_nonzero(src)
    # files are stored byte for byte
    m = ds.manifest.to_pylist()
    for r in m:
        assert sha(inputs / "rgb" / f"{r['id']}.png") == r["rgb_sha256"] == sha(out / r["rgb_path"])
        assert sha(inputs / "gt" / f"{r['id']}.png") == sha(out / r["gt_path"])
        assert r["density"] == r["n_sparse"] / (W * H)
        assert r["sequence"] == r["id"].split("/")[0] and r["frame"] == r["id"].split("/")[1]
        assert json.loads(r["generation_params"])["sparse_format"] == "both"
    assert verify_dataset(out).problems == ()


def test_png_sparse_input_is_copied_and_parquet_holds_decoded_values(tmp_path):
    inputs = make_inputs(tmp_path / "in", sparse_kind="png", conf=False, calib=False)
    out = tmp_path / "ds"
    build(inputs, out)
    ds = DatasetReader(out)
    for r in ds.manifest.to_pylist():
        src = inputs / "sparse" / f"{r['id']}.png"
        assert sha(src) == r["sparse_sha256"] == sha(out / r["sparse_path"])
        s = ds.sample(r["id"])
        assert s["sparse"].tobytes() == read_depth_png(src).tobytes()
        assert s["intrinsics"] is None and s["confidence"] is None


@pytest.mark.parametrize("fmt", ["png", "parquet"])
def test_single_sparse_format(inputs, tmp_path, fmt):
    out = tmp_path / "ds"
    build(inputs, out, sparse_format=fmt)
    m = read_manifest(out / MANIFEST_NAME)[0].to_pylist()
    parts = sorted((out / "sparse").glob("part-*.parquet"))
    if fmt == "png":
        assert not parts and all(r["sparse_parquet"] is None for r in m)
        ds = DatasetReader(out)
        src = np.load(inputs / "sparse" / f"{m[0]['id']}.npy")
        # PNG keeps KITTI quantisation: round(d * 256) / 256, clipped to 65535 / 256
        expect = np.where(
            src > 0, np.clip(np.rint(src.astype(np.float64) * 256), 1, 65535) / 256, 0
        )
        np.testing.assert_array_equal(ds.sample(0)["sparse"], expect.astype(np.float32))
    else:
        assert len(parts) == 1 and all(r["sparse_path"] is None for r in m)
        assert not list((out / "sparse").rglob("*.png"))
    assert verify_dataset(out).problems == ()


def test_part_files_schema_readable_by_pyarrow(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out)
    t = pq.read_table(out / "sparse" / "part-00000.parquet")
    assert t.schema.field("u").type == pa.list_(pa.uint16())
    assert t.schema.field("v").type == pa.list_(pa.uint16())
    assert t.schema.field("depth").type == pa.list_(pa.float32())
    assert (
        pq.ParquetFile(out / "sparse" / "part-00000.parquet")
        .metadata.row_group(0)
        .column(1)
        .compression
        == "ZSTD"
    )
    row = t.slice(0, 1).to_pylist()[0]
    depth = np.zeros((row["height"], row["width"]), np.float32)
    depth[row["v"], row["u"]] = row["depth"]
    src = np.load(inputs / "sparse" / f"{row['id']}.npy")
    assert depth.tobytes() == src.tobytes()


def test_manifest_readable_by_installed_dataframe_libraries(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out)
    path = out / MANIFEST_NAME
    t = pq.read_table(path)  # pyarrow always
    assert t.num_rows == 9 and t.schema.metadata[METADATA_VERSION_KEY] == b"2"
    ids = sorted(t.column("id").to_pylist())
    if importlib.util.find_spec("pandas"):
        import pandas as pd

        df = pd.read_parquet(path)
        assert sorted(df["id"]) == ids and df["n_sparse"].dtype.kind == "i"
    if importlib.util.find_spec("polars"):
        import polars as pl

        assert sorted(pl.read_parquet(path)["id"].to_list()) == ids
    if importlib.util.find_spec("duckdb"):
        import duckdb

        rows = duckdb.sql(f"SELECT id FROM read_parquet('{path}') ORDER BY id").fetchall()
        assert [r[0] for r in rows] == ids


def test_workers_give_identical_manifest(inputs, tmp_path):
    build(inputs, tmp_path / "a")
    build(inputs, tmp_path / "b", workers=2)
    ta = pq.read_table(tmp_path / "a" / MANIFEST_NAME)
    tb = pq.read_table(tmp_path / "b" / MANIFEST_NAME)
    assert ta.equals(tb)
    assert sha(tmp_path / "a/sparse/part-00000.parquet") == sha(
        tmp_path / "b/sparse/part-00000.parquet"
    )


def test_manifest_row_is_the_schema_and_round_trips_arrow(inputs, tmp_path):
    """ManifestRow's fields are MANIFEST_SCHEMA's, in order; rows -> table -> rows is exact and
    the table is what the manifest holds (same schema, same values)."""
    assert [f.name for f in dataclasses.fields(ManifestRow)] == FULL_SCHEMA.names
    empty = ManifestRow.to_table([])
    assert empty.num_rows == 0 and empty.schema.equals(MANIFEST_SCHEMA)
    out = tmp_path / "ds"
    build(inputs, out)
    table, _ = read_manifest(out / MANIFEST_NAME)
    rows = ManifestRow.from_table(table)
    assert [r.id for r in rows] == table.column("id").to_pylist()
    back = ManifestRow.to_table(rows)
    assert back.schema.equals(MANIFEST_SCHEMA)
    # a dataset that references no image is written without the reference columns (schema 2)
    from sparsetools.io.dataset import REFERENCE_COLUMNS

    on_disk = pq.read_table(out / MANIFEST_NAME).replace_schema_metadata(None)
    assert back.drop_columns(list(REFERENCE_COLUMNS)).equals(on_disk)
    assert ManifestRow.from_table(back) == rows
    for r in rows:  # a dict of JSON values (the staging record's form) and back
        assert ManifestRow.from_dict(json.loads(json.dumps(r.to_dict()))) == r
    r = rows[0]
    assert r["n_sparse"] == r.n_sparse and r.split in ("train", "val", "test")
    with pytest.raises(KeyError):
        r["no_such_column"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.split = "val"
    # a pose travels as a tuple in the row, a list in Arrow and JSON
    posed = dataclasses.replace(r, T_world_cam=tuple(float(i) for i in range(16)))
    assert ManifestRow.from_table(ManifestRow.to_table([posed])) == [posed]
    assert posed.to_dict()["T_world_cam"] == list(range(16))
    assert DatasetReader(out).row(r.id) == r


def test_build_is_a_batch_job_run_by_run_job(inputs, tmp_path):
    """The library's build_dataset is settings -> find_build_inputs -> run_job(DatasetJob)."""
    from sparsetools.pipeline.core import BatchJob, run_job
    from sparsetools.pipeline.dataset import (
        BuildSettings,
        DatasetFrameStats,
        DatasetJob,
        find_build_inputs,
    )

    settings = BuildSettings.with_splits("0.5,0.5", seed=2)
    found = find_build_inputs(
        settings, rgb=inputs / "rgb", sparse=inputs / "sparse", gt=inputs / "gt"
    )
    assert [x.id for x in found.frames] == sorted(x.id for x in found.frames)
    assert len(found.frames) == 9 and found.unmatched == {"rgb_without_sparse": 0, "without_gt": 0}
    job = DatasetJob.for_inputs(settings, found)
    assert isinstance(job, BatchJob) and job.command == "dataset build"
    assert pickle.loads(pickle.dumps(job)) == job
    summary = run_job(job, found.frames, tmp_path / "a", batch=Batch(progress=False),
                      inputs=found.roots)  # fmt: skip
    stats = job.stats(summary)
    assert all(isinstance(s, DatasetFrameStats) for s in stats) and len(stats) == 9
    reader = DatasetReader(tmp_path / "a")
    assert [s.n_sparse for s in stats] == [reader.row(x.id).n_sparse for x in found.frames]
    same = build_dataset(tmp_path / "b", rgb=inputs / "rgb", sparse=inputs / "sparse",
                         gt=inputs / "gt", split="0.5,0.5", seed=2)  # fmt: skip
    a = summary.as_dict()
    for d in (a, same):
        d.pop("seconds"), d.pop("stage_seconds"), d.pop("output")
    assert a == same
    assert pq.read_table(tmp_path / "a" / MANIFEST_NAME).equals(
        pq.read_table(tmp_path / "b" / MANIFEST_NAME)
    )


def test_build_settings_are_validated_once_and_recorded_as_before():
    from sparsetools.pipeline.dataset import BuildSettings, DatasetJob

    assert BuildSettings().split == {"train": 0.8, "val": 0.1, "test": 0.1}
    tree = BuildSettings.with_splits("tree")
    assert tree.split_from_tree and tree.split is None and tree.split_files is None
    files = BuildSettings.with_splits(None, ["a.txt", ("test", "b.txt")])
    assert not files.split_from_tree and files.split is None
    # 0.2.0 recorded every split file as str(item): its datasets resume
    assert DatasetJob(files).record()["split_files"] == ["a.txt", "('test', 'b.txt')"]
    assert DatasetJob(BuildSettings.with_splits("0.6,0.4")).record()["split"] == {
        "train": 0.6,
        "val": 0.4,
    }
    with pytest.raises(ParameterError, match="--sparse-format"):
        BuildSettings(sparse_format="tiff")
    with pytest.raises(ParameterError, match="give one of .*, not two"):
        BuildSettings.with_splits("0.5,0.5", ["a.txt"])
    with pytest.raises(ParameterError, match="sum to 1"):
        BuildSettings(split={"train": 0.5})
    with pytest.raises(ParameterError, match="sequence-from"):
        BuildSettings(sequence_from="folder")
    with pytest.raises(ParameterError, match="--source"):
        BuildSettings(source=" ")
    with pytest.raises(ParameterError, match="frames-per-part"):
        DatasetJob(BuildSettings(), frames_per_part=0)


def test_info_and_verify_are_records_with_their_own_text(inputs, tmp_path):
    from sparsetools.pipeline.dataset import dataset_info

    out = tmp_path / "ds"
    build(inputs, out, split="0.34,0.33,0.33")
    info = dataset_info(out)
    d = json.loads(json.dumps(info.to_dict()))  # JSON values only
    assert list(d) == [
        "dataset", "schema_version", "created_by", "samples", "sequences", "splits",
        "image_sizes", "sources", "with_gt", "with_confidence", "with_intrinsics", "n_sparse",
        "density_percent", "bytes", "total_bytes", "missing_files", "split_method",
        "official_split",
        "gt_methods", "referenced_files", "referenced_bytes", "missing_references",
    ]  # fmt: skip
    assert d["official_split"] is None  # fractions; an official split records its name
    # dataset build records no gt_method: counted, not printed (tests/test_gt_routes.py)
    assert d["gt_methods"] == {"unrecorded": 9} and "gt methods" not in str(info)
    assert d["splits"]["train"] == {"samples": 3, "sequences": 1, "with_gt": 3}
    assert d["image_sizes"] == {f"{W}x{H}": 9} and d["schema_version"] == 2
    assert set(d["n_sparse"]) == {"min", "median", "mean", "max"}
    lines = str(info).splitlines()
    assert lines[0].split() == ["dataset", str(out)]
    assert "with gt / confidence / intrinsics  9 / 9 / 9" in lines
    assert not any("missing files" in line for line in lines)

    report = verify_dataset(out)
    assert report.ok and str(report) == f"{out}: 9 sample(s) verified, no problem"
    assert report.to_dict() == {"dataset": str(out), "schema_version": 2, "samples": 9,
                                "inputs_changed": 0, "problems": [], "warnings": [],
                                "references": 0, "references_missing": 0,
                                "references_changed": 0}  # fmt: skip
    (out / "rgb" / "seqA" / "000000.png").unlink()
    report = verify_dataset(out)
    assert not report.ok and str(report) == "problem: seqA/000000: rgb/seqA/000000.png is missing"
    assert str(dataset_info(out)).splitlines()[-1].split() == [
        "missing", "files", "1", "(run", "'dataset", "verify')"
    ]  # fmt: skip


def test_verify_reports_the_same_whatever_its_chunk_and_threads(inputs, tmp_path, monkeypatch):
    """verify walks the manifest in chunks (memory): chunks of one row, of two and the default,
    on one thread and on three, give the same report, problems in the same order."""
    from sparsetools.pipeline.dataset import verify

    out = tmp_path / "ds"
    build(inputs, out)
    (out / "rgb" / "seqA" / "000001.png").unlink()
    (out / "sparse" / "seqB" / "000002.png").write_bytes(b"not a png")
    reports = []
    for chunk in (1, 2, verify._VERIFY_CHUNK):
        monkeypatch.setattr(verify, "_VERIFY_CHUNK", chunk)
        for threads in (1, 3):
            reports.append(verify_dataset(out, threads=threads).to_dict())
    assert len(reports[0]["problems"]) >= 2 and reports[0]["samples"] == 9
    assert all(r == reports[0] for r in reports[1:])


def test_verify_judges_inputs_by_the_last_journal_line_of_each_sample(inputs, tmp_path):
    """The build's journal may hold several lines of one sample (an interrupted run): verify
    (which streams the journal) checks the last one only, as the resume does."""
    import dataclasses

    from sparsetools.io.provenance import FRAMES_FILE, RECORD_DIR, FrameRecord

    out = tmp_path / "ds"
    build(inputs, out)
    journal = out / RECORD_DIR / FRAMES_FILE
    lines = journal.read_text().splitlines()
    rec = FrameRecord.from_line(lines[0])
    stale = dataclasses.replace(
        rec, inputs=tuple(dataclasses.replace(i, size=i.size + 1) for i in rec.inputs)
    ).to_line()
    journal.write_text("\n".join([stale, *lines]) + "\n")  # stale first: the last line wins
    assert verify_dataset(out).problems == ()
    journal.write_text("\n".join([*lines, stale]) + "\n")  # stale last: every input "changed"
    problems = verify_dataset(out).problems
    assert len(problems) == len(rec.inputs) > 0
    assert all(
        p.startswith(f"{rec.key}: input ") and "changed since the build" in p for p in problems
    )


def test_reader_split_views_and_pickling(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out, split="0.34,0.33,0.33")
    ds = DatasetReader(out)
    assert ds.splits == ["test", "train", "val"]
    total = 0
    for name in ds.splits:
        part = ds.split(name)
        assert all(r["split"] == name for r in part.manifest.to_pylist())
        assert len(part) == 3  # one sequence of 3 frames each
        assert DatasetReader(out, split=name).ids == part.ids
        total += len(part)
    assert total == len(ds)
    with pytest.raises(ParameterError, match="no split 'nope'"):
        ds.split("nope")
    clone = pickle.loads(pickle.dumps(ds.split("train")))
    a = clone.sample(1)
    b = ds.split("train").sample(1)
    assert a["id"] == b["id"] and a["sparse"].tobytes() == b["sparse"].tobytes()
    with pytest.raises(IndexError):
        ds.sample(99)
    with pytest.raises(ParameterError):
        ds.sample("no/such/id")


# -- splits -----------------------------------------------------------------------------------------
def test_assign_splits_deterministic_and_whole_sequences():
    seqs = [f"drive_{i:03d}" for i in range(20)]
    fr = {"train": 0.8, "val": 0.1, "test": 0.1}
    a = assign_splits(seqs, fr, seed=0)
    assert a == assign_splits(list(reversed(seqs)), fr, seed=0)  # order does not matter
    assert sorted(a) == sorted(seqs)
    counts = {k: list(a.values()).count(k) for k in fr}
    assert counts == {"train": 16, "val": 2, "test": 2}
    others = [assign_splits(seqs, fr, seed=s) for s in range(1, 6)]
    assert any(o != a for o in others)  # the seed matters
    # pinned sequences keep their split; new ones fill the remaining quotas
    pinned = {s: "test" for s in seqs[:3]}
    b = assign_splits(seqs, fr, seed=0, pinned=pinned)
    assert all(b[s] == "test" for s in seqs[:3])
    assert list(b.values()).count("train") == 16


def test_quota_gives_every_split_a_sequence_when_possible():
    a = assign_splits(["a", "b", "c"], {"train": 0.8, "val": 0.1, "test": 0.1}, seed=0)
    assert sorted(a.values()) == ["test", "train", "val"]
    one = assign_splits(["a"], {"train": 0.8, "val": 0.1, "test": 0.1}, seed=3)
    assert one == {"a": "train"}


def test_parse_split_fractions():
    assert parse_split_fractions("0.8,0.1,0.1") == {"train": 0.8, "val": 0.1, "test": 0.1}
    assert parse_split_fractions("0.9,0.1") == {"train": 0.9, "val": 0.1}
    assert parse_split_fractions("a=0.5,b=0.5") == {"a": 0.5, "b": 0.5}
    for bad in ("0.8,0.1", "1", "x,y,z", "0.5,0.5,0.5,-0.5", "a=0.5,b", "1.2,-0.2"):
        with pytest.raises(ParameterError):
            parse_split_fractions(bad)


def test_no_sequence_leakage_and_build_determinism(tmp_path):
    inputs = make_inputs(
        tmp_path / "in",
        sequences=[f"s{i:02d}" for i in range(12)],
        frames=2,
        conf=False,
        calib=False,
    )
    build(inputs, tmp_path / "a", seed=7)
    build(inputs, tmp_path / "b", seed=7)
    ma = read_manifest(tmp_path / "a" / MANIFEST_NAME)[0].to_pylist()
    mb = read_manifest(tmp_path / "b" / MANIFEST_NAME)[0].to_pylist()
    assert [r["split"] for r in ma] == [r["split"] for r in mb]
    seq_split = {}
    for r in ma:
        assert seq_split.setdefault(r["sequence"], r["split"]) == r["split"]
    assert assign_splits(seq_split, parse_split_fractions("0.8,0.1,0.1"), seed=7) == seq_split


def test_regex_sequence(tmp_path):
    rng = np.random.default_rng(0)
    for name in ("runA_0001", "runA_0002", "runB_0001", "runC_0001"):
        write_image(
            tmp_path / "rgb" / f"{name}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
        )
        write_depth_png(tmp_path / "sp" / f"{name}.png", np.full((H, W), 5.0))
    build_dataset(
        tmp_path / "ds",
        rgb=tmp_path / "rgb",
        sparse=tmp_path / "sp",
        sequence_from=r"regex:^(?P<sequence>run[A-Z])_",
        progress=False,
    )
    m = read_manifest(tmp_path / "ds" / MANIFEST_NAME)[0].to_pylist()
    assert [r["sequence"] for r in m] == ["runA", "runA", "runB", "runC"]
    assert len({r["split"] for r in m if r["sequence"] == "runA"}) == 1
    with pytest.raises(ParameterError, match="does not match"):
        build_dataset(
            tmp_path / "ds2",
            rgb=tmp_path / "rgb",
            sparse=tmp_path / "sp",
            sequence_from="regex:^zzz",
            progress=False,
        )
    # flat folder with 'parent': one sequence named after the folder
    build_dataset(tmp_path / "ds3", rgb=tmp_path / "rgb", sparse=tmp_path / "sp", progress=False)
    assert {
        r["sequence"] for r in read_manifest(tmp_path / "ds3" / MANIFEST_NAME)[0].to_pylist()
    } == {"rgb"}


def make_kitti_raw_like(root: Path) -> Path:
    rng = np.random.default_rng(2)
    for drive in ("2011_09_26_drive_0001_sync", "2011_09_26_drive_0002_sync"):
        for cam in ("image_02", "image_03"):
            for f in (5, 6, 7):
                key = f"2011_09_26/{drive}/{cam}/data/{f:010d}"
                write_image(
                    root / "rgb" / f"{key}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
                )
                write_depth_png(root / "sparse" / f"{key}.png", np.full((H, W), 2.0 + f))
    return root


def test_eigen_split_files(tmp_path):
    root = make_kitti_raw_like(tmp_path / "raw")
    (tmp_path / "eigen_train_files.txt").write_text(
        "2011_09_26/2011_09_26_drive_0001_sync 0000000005 l\n"
        "2011_09_26/2011_09_26_drive_0001_sync 0000000006 r\n"
        "# a comment\n\n"
        "2011_09_26/2011_09_26_drive_0009_sync 0000000005 l\n"  # not present
    )
    (tmp_path / "test.txt").write_text("2011_09_26/2011_09_26_drive_0002_sync 7 l\n")
    summary = build_dataset(
        tmp_path / "ds",
        rgb=root / "rgb",
        sparse=root / "sparse",
        progress=False,
        split_files=[str(tmp_path / "eigen_train_files.txt"), ("test", str(tmp_path / "test.txt"))],
    )
    m = {r["id"]: r["split"] for r in read_manifest(tmp_path / "ds" / MANIFEST_NAME)[0].to_pylist()}
    assert m == {
        "2011_09_26/2011_09_26_drive_0001_sync/image_02/data/0000000005": "train",
        "2011_09_26/2011_09_26_drive_0001_sync/image_03/data/0000000006": "train",
        "2011_09_26/2011_09_26_drive_0002_sync/image_02/data/0000000007": "test",
    }
    assert summary["unmatched"]["not_in_split_files"] == 12 - 3
    info = DatasetReader(tmp_path / "ds").info
    assert info["split"]["method"] == "split-file" and info["split"]["missing"] == 1
    # a frame listed in two splits is an error
    (tmp_path / "val.txt").write_text("2011_09_26/2011_09_26_drive_0002_sync 0000000007 l\n")
    with pytest.raises(ParameterError, match="two splits"):
        build_dataset(
            tmp_path / "ds2",
            rgb=root / "rgb",
            sparse=root / "sparse",
            progress=False,
            split_files=[str(tmp_path / "test.txt"), str(tmp_path / "val.txt")],
        )
    with pytest.raises(ParameterError, match="NAME=PATH"):
        build_dataset(
            tmp_path / "ds3",
            rgb=root / "rgb",
            sparse=root / "sparse",
            progress=False,
            split_files=[str(tmp_path / "eigen_train_files.txt").replace("eigen_train_files", "x")],
        )


def test_match_split_lines_rules(tmp_path):
    samples = {
        "d1/image_02/0000000005": "d1/image_02",
        "d1/image_03/0000000005": "d1/image_03",
        "flat_0005": "seq",
        "other/0000000005": "other",
    }
    matches, missing = match_split_lines(
        [("2011/d1", "5", "l"), ("x/d1", "0000000005"), ("flat_0005",), ("seq", "5"), ("d9", "5")],
        samples,
    )
    assert matches["2011/d1 5 l"] == ["d1/image_02/0000000005"]
    assert sorted(matches["x/d1 0000000005"]) == [
        "d1/image_02/0000000005",
        "d1/image_03/0000000005",
    ]
    assert matches["flat_0005"] == ["flat_0005"]
    assert matches["seq 5"] == ["flat_0005"]
    assert missing == 1
    bad = tmp_path / "bad.txt"
    bad.write_text("a b c d\n")
    with pytest.raises(ParameterError, match="bad.txt:1"):
        read_split_file(bad)
    bad.write_text("drive notanumber l\n")
    with pytest.raises(ParameterError, match="not a number"):
        read_split_file(bad)


# -- append and resume ----------------------------------------------------------------------------------
def test_append_keeps_rows_and_sequence_splits(tmp_path):
    first = make_inputs(tmp_path / "in1", sequences=("s1", "s2", "s3", "s4"), frames=2)
    out = tmp_path / "ds"
    build(first, out)
    before = {r["id"]: r for r in read_manifest(out / MANIFEST_NAME)[0].to_pylist()}
    # new frames: two more of an existing sequence, one new sequence
    second = make_inputs(tmp_path / "in2", sequences=("s2", "s9"), frames=4, seed=5)
    for seq in ("s2",):
        for f in range(2):  # drop the frames that already exist
            for sub, ext in (
                ("rgb", ".png"),
                ("sparse", ".npy"),
                ("gt", ".png"),
                ("calib", ".json"),
            ):
                (second / sub / seq / f"{f:06d}{ext}").unlink()
            (second / "conf" / seq / f"{f:06d}_conf.png").unlink()
    summary = build(second, out)
    assert summary["processed"] == 6 and summary["samples"] == 14
    after = {r["id"]: r for r in read_manifest(out / MANIFEST_NAME)[0].to_pylist()}
    for k, r in before.items():
        same = {c: r[c] for c in r if c not in ("sparse_parquet", "sparse_row")}
        assert same == {c: after[k][c] for c in same}
    assert after["s2/000002"]["split"] == after["s2/000000"]["split"]
    assert after["s2/000003"]["split"] == before["s2/000000"]["split"]
    assert len({after[f"s9/{i:06d}"]["split"] for i in range(4)}) == 1
    assert verify_dataset(out).problems == ()
    # a second run with the same inputs does nothing
    again = build(second, out)
    assert again["processed"] == 0 and again["skipped_existing"] == 6 and again["samples"] == 14
    ds = DatasetReader(out)
    src = np.load(first / "sparse" / "s1/000001.npy")
    assert ds.sample("s1/000001")["sparse"].tobytes() == src.tobytes()


def test_overwrite_rebuilds_given_frames_and_rewrites_parts(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out)
    new = np.zeros((H, W), np.float32)
    new[3, 4] = 42.0
    np.save(inputs / "sparse" / "seqA/000001.npy", new)
    summary = build(inputs, out, overwrite=True)
    assert summary["processed"] == 9
    parts = sorted(p.name for p in (out / "sparse").glob("part-*.parquet"))
    assert parts == ["part-00001.parquet"]  # the old part is replaced and removed
    ds = DatasetReader(out)
    assert ds.sample("seqA/000001")["sparse"].tobytes() == new.tobytes()
    assert ds.row("seqA/000001").n_sparse == 1
    assert verify_dataset(out).problems == ()


def test_overwrite_keeps_only_this_runs_frames(tmp_path):
    inputs = make_inputs(tmp_path / "in", sequences=("a", "b"), frames=2, conf=False, calib=False)
    out = tmp_path / "ds"
    build(inputs, out)
    for sub in ("rgb", "sparse", "gt"):
        shutil.rmtree(inputs / sub / "b")
    np.save(inputs / "sparse" / "a/000000.npy", np.full((H, W), 7.5, np.float32))
    summary = build(inputs, out, overwrite=True)
    # --overwrite replaces the folder's results: the frames of the earlier run that this run
    # does not make (sequence b) are removed, rows and files, so no settings are mixed.
    assert summary["removed_stale"] > 0
    ds = DatasetReader(out)
    assert len(ds) == 2 and sorted(ds.manifest.column("id").to_pylist()) == ["a/000000", "a/000001"]
    assert float(ds.sample("a/000000")["sparse"][5, 5]) == 7.5
    src = np.load(tmp_path / "in" / "sparse" / "a/000001.npy")
    assert ds.sample("a/000001")["sparse"].tobytes() == src.tobytes()
    assert not list((out / "rgb").rglob("b/*"))
    assert verify_dataset(out).problems == ()
    assert len(list((out / "sparse").glob("part-*.parquet"))) == 1


def test_resume_after_interrupted_run(inputs, tmp_path):
    out = tmp_path / "ds"
    bad = inputs / "rgb" / "seqC" / "000002.png"
    good = bad.read_bytes()
    bad.write_bytes(good[:60])  # truncated: the last frame fails, the others are staged
    with pytest.raises(FrameError, match="seqC/000002"):
        build(inputs, out)
    assert not (out / MANIFEST_NAME).exists()
    from sparsetools.pipeline.dataset.staged import latest_entries

    assert len(latest_entries(out / ".staging")) == 8  # staged: one pack entry per frame
    assert not list((out / ".staging").rglob("*.rec"))
    bad.write_bytes(good)
    summary = build(inputs, out)
    assert (
        summary["processed"] == 1 and summary["skipped_existing"] == 8 and summary["samples"] == 9
    )
    assert not (out / ".staging").exists()
    assert verify_dataset(out).problems == ()


@pytest.mark.parametrize("earlier", ["merged", "staged only"])
def test_a_frame_that_fails_on_a_rerun_leaves_the_manifest(inputs, tmp_path, earlier):
    """A rerun holds what a fresh run would: a frame whose input broke since it was built
    (its row merged, or only staged by a run interrupted before the merge) fails and is not
    in the manifest; its stale row or staged entry never stands for it."""
    out = tmp_path / "ds"
    last = inputs / "rgb" / "seqC" / "000002.png"
    last_bytes = last.read_bytes()
    if earlier == "staged only":
        last.write_bytes(last_bytes[:60])  # the first run stops there, before its merge
        with pytest.raises(FrameError):
            build(inputs, out)
        assert not (out / MANIFEST_NAME).exists()
        last.write_bytes(last_bytes)
    else:
        build(inputs, out)
    broken = inputs / "rgb" / "seqA" / "000000.png"
    good = broken.read_bytes()
    broken.write_bytes(good[:60])
    summary = build(inputs, out, on_error="skip")
    assert summary["failed"] == 1 and list(summary["failures"]) == ["seqA/000000"]
    assert summary["samples"] == 8
    ids = DatasetReader(out).manifest.column("id").to_pylist()
    assert "seqA/000000" not in ids and len(ids) == 8
    assert verify_dataset(out).problems == ()
    broken.write_bytes(good)  # mended: the frame is built again and comes back
    summary = build(inputs, out, on_error="skip")
    assert summary["processed"] == 1 and summary["failed"] == 0 and summary["samples"] == 9
    ds = DatasetReader(out)
    assert ds.row("seqA/000000").rgb_sha256 == hashlib.sha256(good).hexdigest()
    assert verify_dataset(out).problems == ()


def test_on_error_skip_writes_the_good_frames(inputs, tmp_path):
    (inputs / "sparse" / "seqB" / "000001.npy").write_bytes(b"not numpy")
    summary = build(inputs, tmp_path / "ds", on_error="skip")
    assert summary["failed"] == 1 and "seqB/000001" in summary["failures"]
    assert summary["samples"] == 8
    assert verify_dataset(tmp_path / "ds").problems == ()


def test_link_mode_never_lets_the_dataset_alter_an_input(inputs, tmp_path):
    from sparsetools.pipeline.dataset.staging import _clone

    out = tmp_path / "ds"
    src = inputs / "rgb" / "seqA" / "000000.png"
    os.chmod(src, 0o444)
    before = (src.read_bytes(), os.stat(src).st_mode, os.stat(src).st_nlink)
    summary = build(inputs, out, link=True, sparse_format="parquet")
    dst = out / "rgb" / "seqA" / "000000.png"
    # reflinks where the file system has them (btrfs, XFS), plain copies elsewhere (ext4)
    probe = tmp_path / "probe"
    reflinks = _clone(str(src), probe)
    assert summary["linked"] == (27 if reflinks else 0)  # rgb, gt, confidence of 9 frames
    assert not dst.is_symlink() and os.stat(src).st_ino != os.stat(dst).st_ino
    assert dst.read_bytes() == before[0]
    os.chmod(dst, 0o600)
    dst.write_bytes(b"changed in the dataset")
    assert (src.read_bytes(), os.stat(src).st_mode, os.stat(src).st_nlink) == before
    os.chmod(src, 0o644)


# -- verify -----------------------------------------------------------------------------------------------
def test_verify_catches_truncated_png_changed_and_missing_files(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out)
    assert verify_dataset(out).problems == ()
    png = out / "sparse" / "seqA" / "000000.png"
    png.write_bytes(png.read_bytes()[:100])
    rgb = out / "rgb" / "seqB" / "000001.png"
    img = read_image(rgb)
    img[0, 0] ^= 1
    write_image(rgb, img)  # still a valid PNG, different content
    (out / "gt" / "seqC" / "000002.png").unlink()
    problems = verify_dataset(out).problems
    assert any("seqA/000000" in p and "decoded" in p for p in problems)
    assert any("seqB/000001" in p and "changed" in p for p in problems)
    assert any("seqC/000002" in p and "missing" in p for p in problems)
    assert len(verify_dataset(out, check_hashes=False, threads=2).problems) == len(problems) - 2


def test_verify_catches_changed_points_and_size_mismatch(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out, sparse_format="parquet")
    part = out / "sparse" / "part-00000.parquet"
    t = pq.read_table(part)
    rows = t.to_pylist()
    rows[2]["depth"][0] += 1.0
    pq.write_table(pa.Table.from_pylist(rows, schema=t.schema), part)
    write_image(out / "rgb" / "seqA" / "000001.png", np.zeros((H + 1, W, 3), np.uint8))
    problems = verify_dataset(out).problems
    assert any(rows[2]["id"] in p and "points sha256" in p for p in problems)
    assert any("seqA/000001" in p and f"{W}x{H + 1}" in p for p in problems)


# -- safety ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "bad",
    [
        "",
        "/etc/passwd",
        "../x.png",
        "rgb/../../x.png",
        "rgb\\x.png",
        "C:/x.png",
        "rgb//x.png",
        "./rgb/x.png",
        "rgb/x\x00.png",
    ],
)
def test_check_relative_path_rejects(bad):
    with pytest.raises(FormatError):
        check_relative_path(bad)


def test_path_traversal_in_manifest_is_rejected(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out)
    table, _info = read_manifest(out / MANIFEST_NAME)
    rows = table.to_pylist()
    rows[0]["gt_path"] = "../../secret.png"
    evil = pa.Table.from_pylist(rows, schema=table.schema).replace_schema_metadata(
        table.schema.metadata
    )
    with pytest.raises(FormatError, match="'..'"):
        write_manifest(out / "other.parquet", evil)  # the writer refuses
    pq.write_table(evil, out / MANIFEST_NAME)  # written behind our back
    with pytest.raises(FormatError, match="not a plain relative path"):
        DatasetReader(out)
    with pytest.raises(FormatError):
        verify_dataset(out)


def test_symlink_out_of_dataset_is_rejected(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out)
    secret = tmp_path / "secret.png"
    shutil.copy(out / "rgb" / "seqA" / "000000.png", secret)
    target = out / "rgb" / "seqA" / "000000.png"
    target.unlink()
    target.symlink_to(secret)
    with pytest.raises(FormatError, match="outside the dataset"):
        resolve_in_dataset(out, "rgb/seqA/000000.png")
    with pytest.raises(FormatError, match="outside the dataset"):
        DatasetReader(out).sample("seqA/000000")
    assert any("outside the dataset" in p for p in verify_dataset(out).problems)


def test_schema_version_checks(inputs, tmp_path):
    out = tmp_path / "ds"
    build(inputs, out)
    t = pq.read_table(out / MANIFEST_NAME)
    pq.write_table(t.replace_schema_metadata({METADATA_VERSION_KEY: b"99"}), out / "newer.parquet")
    with pytest.raises(FormatError, match="newer"):
        read_manifest(out / "newer.parquet")
    pq.write_table(t.replace_schema_metadata({}), out / "plain.parquet")
    with pytest.raises(FormatError, match="schema version"):
        read_manifest(out / "plain.parquet")
    with pytest.raises(FormatError, match="no such manifest"):
        DatasetReader(tmp_path)


# -- bad input ---------------------------------------------------------------------------------------------
def test_bad_inputs(inputs, tmp_path):
    with pytest.raises(ParameterError, match="no frame has all its inputs"):
        build_dataset(
            tmp_path / "x",
            rgb=inputs / "rgb",
            sparse=inputs / "gt" / "seqA" / "000000.png",
            progress=False,
        )
    with pytest.raises(ParameterError, match="--sparse-format"):
        build(inputs, tmp_path / "x", sparse_format="tiff")
    with pytest.raises(ParameterError, match="give one of .*, not two"):
        build(inputs, tmp_path / "x", split="0.5,0.5", split_files=["a"])
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="not a sparsetools dataset"):
        build(inputs, busy)
    assert (busy / "notes.txt").read_text() == "mine"
    with pytest.raises(OutputError, match="inside the input"):
        build(inputs, inputs / "rgb" / "ds")
    build(inputs, tmp_path / "ds")
    with pytest.raises(OutputError, match="inside the dataset"):
        build(inputs, tmp_path / "ds", gt=tmp_path / "ds" / "gt")
    write_depth_png(inputs / "sparse" / "seqA" / "000000.png", np.ones((H, W + 2)))
    (inputs / "sparse" / "seqA" / "000000.npy").unlink()
    with pytest.raises(FrameError, match=f"{W + 2}x{H}"):
        build(inputs, tmp_path / "y")
    assert not (tmp_path / "y" / MANIFEST_NAME).exists()


def test_calibration_size_mismatch(inputs, tmp_path):
    calib = inputs / "calib" / "seqA" / "000000.json"
    d = json.loads(calib.read_text())
    d["width"] = 100
    calib.write_text(json.dumps(d))
    with pytest.raises(FrameError, match="calibration is for 100x"):
        build(inputs, tmp_path / "ds")


def test_sparse_points_table_input(inputs, tmp_path):
    rows = []
    for p in sorted((inputs / "sparse").rglob("*.npy")):
        d = np.load(p)
        v, u = np.nonzero(d)
        key = p.relative_to(inputs / "sparse").with_suffix("").as_posix()
        rows.append(
            {
                "id": key,
                "u": u.astype(np.uint16),
                "v": v.astype(np.uint16),
                "depth": d[v, u],
                "height": H,
                "width": W,
            }
        )
    table = pa.table(
        {
            "id": [r["id"] for r in rows],
            "u": pa.array([r["u"] for r in rows], type=pa.list_(pa.uint16())),
            "v": pa.array([r["v"] for r in rows], type=pa.list_(pa.uint16())),
            "depth": pa.array([r["depth"] for r in rows], type=pa.list_(pa.float32())),
            "height": [H] * len(rows),
            "width": [W] * len(rows),
        }
    )
    pq.write_table(table, tmp_path / "sparse.parquet")
    build(inputs, tmp_path / "ds", sparse=tmp_path / "sparse.parquet")
    ds = DatasetReader(tmp_path / "ds")
    for r in rows:
        src = np.load(inputs / "sparse" / f"{r['id']}.npy")
        assert ds.sample(r["id"])["sparse"].tobytes() == src.tobytes()


# -- real data -----------------------------------------------------------------------------------------------
@pytest.mark.real
def test_real_kitti_depth_frames(tmp_path):
    src = REAL / "kitti-depth-gt-metric3d"
    if not src.is_dir():
        pytest.skip(f"real data not present at {REAL}")
    out = tmp_path / "ds"
    build_dataset(
        out,
        rgb=src / "rgb",
        sparse=src / "depth",
        gt=src / "depth",
        calib=REAL / "kitti-raw-calib-2011_09_26",
        source="lidar-accumulated",
        progress=False,
    )
    ds = DatasetReader(out)
    assert len(ds) == 3
    s = ds.sample("0000000005")
    gt = read_depth_png(src / "depth" / "0000000005.png")
    assert s["rgb"].shape == (375, 1242, 3)
    assert s["sparse"].tobytes() == gt.tobytes()
    assert s["intrinsics"][0, 0] == pytest.approx(721.5377)
    r = ds.row("0000000005")
    assert r.sparse_sha256 == sha(src / "depth" / "0000000005.png")
    assert 0.19 < r.density < 0.21  # README: ~19.5-20.6 % valid
    assert verify_dataset(out).problems == ()


# -- sample data: project -> dataset build -> reader ---------------------------------------------------------
SAMPLE = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"


def test_dataset_from_sample_data_is_readable(tmp_path):
    """``project --format parquet`` output (sparse.parquet + calib/) feeds the build directly."""
    from click.testing import CliRunner

    from sparsetools.cli.main import cli

    lidar = tmp_path / "lidar"
    res = CliRunner().invoke(
        cli,
        [
            "project",
            str(SAMPLE / "velodyne"),
            "--calib",
            str(SAMPLE / "calib"),
            "--image",
            str(SAMPLE / "image_2"),
            "-o",
            str(lidar),
            "--format",
            "parquet",
        ],
    )
    assert res.exit_code == 0, res.output
    out = tmp_path / "ds"
    summary = build_dataset(
        out,
        rgb=SAMPLE / "image_2",
        sparse=lidar,
        gt=SAMPLE / "depth_gt",
        calib=lidar / "calib",
        progress=False,
    )
    assert summary["samples"] == 3 and summary["splits"] == {"train": 3}  # one sequence
    projected = {r["frame"]: r for r in pq.read_table(lidar / "sparse.parquet").to_pylist()}
    ds = DatasetReader(out).split("train")
    for i in range(len(ds)):
        s = ds[i]
        p = projected[s["id"]]
        h, w = s["sparse"].shape
        expect = np.zeros((h, w), np.float32)
        expect[p["v"], p["u"]] = np.asarray(p["depth"], np.float32)
        assert s["sparse"].tobytes() == expect.tobytes()
        assert s["rgb"].shape == (h, w, 3) and s["gt"].shape == (h, w)
        np.testing.assert_allclose(
            s["intrinsics"][[0, 1, 0, 1], [0, 1, 2, 2]], [p["fx"], p["fy"], p["cx"], p["cy"]]
        )
        # LiDAR returns agree with the dense ground truth where both exist
        both = (s["sparse"] > 0) & (s["gt"] > 0)
        assert both.sum() > 1000
        assert np.median(np.abs(s["sparse"][both] - s["gt"][both])) < 0.1
    assert verify_dataset(out).problems == ()


def test_png_and_parquet_agree_at_the_range_limits(tmp_path):
    """Depths below 1/256 m and above 256 m are clipped in the PNG; verify accepts that."""
    rng = np.random.default_rng(9)
    write_image(tmp_path / "rgb" / "f.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    d = np.zeros((H, W), np.float32)
    d[0, :5] = [0.001, 1 / 512, 255.99, 300.0, 12.3456]
    (tmp_path / "sp").mkdir()
    np.save(tmp_path / "sp" / "f.npy", d)
    summary = build_dataset(
        tmp_path / "ds", rgb=tmp_path / "rgb", sparse=tmp_path / "sp", progress=False
    )
    assert summary["samples"] == 1
    r = DatasetReader(tmp_path / "ds").row("f")
    # 0.001 m and 1/512 m round to 0 (< 1) and 300 m to > 65535: three clipped values
    assert json.loads(r.generation_params)["png_clipped"] == 3
    assert DatasetReader(tmp_path / "ds").sample("f")["sparse"].tobytes() == d.tobytes()
    assert verify_dataset(tmp_path / "ds").problems == ()
    # a PNG that really differs from the points is reported
    write_depth_png(tmp_path / "ds" / "sparse" / "f.png", np.where(d > 0, d + 1, 0))
    problems = verify_dataset(tmp_path / "ds", check_hashes=False).problems
    assert problems == ("f: sparse/f.png and sparse/part-00000.parquet disagree",)
