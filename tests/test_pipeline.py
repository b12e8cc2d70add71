"""The frame runner: resume, atomic outputs, error policy, worker-count independence."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from _pipeline_jobs import RandomInput, WriteRandom, crash
from sparsetools.errors import FrameError, OutputError, ParameterError
from sparsetools.io.sources import FrameKey
from sparsetools.pipeline import Batch, FrameTask, check_output_dir, make_executor, run_frames
from sparsetools.random import frame_rng, frame_seed


def _tasks(out: Path, n=6, sequence="", sources=()):
    tasks = []
    for i in range(n):
        key = FrameKey(sequence, f"{i:06d}")
        src = sources[i] if sources else None
        tasks.append(
            FrameTask(
                key,
                RandomInput(None if src is None else str(src)),
                {"data": key.path(out, ".bin")},
                () if src is None else (src,),
            )
        )
    return tasks


def _contents(out: Path):
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.is_file()}


def test_serial_and_pool_give_identical_bytes(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    s1 = run_frames(WriteRandom(), _tasks(a), batch=Batch(workers=1))
    s2 = run_frames(WriteRandom(), _tasks(b), batch=Batch(workers=2))
    assert len(s1.done) == len(s2.done) == 6
    assert _contents(a) == _contents(b)
    assert s1.total("sum") == pytest.approx(s2.total("sum"))


def test_resume_skips_complete_outputs_and_overwrite_recomputes(tmp_path):
    out = tmp_path / "o"
    run_frames(WriteRandom(), _tasks(out, n=3))
    (out / "000001.bin").write_bytes(b"sentinel")
    s = run_frames(WriteRandom(), _tasks(out, n=5))
    assert len(s.resumed) == 3 and len(s.done) == 2
    assert (out / "000001.bin").read_bytes() == b"sentinel"
    s = run_frames(WriteRandom(), _tasks(out, n=5), batch=Batch(overwrite=True))
    assert len(s.done) == 5 and (out / "000001.bin").read_bytes() != b"sentinel"


def test_outputs_mirror_the_sequence(tmp_path):
    out = tmp_path / "o"
    tasks = _tasks(out, n=2, sequence="drive_a") + _tasks(out, n=2, sequence="drive_b")
    s = run_frames(WriteRandom(), tasks)
    assert len(s.done) == 4
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*.bin")) == [
        "drive_a/000000.bin",
        "drive_a/000001.bin",
        "drive_b/000000.bin",
        "drive_b/000001.bin",
    ]
    # per-frame seeds come from the whole frame id, so the two drives differ
    assert (out / "drive_a/000000.bin").read_bytes() != (out / "drive_b/000000.bin").read_bytes()


def test_two_frames_writing_one_output_name_both(tmp_path):
    a = FrameTask(
        FrameKey("", "a"), RandomInput(), {"data": tmp_path / "x.bin"}, (tmp_path / "in_a",)
    )
    b = FrameTask(
        FrameKey("", "b"), RandomInput(), {"data": tmp_path / "x.bin"}, (tmp_path / "in_b",)
    )
    with pytest.raises(ParameterError, match=r"frames a .*in_a.* and b .*in_b.* would both write"):
        run_frames(WriteRandom(), [a, b])


def test_output_replacing_an_input_is_refused(tmp_path):
    src = tmp_path / "in.bin"
    src.write_bytes(b"x")
    t = FrameTask(FrameKey("", "a"), RandomInput(str(src)), {"data": src}, (src,))
    with pytest.raises(OutputError, match="would replace an input"):
        run_frames(WriteRandom(), [t])
    assert src.read_bytes() == b"x"


def test_stale_temporaries_are_removed(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / ".tmp-sparsetools-xyz.bin").write_bytes(b"half")
    run_frames(WriteRandom(), _tasks(out, n=2))
    assert sorted(p.name for p in out.iterdir()) == ["000000.bin", "000001.bin"]


def test_on_error_stop_raises_with_frame_id(tmp_path):
    with pytest.raises(FrameError, match="frame 000002: 000002.bin: truncated"):
        run_frames(WriteRandom(bad=("000002",)), _tasks(tmp_path))


@pytest.mark.parametrize("workers", [1, 2])
def test_on_error_skip_reports_and_completes_the_rest(tmp_path, workers):
    s = run_frames(
        WriteRandom(bad=("000002",)),
        _tasks(tmp_path),
        batch=Batch(on_error="skip", workers=workers),
    )
    assert [r.frame_id for r in s.failed] == ["000002"]
    assert len(s.done) == 5
    assert not (tmp_path / "000002.bin").exists()
    assert s.as_dict()["failures"] == {"000002": "000002.bin: truncated"}


def test_unexpected_exception_becomes_internal_error(tmp_path):
    s = run_frames(crash, _tasks(tmp_path, n=1), batch=Batch(on_error="skip"))
    assert s.failed[0].error.startswith("internal error: ZeroDivisionError")
    assert s.failed[0].detail == ""


def test_debug_keeps_the_frames_traceback(tmp_path):
    with pytest.raises(FrameError) as info:
        run_frames(crash, _tasks(tmp_path, n=1), batch=Batch(debug=True))
    text = str(info.value)
    assert text.startswith("frame 000000: internal error: ZeroDivisionError")
    # the line of the failure inside the job, not only the runner's frames
    assert "_pipeline_jobs.py" in text and 'raise ZeroDivisionError("bug")' in text


def test_duplicate_frame_ids_and_bad_policy(tmp_path):
    tasks = _tasks(tmp_path, n=2)
    with pytest.raises(ParameterError, match="same frame id"):
        run_frames(WriteRandom(), tasks + tasks[:1])
    with pytest.raises(ParameterError, match="--on-error"):
        Batch(on_error="ignore")
    with pytest.raises(ParameterError, match="workers"):
        make_executor(workers=0)


def test_workers_are_capped_by_the_task_count(tmp_path, caplog):
    import logging

    with caplog.at_level(logging.WARNING):
        s = run_frames(WriteRandom(), _tasks(tmp_path, n=2), batch=Batch(workers=64))
    pids = {r.stats["pid"] for r in s.done}
    assert len(s.done) == 2 and len(pids) <= 2
    assert "--workers 64 capped to" in caplog.text


def test_check_output_dir(tmp_path):
    inp = tmp_path / "in"
    inp.mkdir()
    with pytest.raises(OutputError, match="inside the input folder"):
        check_output_dir(inp / "out", [inp])
    with pytest.raises(OutputError, match="inside the input folder"):
        check_output_dir(inp, [inp])
    (tmp_path / "f").write_bytes(b"")
    with pytest.raises(OutputError, match="is a file"):
        check_output_dir(tmp_path / "f", [inp])
    assert check_output_dir(tmp_path / "new" / "deep", [inp]) == tmp_path / "new" / "deep"
    assert (tmp_path / "new" / "deep").is_dir()


def test_frame_rng_depends_on_seed_and_id_only():
    a = frame_rng(3, "000001").random(4)
    assert np.array_equal(a, frame_rng(3, "000001").random(4))
    assert not np.array_equal(a, frame_rng(4, "000001").random(4))
    assert not np.array_equal(a, frame_rng(3, "000002").random(4))
    assert frame_seed(3, 1).entropy == frame_seed(3, "1").entropy
