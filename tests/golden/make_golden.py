"""Write ``tests/golden/v0.2.0.json``: what sparsetools 0.2.0 wrote for every batch command.

Run with the 0.2.0 code (``git worktree add /tmp/v020 aeafbc4``), from the checkout whose
golden file it makes::

    PYTHONPATH=/tmp/v020/src python tests/golden/make_golden.py

For each case (one canonical invocation of a batch command on ``sample_data/``) it records
the sha256 of every file the command wrote (``.sparsetools/`` left out), the folder's run
record (command, version, settings) and, per frame, the recorded outputs and statistics.
``tests/test_compat_v020.py`` runs the same invocations with the current code (new option
spellings) and checks the same bytes, the same record and that a folder of 0.2.0 resumes.
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

from click.testing import CliRunner

ROOT = Path(__file__).resolve().parent.parent.parent
sys.path.insert(1, str(ROOT / "tests"))

from golden.canon import digests, record  # noqa: E402
from golden.cases import CASES, DERIVED, make_raw_tree  # noqa: E402
from sparsetools.cli.main import cli  # noqa: E402


def expand(args: list[str], data: Path, out: Path) -> list[str]:
    return [a.format(S=ROOT / "sample_data" / "synthetic", K=ROOT / "sample_data" / "kitti",
                     D=data, O=out, R=ROOT.parent / "shared" / "data" / "real")
            for a in args]  # fmt: skip


def substitutions(data: Path, out: Path) -> dict[str, str]:
    """Absolute paths -> placeholders (resolved and as given, both)."""
    subs = {}
    for path, name in ((ROOT, "{ROOT}"), (data, "{D}"), (out, "{O}"),
                       (ROOT.parent / "shared", "{SHARED}")):  # fmt: skip
        subs[str(path)] = name
        subs[str(path.resolve())] = name
    return subs


def main() -> None:
    import sparsetools

    golden = {"version": sparsetools.__version__, "cases": {}}
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        data.mkdir()
        make_raw_tree(ROOT.parent / "shared" / "data" / "real", data / "raw")
        for name, args in DERIVED.items():
            r = CliRunner().invoke(cli, ["-q", *expand(args, data, data / name)])
            assert r.exit_code == 0, (name, r.output)
        for name, case in CASES.items():
            out = Path(tmp) / "out" / name
            r = CliRunner().invoke(cli, ["-q", *expand(case["old"], data, out), "--json"])
            assert r.exit_code == 0, (name, r.output)
            subs = substitutions(data, out)
            golden["cases"][name] = {
                "digests": digests(out, subs),
                "record": record(out, subs),
                "summary_keys": sorted(json.loads(r.stdout)),
            }
            shutil.rmtree(out)
            print(name, len(golden["cases"][name]["digests"]), "files", flush=True)
    target = Path(__file__).with_name(f"v{golden['version']}.json")
    target.write_text(json.dumps(golden, indent=1, sort_keys=True) + "\n")
    print("wrote", target)


if __name__ == "__main__":
    main()
