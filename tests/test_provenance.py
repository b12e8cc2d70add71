"""The make-like resume rule (pipeline.provenance) on the frame runner itself."""

from __future__ import annotations

import hashlib
import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from _pipeline_jobs import RandomInput, WriteRandom
from sparsetools.errors import FrameError, OutputError
from sparsetools.io.provenance import (
    FileIdentity,
    OutputIdentity,
    file_identity,
    hold_lock,
    output_identity,
    output_unchanged,
    read_frame_records,
    read_run_record,
)
from sparsetools.io.sources import FrameKey
from sparsetools.pipeline import Batch, FrameTask, RunSpec, run_frames
from sparsetools.pipeline.provenance import settings_difference


@dataclass(frozen=True)
class Settings:
    seed: int = 7
    max_depth: float | None = 80.0
    fmt: str = field(default="bin", metadata={"option": "--format"})


def _inputs(folder: Path, n: int) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        p = folder / f"{i:06d}.dat"
        if not p.exists():
            p.write_bytes(bytes([i]) * (10 + i))
        paths.append(p)
    return paths


def _tasks(out: Path, sources: list[Path]) -> list[FrameTask]:
    return [
        FrameTask(
            FrameKey("", src.stem),
            RandomInput(str(src)),
            {"data": out / f"{src.stem}.bin"},
            (src,),
        )
        for src in sources
    ]


def _run(out, sources, settings=Settings(), **batch):
    spec = RunSpec("test", out, settings, noun="test outputs")
    return run_frames(
        WriteRandom(seed=settings.seed), _tasks(out, sources), batch=Batch(**batch), spec=spec
    )


def test_rerun_with_same_settings_is_a_no_op(tmp_path):
    src = _inputs(tmp_path / "in", 3)
    out = tmp_path / "out"
    first = _run(out, src)
    assert len(first.done) == 3
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.bin")}
    again = _run(out, src)
    assert len(again.resumed) == 3 and not again.done
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.bin")} == before
    # statistics of up-to-date frames come from the record: totals describe every frame
    assert again.total("sum") == pytest.approx(first.total("sum"))
    rec = read_run_record(out)
    assert rec.command == "test" and rec.settings == {"seed": 7, "max_depth": 80.0, "fmt": "bin"}
    assert sorted(read_frame_records(out)) == ["000000", "000001", "000002"]


def test_changed_setting_is_refused_naming_it(tmp_path):
    src = _inputs(tmp_path / "in", 2)
    out = tmp_path / "out"
    _run(out, src)
    before = {p.name: p.read_bytes() for p in out.glob("*.bin")}
    with pytest.raises(OutputError, match=r"made with --max-depth 80, not 20: use --overwrite"):
        _run(out, src, Settings(max_depth=20.0))
    with pytest.raises(OutputError, match=r"made with --format bin, not png"):
        _run(out, src, Settings(fmt="png"))
    assert {p.name: p.read_bytes() for p in out.glob("*.bin")} == before
    s = _run(out, src, Settings(max_depth=20.0), overwrite=True)
    assert len(s.done) == 2
    assert read_run_record(out).settings["max_depth"] == 20.0


def test_changed_input_recomputes_exactly_that_frame(tmp_path):
    src = _inputs(tmp_path / "in", 4)
    out = tmp_path / "out"
    _run(out, src)
    old = (out / "000002.bin").read_bytes()
    src[2].write_bytes(b"a different content, a different size")
    s = _run(out, src)
    assert [r.frame_id for r in s.done] == ["000002"]
    assert [r.frame_id for r in s.recomputed] == ["000002"]
    assert s.as_dict()["recomputed"] == 1 and len(s.resumed) == 3
    assert (out / "000002.bin").read_bytes() != old
    assert (out / "000002.bin").read_bytes().endswith(b"a different content, a different size")


def test_touched_small_input_with_the_same_bytes_is_up_to_date(tmp_path):
    src = _inputs(tmp_path / "in", 2)
    out = tmp_path / "out"
    _run(out, src)
    st = src[0].stat()
    os.utime(src[0], ns=(st.st_atime_ns, st.st_mtime_ns + 10_000_000_000))
    s = _run(out, src)
    assert not s.done and len(s.resumed) == 2


def test_same_size_new_mtime_and_content_is_recomputed(tmp_path):
    src = _inputs(tmp_path / "in", 1)
    out = tmp_path / "out"
    _run(out, src)
    data = bytearray(src[0].read_bytes())
    data[0] ^= 0xFF
    st = src[0].stat()
    src[0].write_bytes(bytes(data))
    os.utime(src[0], ns=(st.st_atime_ns, st.st_mtime_ns + 5_000_000_000))
    assert [r.frame_id for r in _run(out, src).recomputed] == ["000000"]


def test_missing_output_is_recomputed(tmp_path):
    src = _inputs(tmp_path / "in", 2)
    out = tmp_path / "out"
    _run(out, src)
    (out / "000001.bin").unlink()
    s = _run(out, src)
    assert [r.frame_id for r in s.done] == ["000001"] and not s.recomputed


def test_foreign_file_at_an_output_path_is_refused(tmp_path):
    src = _inputs(tmp_path / "in", 2)
    out = tmp_path / "out"
    out.mkdir()
    (out / "000000.bin").write_bytes(b"the user's own file")
    with pytest.raises(OutputError, match=r"000000.bin exists but .* has no record"):
        _run(out, src)
    assert (out / "000000.bin").read_bytes() == b"the user's own file"
    assert not (out / ".sparsetools").exists()  # a refused run leaves nothing behind
    _run(out, src, overwrite=True)
    assert (out / "000000.bin").read_bytes() != b"the user's own file"


def test_another_command_is_refused(tmp_path):
    src = _inputs(tmp_path / "in", 1)
    out = tmp_path / "out"
    _run(out, src)
    spec = RunSpec("other", out, Settings())
    with pytest.raises(OutputError, match="holds the output of `sparsetools test`, not `other`"):
        run_frames(WriteRandom(), _tasks(out, src), spec=spec)


def test_overwrite_removes_only_the_previous_runs_outputs(tmp_path):
    src = _inputs(tmp_path / "in", 3)
    out = tmp_path / "out"
    _run(out, src)
    (out / "notes.txt").write_text("mine")
    s = _run(out, src[:1], Settings(seed=8), overwrite=True)
    assert len(s.done) == 1 and s.as_dict()["removed_stale"] == 2
    assert sorted(p.name for p in out.iterdir() if p.is_file()) == ["000000.bin", "notes.txt"]
    assert sorted(read_frame_records(out)) == ["000000"]


def test_a_run_whose_frames_all_fail_leaves_nothing(tmp_path):
    src = _inputs(tmp_path / "in", 2)
    out = tmp_path / "out"
    spec = RunSpec("test", out, Settings())
    with pytest.raises(FrameError):
        run_frames(WriteRandom(bad=("000000", "000001")), _tasks(out, src), spec=spec)
    assert list(out.iterdir()) == []


def test_interrupted_record_line_is_ignored_and_the_frame_recomputed(tmp_path):
    src = _inputs(tmp_path / "in", 3)
    out = tmp_path / "out"
    _run(out, src)
    journal = out / ".sparsetools" / "frames.jsonl"
    lines = journal.read_text().splitlines()
    journal.write_text("\n".join(lines[:2]) + "\n" + lines[2][: len(lines[2]) // 2])
    s = _run(out, src)
    assert [r.frame_id for r in s.done] == ["000002"] and len(s.resumed) == 2
    assert sorted(read_frame_records(out)) == ["000000", "000001", "000002"]


def test_failed_frame_keeps_no_record(tmp_path):
    src = _inputs(tmp_path / "in", 3)
    out = tmp_path / "out"
    spec = RunSpec("test", out, Settings())
    s = run_frames(
        WriteRandom(bad=("000001",)), _tasks(out, src), spec=spec, batch=Batch(on_error="skip")
    )
    assert len(s.failed) == 1
    assert sorted(read_frame_records(out)) == ["000000", "000002"]
    s = _run(out, src)
    assert [r.frame_id for r in s.done] == ["000001"]


def test_second_writer_is_refused_while_the_first_holds_the_lock(tmp_path):
    src = _inputs(tmp_path / "in", 1)
    out = tmp_path / "out"
    out.mkdir()
    with hold_lock(out), pytest.raises(OutputError, match="another sparsetools run is writing"):
        _run(out, src)
    assert len(_run(out, src).done) == 1  # released with the holder


def test_record_lists_input_identity(tmp_path):
    src = _inputs(tmp_path / "in", 1)
    out = tmp_path / "out"
    _run(out, src)
    rec = read_frame_records(out)["000000"]
    assert rec.outputs == {"data": "000000.bin"}
    (ident,) = rec.inputs
    assert ident == file_identity(src[0])
    assert ident.path == str(src[0].resolve()) and ident.size == src[0].stat().st_size
    assert ident.sha256 is not None  # small file: hashed
    line = json.loads((out / ".sparsetools" / "frames.jsonl").read_text().splitlines()[0])
    assert set(line) == {"key", "outputs", "inputs", "stats", "output_ids"}
    written = (out / "000000.bin").read_bytes()
    size, mtime, digest = line["output_ids"]["data"]
    assert size == len(written) and mtime == (out / "000000.bin").stat().st_mtime_ns
    assert digest == hashlib.sha256(written).hexdigest()


def _touch_later(path):
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))


@pytest.mark.parametrize("legacy", [False, True])
def test_a_touched_output_is_judged_by_the_digest_its_record_holds(tmp_path, legacy):
    """Records written before 0.3 hold BLAKE2b-128 output digests (32 hex digits), today's
    SHA-256 (64): a touched but unchanged output is up to date either way, an edited one of
    the same size is not."""
    p = tmp_path / "out.bin"
    p.write_bytes(b"abcdefgh" * 100)
    data = p.read_bytes()
    st = p.stat()
    digest = (
        hashlib.blake2b(data, digest_size=16).hexdigest() if legacy
        else hashlib.sha256(data).hexdigest()
    )  # fmt: skip
    rec = OutputIdentity(st.st_size, st.st_mtime_ns, digest)
    if not legacy:
        assert output_identity(p) == rec
    assert output_unchanged(p, rec)
    _touch_later(p)
    assert output_unchanged(p, rec)  # same bytes, later mtime: the digest decides
    p.write_bytes(b"abcdefgX" * 100)
    _touch_later(p)
    assert not output_unchanged(p, rec)
    assert not output_unchanged(p, OutputIdentity(st.st_size, 0, "ab" * 20))  # unknown kind


def test_identity_of_a_large_file_has_no_hash(tmp_path):
    p = tmp_path / "big.bin"
    p.write_bytes(b"\0" * ((1 << 16) + 1))
    assert file_identity(p).sha256 is None
    missing = file_identity(tmp_path / "nope")
    assert missing.size == -1 and not missing.same_file(file_identity(p))


def test_same_file_rule():
    a = FileIdentity("/x", 10, 1, "h")
    assert a.same_file(FileIdentity("/x", 10, 2, "h"))  # touched, same bytes
    assert not a.same_file(FileIdentity("/x", 10, 2, "g"))
    assert not a.same_file(FileIdentity("/x", 11, 1, "h"))
    assert not FileIdentity("/x", 10, 1, None).same_file(FileIdentity("/x", 10, 2, None))


def test_settings_difference_names_the_first_differing_option():
    assert settings_difference({"a": 1}, {"a": 1}) is None
    assert settings_difference({"max_depth": None}, {"max_depth": 20.0}) == (
        "--max-depth",
        "none",
        "20",
    )
    assert settings_difference({"fmt": "png"}, {"fmt": "npy"}, {"fmt": "--format"}) == (
        "--format",
        "png",
        "npy",
    )
    assert settings_difference({"crop": [1, 2, 3, 4]}, {"crop": None})[1] == "1,2,3,4"
