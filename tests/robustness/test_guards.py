"""Guarantees of docs/reliability.md that no test pinned before: each test here fails when the
guard it names is disabled (the audit table of docs/reliability.md says how each was checked).

- Outputs made by another sparsetools version are refused, whatever the kind of output
  (a batch folder, a single file, a whole tree: the three callers of
  ``pipeline.provenance.check_made_by``), and those of a compatible version
  (``COMPATIBLE_VERSIONS``) resume.

``--on-error stop``'s guarantee (the frames completed before the failure are kept, complete
and recorded) is tested beside ``--on-error skip`` in ``test_faults.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_helpers import assert_no_traceback, assert_one_error_line, invoke
from corpus_builder import H, W, replicate, tree_digest

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
