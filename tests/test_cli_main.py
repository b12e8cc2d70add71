"""The command group: version, help, error mapping, logging flags."""

from __future__ import annotations

import click
from click.testing import CliRunner

from sparsetools import __version__
from sparsetools.cli import main as cli_main
from sparsetools.cli.main import cli
from sparsetools.errors import FormatError


def test_version_and_help():
    r = CliRunner().invoke(cli, ["--version"])
    assert r.exit_code == 0 and __version__ in r.output
    r = CliRunner().invoke(cli, ["--help"])
    assert r.exit_code == 0 and "synth-scene" in r.output


def test_every_listed_command_has_help_with_an_example():
    runner = CliRunner()
    names = cli.list_commands(None)
    assert "synth-scene" in names
    for name in names:
        r = runner.invoke(cli, [name, "--help"])
        assert r.exit_code == 0, (name, r.output)
        assert "Example" in r.output or "example" in r.output, name


def _add_command(monkeypatch, fn):
    monkeypatch.setitem(cli_main.COMMANDS, "boom", "x:y")
    monkeypatch.setattr(
        cli_main.LazyGroup, "get_command", lambda self, ctx, name: fn if name == "boom" else None
    )


def test_library_error_is_one_line_exit_1(monkeypatch):
    @click.command()
    def boom():
        """Raise a library error."""
        raise FormatError("000000.bin: size 17 bytes is not a multiple of 16")

    _add_command(monkeypatch, boom)
    r = CliRunner().invoke(cli, ["boom"])
    assert r.exit_code == 1
    assert r.stderr.strip() == "Error: 000000.bin: size 17 bytes is not a multiple of 16"
    assert "Traceback" not in r.output


def test_debug_shows_the_exception(monkeypatch):
    @click.command()
    def boom():
        """Raise a library error."""
        raise FormatError("bad")

    _add_command(monkeypatch, boom)
    r = CliRunner().invoke(cli, ["--debug", "boom"])
    assert r.exit_code == 1 and r.stderr.startswith("Error: bad")
    assert "Traceback" in r.stderr and "FormatError: bad" in r.stderr


def test_usage_error_is_exit_2():
    r = CliRunner().invoke(cli, ["synth-scene"])
    assert r.exit_code == 2 and "Missing option" in r.stderr
    r = CliRunner().invoke(cli, ["no-such-command"])
    assert r.exit_code == 2
