"""``dataset build`` stages each frame as an entry of a per-process pack (pipeline/dataset/
staged.py): round trips, the later of two entries, cut-short and edited packs, an entry that
names another sample, and folders staged by earlier versions (a file per frame)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from sparsetools.errors import FormatError, FrameError, SparsetoolsError
from sparsetools.io.dataset import MANIFEST_NAME, read_manifest
from sparsetools.io.provenance import RECORD_DIR
from sparsetools.pipeline.dataset import verify_dataset
from sparsetools.pipeline.dataset.staged import (
    append_staged,
    decode_record,
    encode_record,
    latest_entries,
    read_staged_entry,
    scan_packs,
    write_record,
)
from test_dataset import build, make_inputs


def _record(i: int, n: int = 3, fid: str | None = None) -> bytes:
    pts = (np.arange(n, dtype=np.uint16), np.arange(n, dtype=np.uint16) + 1, np.full(n, i, "f4"))
    return encode_record({"id": fid or f"s/{i:06d}", "width": 4}, pts)


# -- packs alone -----------------------------------------------------------------------------------
def test_entries_read_back_where_append_said(tmp_path):
    staging = tmp_path / ".staging"  # made by the first append
    records = [_record(i, n=i) for i in range(5)]
    ats = [append_staged(staging, f"s/{i:06d}", r) for i, r in enumerate(records)]
    assert len({at.pack for at in ats}) == 1, "one pack per process"
    assert list(scan_packs(staging)) == ats
    for at, r in zip(ats, records, strict=True):
        assert read_staged_entry(staging, at) == r
        row, pts = decode_record(read_staged_entry(staging, at), "x")
        assert row["id"] == at.id and len(pts[2]) == len(pts[0]) and pts[2].dtype == np.float32
    assert latest_entries(staging) == {at.id: at for at in ats}


def test_the_later_entry_of_a_sample_counts(tmp_path):
    staging = tmp_path / ".staging"
    first = append_staged(staging, "s/000000", _record(0))
    other = append_staged(staging, "s/000001", _record(1))
    again = append_staged(staging, "s/000000", _record(7, fid="s/000000"))
    assert again.appended_ns >= first.appended_ns
    assert latest_entries(staging) == {"s/000000": again, "s/000001": other}
    assert decode_record(read_staged_entry(staging, again), "x")[1][2][0] == 7


def test_a_cut_short_last_entry_is_not_an_entry(tmp_path):
    staging = tmp_path / ".staging"
    first = append_staged(staging, "a", _record(0))
    second = append_staged(staging, "b", _record(1, n=50))
    with open(staging / first.pack, "r+b") as fh:
        fh.truncate(second.offset + 60)  # an append interrupted half-way
    assert list(scan_packs(staging)) == [first]
    with pytest.raises(FormatError, match="corrupt staging pack"):
        read_staged_entry(staging, second)


def test_an_edited_entry_is_refused_and_garbage_is_named(tmp_path):
    staging = tmp_path / ".staging"
    at = append_staged(staging, "a", _record(0))
    pack = staging / at.pack
    data = bytearray(pack.read_bytes())
    data[-1] ^= 0xFF  # one bit of a point's depth
    pack.write_bytes(bytes(data))
    with pytest.raises(FormatError) as exc:
        read_staged_entry(staging, at)
    assert "does not match its digest" in str(exc.value) and "\n" not in str(exc.value)
    pack.write_bytes(bytes(data) + b"not an entry at all, but long enough to hold a prefix")
    with pytest.raises(FormatError, match="no entry at byte"):
        list(scan_packs(staging))


def test_a_pack_that_is_a_link_is_never_followed(tmp_path):
    staging = tmp_path / ".staging"
    staging.mkdir()
    outside = tmp_path / "outside.bin"
    outside.write_bytes(b"anything")
    (staging / "planted.pack").symlink_to(outside)
    with pytest.raises(FormatError, match="corrupt staging pack"):
        list(scan_packs(staging))
    assert outside.read_bytes() == b"anything"


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX")
def test_a_forked_child_appends_to_a_pack_of_its_own(tmp_path):
    staging = tmp_path / ".staging"
    mine = append_staged(staging, "a", _record(0))
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.write(w, append_staged(staging, "a", _record(1, fid="a")).pack.encode())
        finally:
            os._exit(0)
    os.close(w)
    theirs = os.read(r, 200).decode()
    os.close(r)
    os.waitpid(pid, 0)
    assert theirs and theirs != mine.pack
    assert append_staged(staging, "b", _record(2)).pack == mine.pack
    assert latest_entries(staging)["a"].pack == theirs  # the child's entry is the later one


# -- a build's packs --------------------------------------------------------------------------------
def _interrupted(tmp_path):
    """A build stopped by its last frame: 8 frames staged, none merged."""
    inputs = make_inputs(tmp_path / "in")
    out = tmp_path / "ds"
    bad = inputs / "rgb" / "seqC" / "000002.png"
    good = bad.read_bytes()
    bad.write_bytes(good[:60])
    with pytest.raises(FrameError):
        build(inputs, out)
    bad.write_bytes(good)
    return inputs, out


def _journal(out: Path) -> list[dict]:
    return [json.loads(x) for x in (out / RECORD_DIR / "frames.jsonl").read_text().splitlines()]


def _manifest_rows(out: Path) -> list[dict]:
    table = read_manifest(out / MANIFEST_NAME)[0]
    return sorted(table.to_pylist(), key=lambda r: r["id"])


def test_a_resumed_build_merges_the_staged_entries_as_an_uninterrupted_one(tmp_path):
    inputs, out = _interrupted(tmp_path)
    staged = {f"seq{s}/{f:06d}" for s in "ABC" for f in range(3)} - {"seqC/000002"}
    assert {r["key"] for r in _journal(out)} == staged == set(latest_entries(out / ".staging"))
    assert not list((out / ".staging").rglob("*.rec"))
    summary = build(inputs, out)
    assert summary["processed"] == 1 and summary["skipped_existing"] == 8
    once = tmp_path / "once"
    build(inputs, once)
    assert _manifest_rows(out) == _manifest_rows(once)
    assert not (out / ".staging").exists()
    assert verify_dataset(out).problems == ()


def test_a_frame_staged_again_is_merged_from_its_new_entry(tmp_path):
    inputs, out = _interrupted(tmp_path)
    src = inputs / "sparse" / "seqA" / "000001.npy"
    depth = np.load(src)
    depth[1, 1] = 42.0
    np.save(src, depth)  # changed: the frame is staged again, its old entry stays behind
    summary = build(inputs, out)
    assert summary["recomputed"] == 1
    once = tmp_path / "once"
    build(inputs, once)
    assert _manifest_rows(out) == _manifest_rows(once)


def test_an_entry_edited_between_runs_is_refused_then_rebuilt(tmp_path):
    inputs, out = _interrupted(tmp_path)
    (pack,) = (out / ".staging").glob("*.pack")
    data = bytearray(pack.read_bytes())
    data[-10] ^= 0x01  # inside the last entry's points
    pack.write_bytes(bytes(data))
    with pytest.raises(SparsetoolsError) as exc:
        build(inputs, out)
    msg = str(exc.value)
    assert "corrupt staging pack" in msg and "delete it and rerun" in msg and "\n" not in msg
    assert not (out / MANIFEST_NAME).exists()
    shutil.rmtree(out / ".staging")  # as the message says: the frames are staged again
    summary = build(inputs, out)
    assert summary["samples"] == 9 and verify_dataset(out).problems == ()


def test_an_entry_naming_another_sample_is_refused(tmp_path):
    inputs, out = _interrupted(tmp_path)
    staging = out / ".staging"
    victim = latest_entries(staging)["seqA/000001"]
    record = read_staged_entry(staging, victim)  # seqA/000001's row ...
    append_staged(staging, "seqA/000000", record)  # ... appended later, as seqA/000000's
    with pytest.raises(SparsetoolsError, match="corrupt staging record .*names sample"):
        build(inputs, out)
    assert not (out / MANIFEST_NAME).exists()


def test_a_folder_staged_a_file_per_frame_still_resumes(tmp_path):
    """What an earlier version leaves after an interruption: `.staging/<id>.rec` files and
    journal records without a pack entry; the next build merges them without restaging."""
    inputs, out = _interrupted(tmp_path)
    staging = out / ".staging"
    for fid, at in latest_entries(staging).items():
        row, pts = decode_record(read_staged_entry(staging, at), "x")
        write_record(staging / f"{fid}.rec", row, pts)
    for p in staging.glob("*.pack"):
        p.unlink()
    summary = build(inputs, out)
    assert summary["processed"] == 1 and summary["skipped_existing"] == 8
    once = tmp_path / "once"
    build(inputs, once)
    assert _manifest_rows(out) == _manifest_rows(once)
    assert verify_dataset(out).problems == ()


def test_overwrite_after_an_interruption_keeps_only_the_frames_it_is_given(tmp_path):
    inputs, out = _interrupted(tmp_path)
    sub = tmp_path / "sub"
    for kind in ("rgb", "sparse", "gt", "conf", "calib"):
        shutil.copytree(inputs / kind / "seqA", sub / kind / "seqA")
    summary = build(sub, out, overwrite=True)
    assert summary["samples"] == 3
    ids = read_manifest(out / MANIFEST_NAME)[0].column("id").to_pylist()
    assert sorted(ids) == ["seqA/000000", "seqA/000001", "seqA/000002"]
    assert verify_dataset(out).problems == ()
    once = tmp_path / "once"
    build(sub, once)
    assert _manifest_rows(out) == _manifest_rows(once)


def test_parallel_workers_write_packs_of_their_own_and_the_same_dataset(tmp_path):
    inputs = make_inputs(tmp_path / "in", sequences=("a", "b", "c", "d"), frames=4)
    one, two = tmp_path / "one", tmp_path / "two"
    build(inputs, one)
    build(inputs, two, workers=2)
    assert (one / MANIFEST_NAME).read_bytes() == (two / MANIFEST_NAME).read_bytes()
    parts = sorted(p.name for p in (one / "sparse").glob("part-*.parquet"))
    assert parts and all(
        (one / "sparse" / n).read_bytes() == (two / "sparse" / n).read_bytes() for n in parts
    )


def test_a_staging_folder_that_is_a_link_is_refused_and_nothing_outside_is_touched(tmp_path):
    inputs = make_inputs(tmp_path / "in")
    out = tmp_path / "ds"
    build(inputs, out)
    outside = tmp_path / "outside"
    outside.mkdir()
    victim = outside / "victim.pack"
    victim.write_bytes(b"not a pack of this dataset")
    (out / ".staging").symlink_to(outside)
    for overwrite in (True, False):
        with pytest.raises(SparsetoolsError, match="symbolic link"):
            build(inputs, out, overwrite=overwrite)
        assert victim.read_bytes() == b"not a pack of this dataset"


def test_an_earlier_versions_record_that_is_a_link_is_not_followed(tmp_path):
    # a record file of a frame this run does not build (no output check of the runner's covers
    # it): the merge reads it, and must not through a link to a record made elsewhere
    inputs, out = _interrupted(tmp_path)
    staging = out / ".staging"
    at = latest_entries(staging)["seqA/000000"]
    row, pts = decode_record(read_staged_entry(staging, at), "x")
    row = {**row, "id": "zzz/000000", "sequence": "zzz"}
    secret = tmp_path / "secret.rec"
    write_record(secret, row, pts)  # a valid record, outside the dataset
    (staging / "zzz").mkdir()
    (staging / "zzz" / "000000.rec").symlink_to(secret)
    with pytest.raises(SparsetoolsError, match="symbolic link"):
        build(inputs, out)
    assert not (out / MANIFEST_NAME).exists()
