"""The command line as the tests call it: ``run`` (quiet, in-process), ``summary`` (its
``--json`` summary, the command having succeeded) and ``one_line_error`` (a failure that says
one line on stderr and no traceback)."""

from __future__ import annotations

import json

from click.testing import CliRunner

from sparsetools.cli.main import cli


def run(*args):
    return CliRunner().invoke(cli, ["-q", *map(str, args)])


def summary(*args) -> dict:
    r = run(*args, "--json")
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


def one_line_error(result) -> str:
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    return lines[0]
