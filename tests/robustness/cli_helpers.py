"""Running the command line in-process and judging what it printed (hardening suite)."""

from __future__ import annotations

import os

#: root ignores permission bits, so read-only folders cannot be tested as root.
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0

#: Prefixes of log lines (not errors) that commands may print on stderr.
LOG_PREFIXES = ("WARNING:", "INFO:", "DEBUG:")


def invoke(args, **kwargs):
    """Run ``sparsetools ARGS`` in-process; return click's Result."""
    from click.testing import CliRunner

    from sparsetools.cli.main import cli

    return CliRunner().invoke(cli, [str(a) for a in args], **kwargs)


def error_lines(stderr: str) -> list[str]:
    """stderr lines that are not log messages."""
    return [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith(LOG_PREFIXES)]


def assert_no_traceback(result) -> None:
    text = result.stdout + result.stderr
    assert "Traceback" not in text, text
    exc = result.exception
    # CliRunner stores an escaped exception instead of printing it: that is a traceback too.
    assert exc is None or isinstance(exc, SystemExit), repr(exc)


def assert_one_error_line(result, match: str = "") -> str:
    """Exit code 1, exactly one ``Error: ...`` line on stderr (log lines aside)."""
    assert_no_traceback(result)
    assert result.exit_code == 1, (result.exit_code, result.stdout, result.stderr)
    lines = error_lines(result.stderr)
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("Error: "), lines[0]
    assert match.lower() in lines[0].lower(), (match, lines[0])
    assert len(lines[0]) < 600, "an error line should be short and clear"
    return lines[0]
