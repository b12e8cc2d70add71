"""One way to do one thing, enforced (issue 22): one batch entry point, one validation
vocabulary, one spelling per option meaning and one syntax for sizes and crops.

Each test reads the code or the command tree and fails on the first counter-example; the
``*_would_be_caught`` tests check the checks on a planted counter-example.
"""

from __future__ import annotations

import ast
import inspect
import re
from pathlib import Path

import click
import pytest

from sparsetools.cli.main import cli
from sparsetools.cli.options import DEPRECATED

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src" / "sparsetools"

#: The one syntax of a size and of a crop box on the command line (sparsetools.validate).
SIZE_METAVAR = "WxH"
CROP_METAVAR = "WxH+LEFT+TOP"
#: A metavar that spells a size or a box some other way (``HxW``, ``TOP,LEFT,H,W``).
_SIZE_LIKE = re.compile(r"\b[A-Z]+x[A-Z]+\b|TOP|LEFT")


def _commands():
    ctx = click.Context(cli)
    out = []

    def walk(cmd, path):
        if isinstance(cmd, click.Group):
            for name in cmd.list_commands(ctx):
                walk(cmd.get_command(ctx, name), [*path, name])
            return
        out.append((" ".join(path), cmd))

    for name in cli.list_commands(ctx):
        walk(cli.get_command(ctx, name), [name])
    return out


COMMANDS = _commands()


# -- one entry point for batch jobs ----------------------------------------------------------------


def _calls(tree: ast.AST, name: str) -> list[int]:
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            called = f.id if isinstance(f, ast.Name) else getattr(f, "attr", None)
            if called == name:
                lines.append(node.lineno)
    return lines


def test_only_run_job_calls_the_frame_runner():
    """``run_frames`` is called by ``run_job`` alone: every batch command goes through it."""
    offenders = []
    for p in SRC.rglob("*.py"):
        tree = ast.parse(p.read_text(encoding="utf-8"))
        for line in _calls(tree, "run_frames"):
            if p.name != "core.py":
                offenders.append(f"{p.relative_to(ROOT)}:{line}")
    assert not offenders, offenders


def test_every_batch_command_body_calls_run_job():
    """A command with the batch options hands its job to ``run_job`` (directly, or through a
    dataset route that does)."""
    routes = {"dataset build", "dataset kitti-raw", "dataset kitti-dc", "dataset nuscenes"}
    missing = []
    for name, cmd in COMMANDS:
        if not any(p.name == "on_error" for p in cmd.params) or name in routes:
            continue
        fn = inspect.unwrap(cmd.callback)
        source = Path(fn.__code__.co_filename).read_text(encoding="utf-8")
        func = next(n for n in ast.walk(ast.parse(source))
                    if isinstance(n, ast.FunctionDef) and n.name == fn.__name__)  # fmt: skip
        if not _calls(func, "run_job"):
            missing.append(name)
    assert not missing, f"batch commands that do not call run_job: {missing}"


_JOB_MODULES = ("project", "beams", "jbf_expand", "lowlight", "equalize", "dark_channel",
                "defocus", "underwater", "densify", "accumulate", "camera_images", "export")  # fmt: skip


@pytest.mark.parametrize("module", _JOB_MODULES)
def test_no_job_module_imports_another(module):
    """Discovery lives in io/sources; a job module imports no other job module."""
    tree = ast.parse((SRC / "pipeline" / f"{module}.py").read_text(encoding="utf-8"))
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
            imported.add(node.module.split(".")[0])
    others = imported & (set(_JOB_MODULES) - {module})
    assert not others, f"pipeline/{module}.py imports {sorted(others)}"


# -- one validation vocabulary -------------------------------------------------------------------

_HAND_RULE = re.compile(r"raise (ParameterError|click\.BadParameter)\(\s*f?[\"'][^\"']*\bmust be\b")


def _hand_written_rules(folder: Path) -> list[str]:
    found = []
    for p in folder.rglob("*.py"):
        text = p.read_text(encoding="utf-8")
        for m in _HAND_RULE.finditer(text):
            found.append(f"{p}:{text.count(chr(10), 0, m.start()) + 1}")
    return found


@pytest.mark.parametrize("layer", ["pipeline", "cli"])
def test_rules_are_stated_in_validate_only(layer):
    """No ``raise ParameterError(f"... must be ...")`` outside validate.py in pipeline/ and
    cli/: a rule is applied through sparsetools.validate, so it reads the same everywhere."""
    assert not _hand_written_rules(SRC / layer)


def test_a_hand_written_rule_would_be_caught(tmp_path):
    (tmp_path / "bad.py").write_text('def f(x):\n    raise ParameterError(f"x must be > 0")\n')
    assert len(_hand_written_rules(tmp_path)) == 1


# -- one spelling per meaning, one syntax per kind of value ---------------------------------------

_DECLARED = re.compile(r"""click\.option\(\s*(?:"-\w",\s*)?"(--[a-z0-9-]+)""")


def _declarations() -> dict[str, list[str]]:
    where: dict[str, list[str]] = {}
    for p in sorted((SRC / "cli").glob("*.py")):
        for name in _DECLARED.findall(p.read_text(encoding="utf-8")):
            where.setdefault(name, []).append(p.name)
    return where


def test_each_option_name_is_declared_once():
    """An option name has one declaration (shared ones in cli/options.py), hence one meaning,
    one type and one help text in every command that has it."""
    twice = {k: v for k, v in _declarations().items() if len(v) > 1}
    assert not twice, f"option names declared more than once: {twice}"


def test_a_second_declaration_would_be_caught(monkeypatch, tmp_path):
    import tests.test_vocabulary as me  # noqa: F401 - the module under test, for its regex

    text = 'click.option("--window", type=int)\nclick.option(\n    "--window", type=float)\n'
    assert _DECLARED.findall(text) == ["--window", "--window"]


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_sizes_and_crops_have_one_syntax(name, cmd):
    """Every option taking a size reads ``WxH`` and every crop ``WxH+LEFT+TOP``."""
    for p in cmd.params:
        if not isinstance(p, click.Option) or p.hidden:
            continue
        metavar = p.metavar or ""
        if _SIZE_LIKE.search(metavar):
            assert metavar in (SIZE_METAVAR, CROP_METAVAR), f"{name} {p.opts[0]}: {metavar}"


def test_another_size_syntax_would_be_caught():
    assert _SIZE_LIKE.search("HxW") and _SIZE_LIKE.search("TOP,LEFT,H,W")
    assert not _SIZE_LIKE.search("N[,N...]") and not _SIZE_LIKE.search("A,B,...")


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_hidden_options_are_registered_deprecated_aliases(name, cmd):
    """The only hidden options are the old spellings kept for one release."""
    for p in cmd.params:
        if isinstance(p, click.Option) and p.hidden:
            assert (name, p.opts[0]) in DEPRECATED, f"{name} {p.opts[0]}"


def test_help_examples_use_no_deprecated_spelling():
    """--help teaches the new names: no example line uses an old spelling."""
    offenders = []
    for name, cmd in COMMANDS:
        text = cmd.help or ""
        for (command, old), new in DEPRECATED.items():
            if command != name:
                continue
            for line in text.splitlines():
                if line.strip().startswith("sparsetools") and re.search(
                    rf"(?<![\w-]){re.escape(old)}(?![\w-])", line
                ):
                    offenders.append(f"{name}: {line.strip()} ({old} -> {new})")
    assert not offenders, offenders
