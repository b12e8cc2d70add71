"""The frame runner: resume, atomic outputs, error policy, worker-count independence."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from _pipeline_jobs import crash, write_random
from sparsetools.errors import FrameError, OutputError, ParameterError
from sparsetools.pipeline import FrameTask, check_output_dir, make_executor, run_frames
from sparsetools.random import frame_rng, frame_seed


def _tasks(out: Path, n=6, **inputs):
    inputs.setdefault("seed", 7)
    return [FrameTask(f"{i:06d}", dict(inputs), (out / f"{i:06d}.bin",)) for i in range(n)]


def _contents(out: Path):
    return {p.name: p.read_bytes() for p in sorted(out.iterdir())}


def test_serial_and_pool_give_identical_bytes(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    s1 = run_frames(write_random, _tasks(a), executor=make_executor(workers=1))
    s2 = run_frames(write_random, _tasks(b), executor=make_executor(workers=2))
    assert len(s1.done) == len(s2.done) == 6
    assert _contents(a) == _contents(b)
    assert s1.total("sum") == pytest.approx(s2.total("sum"))


def test_resume_skips_complete_outputs_and_overwrite_recomputes(tmp_path):
    out = tmp_path / "o"
    run_frames(write_random, _tasks(out, n=3))
    (out / "000001.bin").write_bytes(b"sentinel")
    s = run_frames(write_random, _tasks(out, n=5))
    assert len(s.resumed) == 3 and len(s.done) == 2
    assert (out / "000001.bin").read_bytes() == b"sentinel"
    s = run_frames(write_random, _tasks(out, n=5), overwrite=True)
    assert len(s.done) == 5 and (out / "000001.bin").read_bytes() != b"sentinel"


def test_stale_temporaries_are_removed(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / ".tmp-sparsetools-xyz.bin").write_bytes(b"half")
    run_frames(write_random, _tasks(out, n=2))
    assert sorted(p.name for p in out.iterdir()) == ["000000.bin", "000001.bin"]


def test_on_error_stop_raises_with_frame_id(tmp_path):
    with pytest.raises(FrameError, match="frame 000002: 000002.bin: truncated"):
        run_frames(write_random, _tasks(tmp_path, bad=("000002",)))


@pytest.mark.parametrize("workers", [1, 2])
def test_on_error_skip_reports_and_completes_the_rest(tmp_path, workers):
    s = run_frames(
        write_random,
        _tasks(tmp_path, bad=("000002",)),
        on_error="skip",
        executor=make_executor(workers=workers),
    )
    assert [r.frame_id for r in s.failed] == ["000002"]
    assert len(s.done) == 5
    assert not (tmp_path / "000002.bin").exists()
    assert s.as_dict()["failures"] == {"000002": "000002.bin: truncated"}


def test_unexpected_exception_becomes_internal_error(tmp_path):
    s = run_frames(crash, _tasks(tmp_path, n=1), on_error="skip")
    assert s.failed[0].error.startswith("internal error: ZeroDivisionError")


def test_duplicate_frame_ids_and_bad_policy(tmp_path):
    tasks = _tasks(tmp_path, n=2)
    with pytest.raises(ParameterError, match="same frame id"):
        run_frames(write_random, tasks + tasks[:1])
    with pytest.raises(ParameterError):
        run_frames(write_random, tasks, on_error="ignore")
    with pytest.raises(ParameterError):
        make_executor(workers=0)


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
