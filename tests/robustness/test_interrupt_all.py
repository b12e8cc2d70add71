"""Kill or interrupt, then rerun: EVERY batch command resumes to the bytes of an uninterrupted
run (docs/reliability.md, "Resume, byte for byte").

Each of the 11 batch commands runs on a few tiny frames (``corpus_builder``) with
``--workers 1``, twice faulted:

- **killed**: a real ``sparsetools`` process sends itself ``SIGKILL`` at the atomic rename in
  the middle of its run (nothing of Python's cleanup runs; the complete temporary file of the
  output being renamed is left behind, the lock file too);
- **interrupted**: ``KeyboardInterrupt`` (what Ctrl-C raises) at the LAST rename of a run,
  in this process: the step after the frames (merged tables, manifests, the record) is
  where a folder is most easily left inconsistent.

Each is followed by a plain rerun; the folder must then hold exactly the files of a run that
was never faulted, byte for byte (the records too, but for the folder's own path and the
mtimes they hold: :func:`corpus_builder.record_text`), no temporary file, and the inputs must
be unchanged. ``tests/robustness/test_faults.py`` interrupts six of these commands at every
rename and kills three of them twice in long runs.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from cli_helpers import assert_no_traceback, invoke
from corpus_builder import (
    H,
    InterruptAt,
    W,
    depth_map,
    depth_png_bytes,
    replicate,
    temp_files,
    tree_digest,
    underwater_tree,
    write,
)

from sparsetools.io.atomic import TMP_PREFIX
from sparsetools.io.provenance import RECORD_DIR

N = 4  # frames per command: the middle rename falls inside the frames


def _project(root: Path):
    f = replicate(root, N)
    return lambda out: ["project", f["cloud"].parent, "--calib", f["calib"],
                        "--image-size", f"{W}x{H}", "-o", out]  # fmt: skip


def _beams(root: Path):
    f = replicate(root, N)
    return lambda out: ["beams", f["cloud"].parent, "--n", "1,4", "-o", out]


def _jbf_expand(root: Path):
    f = replicate(root, N)
    for i in range(N):
        write(root / "radar" / f"{i:06d}.png", depth_png_bytes(depth_map(i, density=0.02)))
    return lambda out: ["jbf-expand", root / "radar", "--image", f["image"].parent,
                        "--fx", "40", "--fy", "40", "-o", out]  # fmt: skip


def _lowlight(root: Path):
    f = replicate(root, N)
    return lambda out: ["lowlight-synth", f["image"].parent, "--variants", "2", "-o", out]


def _equalize(root: Path):
    f = replicate(root, N)
    return lambda out: ["equalize", f["image"].parent, "-o", out]


def _defocus(root: Path):
    f = replicate(root, N)
    return lambda out: ["defocus-synth", f["image"].parent, "--depth", f["depth"].parent,
                        "--missing-depth", "far", "-o", out]  # fmt: skip


def _dark_channel(root: Path):
    f = replicate(root, N)
    return lambda out: ["dark-channel", f["image"].parent, "-o", out]


def _underwater(root: Path):
    # three segments of 32 frames: the middle rename falls after the first segment
    sea, water = underwater_tree(root, n_seafloor=96)
    return lambda out: ["underwater", sea, "--water", water, "--median-window", "3", "-o", out]


def _densify(root: Path):
    f = replicate(root, N)
    return lambda out: ["densify", f["depth"].parent, "-o", out]


def _accumulate(root: Path):
    f = replicate(root, N)
    poses = write(root / "poses.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n" * N)  # the scans' own frame
    return lambda out: ["accumulate", f["cloud"].parent, "--calib", f["calib"],
                        "--image-size", f"{W}x{H}", "--poses", poses, "--poses-frame", "sensor",
                        "--neighbours", "1", "-o", out]  # fmt: skip


def _dataset_build(root: Path):
    f = replicate(root, N)
    return lambda out: ["dataset", "build", "--rgb", f["image"].parent, "--sparse",
                        f["depth"].parent, "-o", out]  # fmt: skip


#: The batch commands (docs/pipeline.md): all of them, each with a small valid input.
COMMANDS = {
    "project": _project,
    "beams": _beams,
    "jbf-expand": _jbf_expand,
    "lowlight-synth": _lowlight,
    "equalize": _equalize,
    "defocus-synth": _defocus,
    "dark-channel": _dark_channel,
    "underwater": _underwater,
    "densify": _densify,
    "accumulate": _accumulate,
    "dataset-build": _dataset_build,
}

#: Runs ``sparsetools ARGV[2:]`` and SIGKILLs the process at its ``ARGV[1]``-th rename of a
#: temporary output into place (before the rename: the temporary file stays behind).
_KILLED_AT_RENAME = """
import os, signal, sys
from sparsetools.io.atomic import TMP_PREFIX
at, calls, real = int(sys.argv[1]), [0], os.replace
def replace(src, dst, *a, **kw):
    if TMP_PREFIX in os.path.basename(os.fspath(src)):
        calls[0] += 1
        if calls[0] == at:
            os.kill(os.getpid(), signal.SIGKILL)
    return real(src, dst, *a, **kw)
os.replace = replace
from sparsetools.cli.main import main
main(["-q", *sys.argv[2:]])
"""


def _kill_at_rename(args: list, at: int) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", _KILLED_AT_RENAME, str(at), *map(str, args)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == -signal.SIGKILL, (proc.returncode, proc.stderr[-2000:])


def _rerun_matches(args: list, out: Path, reference: dict) -> dict:
    """Rerun into ``out``: its files must be the reference's; returns the run's summary."""
    r = invoke([*args, "--json"])
    assert_no_traceback(r)
    assert r.exit_code == 0, r.stderr
    got = tree_digest(out)
    assert got.keys() == reference.keys(), "files differ from an uninterrupted run"
    different = sorted(k for k in got if got[k] != reference[k])
    assert not different, f"resumed bytes differ from an uninterrupted run: {different}"
    assert not temp_files(out)
    return json.loads(r.stdout)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_killed_or_interrupted_run_resumes_to_the_same_bytes(command, tmp_path, monkeypatch):
    args_for = COMMANDS[command](tmp_path / "in")
    inputs = tree_digest(tmp_path / "in")

    counter = InterruptAt(0)
    monkeypatch.setattr(os, "replace", counter)
    r = invoke(args_for(tmp_path / "ref"))
    monkeypatch.setattr(os, "replace", counter.real)
    assert r.exit_code == 0, r.stderr
    renames = counter.calls
    assert renames >= 4, f"{command}: {renames} renames, too few to fault the middle"
    reference = tree_digest(tmp_path / "ref")

    # SIGKILL in the middle of the frames: what is left is complete; the rerun resumes
    killed = tmp_path / "killed"
    _kill_at_rename(args_for(killed), renames // 2 + 1)
    assert temp_files(killed), "the kill should leave the temporary file it was renaming"
    left = {k: v for k, v in tree_digest(killed).items() if RECORD_DIR not in k and v != "dir"}
    left = {k: v for k, v in left.items() if TMP_PREFIX not in k}
    done = {k: v for k, v in left.items() if k in reference}  # (and staging files of a build)
    assert done, "nothing was written before the kill"
    assert all(reference[k] == v for k, v in done.items()), "an output is incomplete"
    summary = _rerun_matches(args_for(killed), killed, reference)
    assert summary["skipped_existing"] >= 1, "the frames done before the kill were redone"

    # KeyboardInterrupt at the last rename (after the frames), then resume
    interrupted = tmp_path / "interrupted"
    monkeypatch.setattr(os, "replace", InterruptAt(renames))
    r = invoke(args_for(interrupted))
    monkeypatch.setattr(os, "replace", counter.real)
    assert r.exit_code == 130 and "Interrupted" in r.stderr, (r.exit_code, r.stderr)
    _rerun_matches(args_for(interrupted), interrupted, reference)

    assert tree_digest(tmp_path / "in") == inputs, "an input changed"
