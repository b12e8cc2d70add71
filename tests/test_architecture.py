"""The structure of DESIGN.md, enforced: layers, module sizes, no file I/O in ops/ (one
declaration per option: tests/test_vocabulary.py)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src" / "sparsetools"
#: A module holds one concern; past this many lines it holds several (DESIGN.md).
MAX_LINES = 700


def test_import_layers_hold():
    """import-linter's contracts in pyproject.toml: no upward import, ops/ never imports io/."""
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "importlinter.cli"]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "0 broken" in r.stdout


def test_an_upward_import_would_be_caught(tmp_path):
    """The contract is live: a copy of the package with ops importing io breaks it."""
    import shutil

    pkg = tmp_path / "src"
    shutil.copytree(SRC, pkg / "sparsetools", ignore=shutil.ignore_patterns("__pycache__"))
    bad = pkg / "sparsetools" / "ops" / "projection.py"
    bad.write_text(bad.read_text() + "\nfrom ..io import atomic  # noqa\n")
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "importlinter.cli"]
    env = {"PYTHONPATH": str(pkg), "PATH": "/usr/bin:/bin"}
    r = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode != 0
    assert "sparsetools.ops.projection -> sparsetools.io.atomic" in r.stdout


def test_no_module_is_over_the_size_limit():
    sizes = {
        p.relative_to(ROOT).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
        for p in SRC.rglob("*.py")
    }
    big = {k: v for k, v in sizes.items() if v > MAX_LINES}
    assert not big, f"modules over {MAX_LINES} lines (split them by concern): {big}"


@pytest.mark.parametrize("layer", ["ops"])
def test_ops_has_no_file_io(layer):
    """ops/ kernels do no file I/O (no open(), no Path reads and writes, no numpy file calls)."""
    pattern = re.compile(
        r"\bopen\(|\.read_(text|bytes)\(|\.write_(text|bytes)\(|np\.(load|save|fromfile)\b"
        r"|importlib\.resources"
    )
    offenders = []
    for p in (SRC / layer).rglob("*.py"):
        for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
            code = line.split("#", 1)[0]
            if pattern.search(code):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)
