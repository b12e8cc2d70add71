"""Every command against a corpus of bad inputs (table in corpus_cases.py).

For each (command, bad input): a non-zero exit code with exactly one ``Error:`` line on
stderr (or click's usage error, exit 2, for option validation), no traceback, no new or
partial output file, no temporary file left, inputs byte-for-byte unchanged. Cases that the
specification says are not errors (an empty cloud, NaN rows, symbolic-link inputs) assert
the documented behaviour instead.
"""

from __future__ import annotations

import fnmatch

import pytest
from cli_helpers import IS_ROOT, assert_no_traceback, assert_one_error_line, invoke
from corpus_builder import invoke_bound_by_permissions, new_files, temp_files, tree_digest
from corpus_cases import CASES


def _params():
    out = []
    for c in CASES:
        marks = list(c.marks)
        if c.root_only and not IS_ROOT:
            continue
        if c.xfail:
            marks.append(pytest.mark.xfail(strict=True, reason=c.xfail))
        out.append(pytest.param(c, id=c.id, marks=marks))
    return out


def test_corpus_is_large_and_unique():
    ids = [c.id for c in CASES]
    assert len(ids) == len(set(ids))
    commands = {i.split("/")[0] for i in ids}
    for cmd in ("project", "beams", "jbf-expand", "lowlight-synth", "equalize", "underwater",
                "dataset-build", "dataset-info", "dataset-verify", "viz", "stats", "train",
                "eval", "synth-scene", "pipeline"):  # fmt: skip
        assert cmd in commands, cmd
    assert len(ids) >= 150


@pytest.mark.parametrize("case", _params())
def test_bad_input(case, tmp_path, capfd):
    setup = case.build(tmp_path)
    in_dir = tmp_path / "in"
    out = setup.out if setup.out is not None else tmp_path / "out"
    inputs_before = tree_digest(in_dir)
    out_before = tree_digest(out) if out != in_dir else inputs_before

    capfd.readouterr()
    if case.root_only is False and IS_ROOT:
        # root ignores permission bits: this case runs in a process that gave that up
        result = invoke_bound_by_permissions(setup.args)
    else:
        result = invoke(setup.args)
    # C libraries (OpenCV, libpng, Open3D/RPly) write to the file descriptors directly,
    # past click's capture: any such line would break the one-error-line contract.
    native = capfd.readouterr()
    assert not native.err.strip() and not native.out.strip(), native

    assert_no_traceback(result)
    if case.expect == "error":
        assert_one_error_line(result, case.match)
    elif case.expect == "usage":
        assert result.exit_code == 2, (result.stdout, result.stderr)
        assert "Usage:" in result.stderr and "Error:" in result.stderr
        assert case.match.lower() in result.stderr.lower(), result.stderr
    else:
        assert result.exit_code == 0, (result.stdout, result.stderr)
    if setup.check is not None:
        setup.check(tmp_path, result)

    if out != in_dir:
        assert tree_digest(in_dir) == inputs_before, "an input changed"
    written = new_files(out_before, out)
    if case.expect != "ok":
        allowed = setup.allowed_outputs
        bad = [f for f in written if not any(fnmatch.fnmatch(f, pat) for pat in allowed)]
        assert not bad, f"new files in the output after a failure: {bad}"
    if out == in_dir:
        assert not written, f"inputs changed: {written}"
    assert not temp_files(out) and not temp_files(in_dir)
