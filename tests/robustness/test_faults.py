"""Fault injection: interrupted batch runs resume to the same bytes; bad frames are skipped.

Three kinds of fault:

- ``SIGKILL`` of a real ``sparsetools`` process in the middle of a batch (twice per run, at
  arbitrary moments, so temporary files may be left half-written), then a rerun;
- an interrupt (``KeyboardInterrupt``, what Ctrl-C raises) at *every* atomic rename of a
  small run, one run per rename, then a rerun — this reaches the merge steps at the end of a
  batch (Parquet tables, manifests) that a kill rarely hits;
- one bad frame among good ones with ``--on-error skip`` (listed, the rest done) and with
  ``--on-error stop`` (the frames completed before it kept, complete and recorded: after the
  fix the rerun does only the rest).

After every rerun the output folder must be byte-identical to an uninterrupted run in
another folder and hold no temporary file.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_no_traceback, assert_one_error_line, error_lines, invoke
from corpus_builder import (
    H,
    InterruptAt,
    W,
    corrupt_png,
    png_bytes,
    replicate,
    temp_files,
    tree_digest,
    underwater_tree,
    write,
)

#: Counted into docs/reliability.md by hand: keep the two in step.
KILLS_PER_RUN = 2


def cli_command() -> list[str]:
    return [sys.executable, "-m", "sparsetools.cli.main"]


def kill_when(args: list, out: Path, pattern: str, at: int, timeout: float = 120.0) -> int:
    """Start ``sparsetools ARGS``; SIGKILL it once ``at`` files match ``out/pattern``.

    Returns how many matched when it was killed; fails if the run ended by itself first.
    """
    proc = subprocess.Popen(
        [*cli_command(), "-q", *map(str, args)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    t_end = time.monotonic() + timeout
    seen = 0
    try:
        while proc.poll() is None and time.monotonic() < t_end:
            seen = len(list(out.glob(pattern))) if out.is_dir() else 0
            if seen >= at:
                proc.send_signal(signal.SIGKILL)
                break
            time.sleep(0.002)
    finally:
        if proc.poll() is None and time.monotonic() >= t_end:
            proc.kill()
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL, (
        f"the run ended (exit {proc.returncode}) before {at} outputs appeared: "
        f"make the batch longer; stderr: {err.decode(errors='replace')[-2000:]}"
    )
    return seen


def kill_resume_compare(tmp_path: Path, args_for, pattern: str, total: int, kill_at) -> dict:
    """Reference run in ``ref``; killed runs then a final run in ``out``; compare."""
    ref, out = tmp_path / "ref", tmp_path / "out"
    r = invoke(args_for(ref))
    assert r.exit_code == 0, r.stderr
    reference = tree_digest(ref)
    assert len([k for k in reference if Path(k).match(pattern)]) == total

    seen = [kill_when(args_for(out), out, pattern, at) for at in kill_at]
    assert seen == sorted(seen) and seen[-1] < total

    final = invoke([*args_for(out), "--json"])
    assert_no_traceback(final)
    assert final.exit_code == 0, final.stderr
    summary = json.loads(final.stdout)
    assert tree_digest(out) == reference, "resumed output differs from an uninterrupted run"
    assert not temp_files(out)
    return summary


@pytest.mark.slow
def test_project_killed_twice_resumes_identically(tmp_path):
    n = 150
    f = replicate(tmp_path / "in", n)

    def args(out):
        return ["project", f["cloud"].parent, "--calib", f["calib"], "--image-size", f"{W}x{H}",
                "-o", out]  # fmt: skip

    summary = kill_resume_compare(tmp_path, args, "*.png", n, kill_at=(20, 70))
    # A frame is complete with both files: the last one seen may lack its calib JSON.
    assert summary["frames"] == n and summary["skipped_existing"] >= 69
    assert summary["processed"] == n - summary["skipped_existing"]


@pytest.mark.slow
def test_lowlight_killed_twice_resumes_identically(tmp_path):
    n = 40
    f = replicate(tmp_path / "in", n)

    def args(out):
        return ["lowlight-synth", f["image"].parent, "--seed", "3", "-o", out]

    summary = kill_resume_compare(tmp_path, args, "*.png", n, kill_at=(6, 20))
    assert summary["manifest_rows"] == n and summary["skipped_existing"] >= 19


@pytest.mark.slow
def test_dataset_build_killed_twice_resumes_identically(tmp_path):
    n = 150
    f = replicate(tmp_path / "in", n)

    def args(out):
        return ["dataset", "build", "--rgb", f["image"].parent, "--sparse", f["depth"].parent,
                "-o", out]  # fmt: skip

    summary = kill_resume_compare(tmp_path, args, "rgb/*.png", n, kill_at=(20, 70))
    assert summary["frames"] == n and summary["skipped_existing"] >= 69
    verify = invoke(["dataset", "verify", tmp_path / "out"])
    assert verify.exit_code == 0, verify.stdout


# -- an interrupt at every atomic rename --------------------------------------------------------


def _inputs_project(root: Path):
    f = replicate(root, 3)
    return lambda out: ["project", f["cloud"].parent, "--calib", f["calib"],
                        "--image-size", f"{W}x{H}", "--format", "parquet", "-o", out]  # fmt: skip


def _inputs_lowlight(root: Path):
    f = replicate(root, 3)
    return lambda out: ["lowlight-synth", f["image"].parent, "--variants", "2", "-o", out]


def _inputs_dataset(root: Path):
    f = replicate(root, 4)
    for stem in ("000000", "000001", "000002", "000003"):
        write(root / "gt" / f"{stem}.png", f["gt"].read_bytes())
    return lambda out: ["dataset", "build", "--rgb", f["image"].parent, "--sparse",
                        f["depth"].parent, "--gt", root / "gt", "-o", out]  # fmt: skip


def _inputs_equalize(root: Path):
    f = replicate(root, 3)
    return lambda out: ["equalize", f["image"].parent, "-o", out]


def _inputs_underwater(root: Path):
    sea, water = underwater_tree(root, n_seafloor=4)
    return lambda out: ["underwater", sea, "--water", water, "--window", "3", "-o", out]


def _inputs_beams(root: Path):
    f = replicate(root, 3)
    return lambda out: ["beams", f["cloud"].parent, "--n", "1,4", "-o", out]


INTERRUPTED = {
    "project-parquet": _inputs_project,
    "lowlight-synth": _inputs_lowlight,
    "dataset-build": _inputs_dataset,
    "equalize": _inputs_equalize,
    "underwater": _inputs_underwater,
    "beams": _inputs_beams,
}


@pytest.mark.parametrize("command", sorted(INTERRUPTED))
def test_interrupt_at_every_rename_resumes_identically(command, tmp_path, monkeypatch):
    args_for = INTERRUPTED[command](tmp_path / "in")
    counter = InterruptAt(0)
    monkeypatch.setattr(os, "replace", counter)
    r = invoke(args_for(tmp_path / "ref"))
    assert r.exit_code == 0, r.stderr
    renames = counter.calls
    assert renames >= 3
    reference = tree_digest(tmp_path / "ref")
    inputs = tree_digest(tmp_path / "in")

    for n in range(1, renames + 1):
        out = tmp_path / f"out{n}"
        monkeypatch.setattr(os, "replace", InterruptAt(n))
        r = invoke(args_for(out))
        assert r.exit_code == 130, (n, r.exit_code, r.stderr)
        assert "Interrupted" in r.stderr
        monkeypatch.setattr(os, "replace", counter.real)
        r = invoke(args_for(out))
        assert r.exit_code == 0, (n, r.stderr)
        assert tree_digest(out) == reference, f"interrupt at rename {n} of {renames}"
        assert not temp_files(out)
        shutil.rmtree(out)
    assert tree_digest(tmp_path / "in") == inputs
    print(f"{command}: {renames} interrupts injected")


# -- --on-error skip ------------------------------------------------------------------------------


def _skip_project(root: Path):
    f = replicate(root, 5)
    write(f["cloud"].with_name("000002.bin"), f["cloud"].read_bytes()[:100])
    args = ["project", f["cloud"].parent, "--calib", f["calib"], "--image-size", f"{W}x{H}"]
    return args, "000002", lambda out: sorted(p.name for p in out.glob("*.png"))


def _skip_beams(root: Path):
    f = replicate(root, 5)
    write(f["cloud"].with_name("000002.bin"), f["cloud"].read_bytes()[:100])
    return (["beams", f["cloud"].parent, "--n", "4"], "000002",
            lambda out: sorted(p.name for p in out.glob("*.bin")))  # fmt: skip


def _skip_lowlight(root: Path):
    f = replicate(root, 5)
    write(f["image"].with_name("000002.png"), corrupt_png())
    return (["lowlight-synth", f["image"].parent], "000002",
            lambda out: sorted(p.name for p in out.glob("*.png")))  # fmt: skip


def _skip_equalize(root: Path):
    f = replicate(root, 5)
    write(f["image"].with_name("000002.png"), b"")
    return (["equalize", f["image"].parent], "000002",
            lambda out: sorted(p.name for p in out.glob("*.png")))  # fmt: skip


def _skip_dataset(root: Path):
    f = replicate(root, 5)
    write(f["depth"].with_name("000002.png"), png_bytes(np.full((H, W), 7, np.uint8)))

    def done(out):
        from sparsetools.io.dataset import read_manifest

        ids = read_manifest(out / "manifest.parquet")[0].column("id").to_pylist()
        files = {p.stem for p in out.rglob("*.png")}
        assert "000002" not in files, "the failed frame left files in the dataset"
        return [f"{i}.png" for i in ids]

    return ["dataset", "build", "--rgb", f["image"].parent, "--sparse", f["depth"].parent], \
        "000002", done  # fmt: skip


def _skip_jbf(root: Path):
    from corpus_builder import depth_map, depth_png_bytes

    f = replicate(root, 5)
    for i in range(5):
        write(root / "radar" / f"{i:06d}.png", depth_png_bytes(depth_map(i, density=0.02)))
    write(root / "radar" / "000002.png", corrupt_png())
    args = ["jbf-expand", root / "radar", "--image", f["image"].parent, "--fx", "40", "--fy", "40"]
    return args, "000002", lambda out: sorted(p.name for p in out.glob("0*[0-9].png"))


SKIPPED = {
    "project": _skip_project,
    "beams": _skip_beams,
    "lowlight-synth": _skip_lowlight,
    "equalize": _skip_equalize,
    "dataset-build": _skip_dataset,
    "jbf-expand": _skip_jbf,
}


@pytest.mark.parametrize("command", sorted(SKIPPED))
def test_on_error_skip_reports_the_bad_frame_and_does_the_rest(command, tmp_path):
    args, bad, outputs = SKIPPED[command](tmp_path / "in")
    out = tmp_path / "out"
    inputs = tree_digest(tmp_path / "in")
    r = invoke([*args, "--on-error", "skip", "-o", out])
    assert_no_traceback(r)
    assert r.exit_code == 1, (r.stdout, r.stderr)
    assert f"failed {bad}" in r.stdout, r.stdout
    lines = error_lines(r.stderr)
    assert lines == ["Error: 1 frame(s) failed (listed above)"], r.stderr
    good = [f"{i:06d}.png" for i in range(5) if f"{i:06d}" != bad]
    got = outputs(out)
    assert [Path(g).stem for g in got] == [Path(g).stem for g in good]
    assert not temp_files(out)
    assert tree_digest(tmp_path / "in") == inputs


def _fix(root: Path, bad: str) -> None:
    """Replace the bad frame's files by copies of frame 000000's (as ``replicate`` made)."""
    for p in root.rglob(f"{bad}.*"):
        p.write_bytes(p.with_name("000000" + p.suffix).read_bytes())


def _frame_files(digest: dict[str, str]) -> dict[str, str]:
    """The per-frame files of a tree digest (named by a frame), not the records or tables."""
    return {k: v for k, v in digest.items()
            if ".sparsetools" not in k and Path(k).name.startswith("0000")}  # fmt: skip


@pytest.mark.parametrize("command", sorted(SKIPPED))
def test_a_rerun_removes_what_an_earlier_run_made_of_a_frame_that_now_fails(command, tmp_path):
    """A rerun leaves what a fresh run would: a frame whose input broke since an earlier run
    made it fails, and the files that run wrote for it go (they stand for inputs it no longer
    has); every other frame's files stay, byte for byte."""
    root = tmp_path / "in"
    args, bad, outputs = SKIPPED[command](root)
    broken = {p: p.read_bytes() for p in root.rglob(f"{bad}.*")}
    _fix(root, bad)
    out = tmp_path / "out"
    r = invoke([*args, "-o", out])
    assert r.exit_code == 0, r.stderr
    before = _frame_files(tree_digest(out))
    assert any(bad in k for k in before)
    for p, data in broken.items():
        p.write_bytes(data)
    inputs = tree_digest(root)
    r = invoke([*args, "--on-error", "skip", "-o", out])
    assert_no_traceback(r)
    assert r.exit_code == 1 and f"failed {bad}" in r.stdout, (r.stdout, r.stderr)
    assert "that an earlier run made of 1 frame(s) failing now" in r.stderr, r.stderr
    good = [f"{i:06d}" for i in range(5) if f"{i:06d}" != bad]
    assert [Path(g).stem for g in outputs(out)] == good
    after = _frame_files(tree_digest(out))
    assert not any(bad in k for k in after), "the failed frame's earlier files stayed"
    assert after == {k: v for k, v in before.items() if bad not in k}
    assert tree_digest(root) == inputs


def test_a_failed_frames_output_edited_since_is_not_removed(tmp_path):
    """Only the very files an earlier run wrote go: one changed since is someone's."""
    root = tmp_path / "in"
    args, bad, _ = _skip_project(root)
    broken = {p: p.read_bytes() for p in root.rglob(f"{bad}.*")}
    _fix(root, bad)
    out = tmp_path / "out"
    assert invoke([*args, "-o", out]).exit_code == 0
    edited = out / f"{bad}.png"
    edited.write_bytes(png_bytes(np.full((H, W), 3, np.uint8)))
    for p, data in broken.items():
        p.write_bytes(data)
    r = invoke([*args, "--on-error", "skip", "-o", out])
    assert r.exit_code == 1 and f"failed {bad}" in r.stdout, (r.stdout, r.stderr)
    assert edited.read_bytes() == png_bytes(np.full((H, W), 3, np.uint8))


@pytest.mark.parametrize("command", sorted(SKIPPED))
def test_on_error_stop_keeps_the_frames_done_before_the_failure(command, tmp_path):
    args, bad, _ = SKIPPED[command](tmp_path / "in")
    before = sorted(f"{i:06d}" for i in range(int(bad)))  # --workers 1: frames in order
    out, ref = tmp_path / "out", tmp_path / "ref"
    r = invoke([*args, "--workers", "1", "--on-error", "stop", "-o", out])
    assert_one_error_line(r, f"frame {bad}")
    kept = tree_digest(out)
    assert not any(bad in k for k in kept), "the failed frame left files"
    assert not temp_files(out)

    _fix(tmp_path / "in", bad)
    r = invoke([*args, "--workers", "1", "--json", "-o", out])
    assert r.exit_code == 0, r.stderr
    summary = json.loads(r.stdout)
    assert invoke([*args, "--workers", "1", "-o", ref]).exit_code == 0
    reference = tree_digest(ref)
    for stem in before:  # kept, complete ...
        mine = {k: v for k, v in kept.items() if stem in k and k in reference}
        assert mine, f"frame {stem}, done before the failure, was removed"
        assert all(reference[k] == v for k, v in mine.items()), f"frame {stem} is damaged"
    # ... and recorded: the rerun does only the rest, and ends as an uninterrupted run
    assert (summary["skipped_existing"], summary["processed"]) == (len(before), 5 - len(before))
    assert tree_digest(out) == reference


def test_skip_then_fix_then_rerun_does_only_the_fixed_frame(tmp_path):
    f = replicate(tmp_path / "in", 5)
    good_bytes = f["cloud"].read_bytes()
    bad = f["cloud"].with_name("000002.bin")
    write(bad, good_bytes[:100])

    def args(out):
        return ["project", f["cloud"].parent, "--calib", f["calib"], "--image-size", f"{W}x{H}",
                "-o", out, "--json"]  # fmt: skip

    r = invoke([*args(tmp_path / "out"), "--on-error", "skip"])
    assert r.exit_code == 1
    write(bad, good_bytes)
    r = invoke(args(tmp_path / "out"))
    assert r.exit_code == 0, r.stderr
    summary = json.loads(r.stdout)
    assert (summary["processed"], summary["skipped_existing"], summary["failed"]) == (1, 4, 0)
    assert invoke(args(tmp_path / "ref")).exit_code == 0
    assert tree_digest(tmp_path / "out") == tree_digest(tmp_path / "ref")
