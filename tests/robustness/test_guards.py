"""Guarantees of docs/reliability.md that no test pinned before: each test here fails when the
guard it names is disabled (the audit table of docs/reliability.md says how each was checked).

- Outputs made by another sparsetools version are refused, whatever the kind of output
  (a batch folder, a single file, a whole tree: the three callers of
  ``pipeline.provenance.check_made_by``), and those of a compatible version
  (``COMPATIBLE_VERSIONS``) resume.
- ``--on-error stop`` keeps the frames completed before the failed one, complete and
  recorded: after the bad input is fixed, the rerun does only the rest and ends with the
  bytes of an uninterrupted run.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_helpers import assert_no_traceback, assert_one_error_line, invoke
from corpus_builder import H, W, corrupt_png, replicate, temp_files, tree_digest, write

from sparsetools import __version__
from sparsetools.io.provenance import RECORD_DIR, file_record_path
from sparsetools.pipeline.provenance import COMPATIBLE_VERSIONS

# -- a record of another version ------------------------------------------------------------------


def _project(tmp: Path):
    f = replicate(tmp / "in", 3)
    out = tmp / "out"
    args = ["project", f["cloud"].parent, "--calib", f["calib"], "--image-size", f"{W}x{H}",
            "-o", out]  # fmt: skip
    return args, out, out / RECORD_DIR / "run.json"


def _viz(tmp: Path):
    f = replicate(tmp / "in", 1)
    out = tmp / "out" / "v.png"
    out.parent.mkdir(parents=True)
    return ["viz", f["depth"], "--image", f["image"], "-o", out], out, file_record_path(out)


def _synth_scene(tmp: Path):
    out = tmp / "out"
    args = ["synth-scene", "-o", out, "--frames", "1", "--image-size", "64x24",
            "--underwater-frames", "0", "--seed", "3"]  # fmt: skip
    return args, out, out / RECORD_DIR / "run.json"


#: One command per kind of output the resume rule guards (OutputFolder, OutputFile,
#: OutputTree in pipeline/provenance.py).
KINDS = {"folder": _project, "file": _viz, "tree": _synth_scene}


def _set_version(record: Path, version: str) -> None:
    doc = json.loads(record.read_text())
    doc["version"] = version
    record.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")


def _outputs(out: Path) -> dict[str, str]:
    return tree_digest(out if out.is_dir() else out.parent)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_outputs_of_another_version_are_refused(kind, tmp_path):
    args, out, record = KINDS[kind](tmp_path)
    r = invoke(args)
    assert r.exit_code == 0, r.stderr
    assert record.is_file(), "the output has no record of its version"
    for other in ("0.1.0", "99.0.0"):
        assert other not in COMPATIBLE_VERSIONS
        _set_version(record, other)
        before = _outputs(out)
        r = invoke(args)
        line = assert_one_error_line(r, f"made by sparsetools {other}, this is {__version__}")
        assert "--overwrite" in line
        assert _outputs(out) == before, "a refused run changed the outputs"


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_outputs_of_a_compatible_version_resume(kind, tmp_path):
    args, out, record = KINDS[kind](tmp_path)
    assert invoke(args).exit_code == 0
    before = _outputs(out)
    for version in sorted(COMPATIBLE_VERSIONS):
        _set_version(record, version)
        r = invoke(args)
        assert_no_traceback(r)
        assert r.exit_code == 0, r.stderr
        # up to date: nothing rewritten (the record aside, which this run may refresh)
        now = _outputs(out)
        assert {k: v for k, v in now.items() if RECORD_DIR not in k} == {
            k: v for k, v in before.items() if RECORD_DIR not in k
        }


# -- --on-error stop -------------------------------------------------------------------------------

N = 5
BAD = "000003"  # frames 000000-000002 are done before it (--workers 1 runs frames in order)


def _stop_project(root: Path):
    f = replicate(root, N)
    bad = f["cloud"].with_name(f"{BAD}.bin")
    return (lambda out: ["project", f["cloud"].parent, "--calib", f["calib"], "--image-size",
                         f"{W}x{H}", "-o", out]), bad, b"\x00" * 100  # fmt: skip


def _stop_lowlight(root: Path):
    f = replicate(root, N)
    bad = f["image"].with_name(f"{BAD}.png")
    return (lambda out: ["lowlight-synth", f["image"].parent, "--seed", "3", "-o", out]), bad, \
        corrupt_png()  # fmt: skip


def _stop_dataset(root: Path):
    f = replicate(root, N)
    bad = f["depth"].with_name(f"{BAD}.png")
    return (lambda out: ["dataset", "build", "--rgb", f["image"].parent, "--sparse",
                         f["depth"].parent, "-o", out]), bad, corrupt_png()  # fmt: skip


STOPPED = {
    "project": _stop_project,
    "lowlight-synth": _stop_lowlight,
    "dataset-build": _stop_dataset,
}


@pytest.mark.parametrize("command", sorted(STOPPED))
def test_on_error_stop_keeps_the_frames_done_before_the_failure(command, tmp_path):
    args_for, bad, broken = STOPPED[command](tmp_path / "in")
    good = bad.read_bytes()
    ref, out = tmp_path / "ref", tmp_path / "out"

    write(bad, broken)
    r = invoke([*args_for(out), "--workers", "1", "--on-error", "stop"])
    assert_one_error_line(r, f"frame {BAD}")
    kept = tree_digest(out)
    assert not any(BAD in k for k in kept), "the failed frame left files"
    assert not temp_files(out)

    write(bad, good)
    r = invoke([*args_for(out), "--workers", "1", "--json"])
    assert r.exit_code == 0, r.stderr
    summary = json.loads(r.stdout)
    assert invoke([*args_for(ref), "--workers", "1"]).exit_code == 0
    reference = tree_digest(ref)
    for i in range(3):  # the frames done before the failure were kept, complete
        stem = f"{i:06d}"
        mine = {k: v for k, v in kept.items() if stem in k and k in reference}
        assert mine, f"frame {stem}, done before the failure, was removed"
        assert all(reference[k] == v for k, v in mine.items()), f"frame {stem} is damaged"
    # ... and recorded: the rerun does only the rest, and ends as an uninterrupted run
    assert (summary["skipped_existing"], summary["processed"]) == (3, N - 3), summary
    assert tree_digest(out) == reference
