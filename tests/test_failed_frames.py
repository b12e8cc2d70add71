"""A frame that fails leaves nothing behind: neither what its failed attempt wrote before it
failed, nor what an earlier run wrote for it (when still those files); an edited file stays."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from sparsetools.errors import FormatError
from sparsetools.io.atomic import atomic_write_bytes
from sparsetools.pipeline import Batch, run_job
from sparsetools.pipeline.core import BatchJob, FrameTask


@dataclass(frozen=True)
class _TwoFiles(BatchJob):
    """Writes ``<frame>.a`` then ``<frame>.b`` per input file; an input holding ``bad`` fails
    between the two writes."""

    command = "two-files (test)"

    def tasks(self, frames: list, out_dir: Path) -> list[FrameTask]:
        return [FrameTask(p.stem, p, {"a": out_dir / f"{p.stem}.a", "b": out_dir / f"{p.stem}.b"},
                          (p,)) for p in frames]  # fmt: skip

    def __call__(self, task: FrameTask) -> None:
        data = task.inputs.read_bytes()
        atomic_write_bytes(task.outputs["a"], b"a:" + data)
        if data == b"bad":
            raise FormatError(f"{task.inputs}: bad")
        atomic_write_bytes(task.outputs["b"], b"b:" + data)


def _inputs(root: Path, bad: str | None = None) -> list[Path]:
    root.mkdir(exist_ok=True)
    frames = []
    for i in range(4):
        p = root / f"{i:06d}.txt"
        p.write_bytes(b"bad" if f"{i:06d}" == bad else f"frame {i}".encode())
        frames.append(p)
    return frames


def _files(out: Path) -> list[str]:
    return sorted(p.name for p in out.iterdir() if p.is_file())


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failed_attempt_leaves_no_file_of_its_own(tmp_path, workers):
    frames = _inputs(tmp_path / "in", bad="000002")
    out = tmp_path / "out"
    summary = run_job(_TwoFiles(), frames, out, batch=Batch(workers=workers, on_error="skip",
                                                             progress=False))  # fmt: skip
    assert [r.frame_id for r in summary.failed] == ["000002"]
    assert _files(out) == [f"{i:06d}.{r}" for i in (0, 1, 3) for r in "ab"]


def test_a_rerun_removes_an_earlier_runs_files_of_a_frame_that_fails_now(tmp_path):
    frames = _inputs(tmp_path / "in")
    out = tmp_path / "out"
    run_job(_TwoFiles(), frames, out, batch=Batch(progress=False))
    kept = {n: (out / n).read_bytes() for n in _files(out) if not n.startswith("000002")}
    frames[2].write_bytes(b"bad")
    edited = out / "000001.b"
    frames[1].write_bytes(b"bad")  # frame 1 fails too, but its .b was edited by someone
    edited.write_bytes(b"someone's notes")
    summary = run_job(_TwoFiles(), frames, out, batch=Batch(on_error="skip", progress=False))
    assert sorted(r.frame_id for r in summary.failed) == ["000001", "000002"]
    left = _files(out)
    assert not [n for n in left if n.startswith("000002")]
    assert left == ["000000.a", "000000.b", "000001.b", "000003.a", "000003.b"]
    assert edited.read_bytes() == b"someone's notes"
    assert {n: (out / n).read_bytes() for n in left if n != "000001.b"} == {
        n: v for n, v in kept.items() if not n.startswith("000001")
    }
