"""Every batch command writes what sparsetools 0.2.0 wrote, records what it recorded, and
resumes a folder that 0.2.0 made.

The expected values are ``tests/golden/v0.2.0.json``, made by the 0.2.0 code itself
(``PYTHONPATH=<0.2.0 checkout>/src python tests/golden/make_golden.py``) from one canonical
invocation per command (``tests/golden/cases.py``); today's code runs the same invocation in
today's spelling of the options.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from golden.canon import digests, record  # noqa: E402
from golden.cases import CASES, DERIVED, make_raw_tree  # noqa: E402

GOLDEN = json.loads((ROOT / "tests" / "golden" / "v0.2.0.json").read_text())
REAL = ROOT.parent / "shared" / "data" / "real"


def expand(args, data: Path, out: Path) -> list[str]:
    return [a.format(S=ROOT / "sample_data" / "synthetic", K=ROOT / "sample_data" / "kitti",
                     D=data, O=out, R=REAL) for a in args]  # fmt: skip


def substitutions(data: Path, out: Path) -> dict[str, str]:
    subs = {}
    for path, name in ((ROOT, "{ROOT}"), (data, "{D}"), (out, "{O}"),
                       (ROOT.parent / "shared", "{SHARED}")):  # fmt: skip
        subs[str(path)] = name
        subs[str(path.resolve())] = name
    return subs


def run(args) -> dict:
    r = CliRunner().invoke(cli, ["-q", *args, "--json"])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("derived")
    have_real = REAL.is_dir()
    if have_real:
        make_raw_tree(REAL, root / "raw")
    for name, args in DERIVED.items():
        if "{D}/raw" in " ".join(args) and not have_real:
            continue
        run(expand(args, root, root / name))
    return root


def _case(name: str) -> dict:
    case = CASES[name]
    if case.get("real") and not REAL.is_dir():
        pytest.skip("needs ../shared/data/real (absent on this machine)")
    return case


#: Outputs that differ from 0.2.0's on purpose, by case: (path prefix, why). Their files must
#: still all be there, under the same names, and decode; their bytes are not compared.
CHANGED_SINCE_020 = {
    "dark_channel": (
        ("pictures/", "labels drawn once (0.2.0 drew each twice, offset, and read garbled)"),
    ),
}


#: What 0.2.0 itself wrote differently on another kind of machine, by case: file -> digest.
#: A few floating-point results round differently from one CPU to another (vectorised
#: kernels of the libraries), so bytes are reproducible on one machine, not across machines.
#: Made 2026-12-03 by ``make_golden.py`` with the 0.2.0 code on a 2-core AVX-512 Xeon VM:
#: every other file and every record of every case was the same as in ``v0.2.0.json``.
OTHER_MACHINE = {
    "lowlight": {
        "000002_v1.png": "e8d95f165943a38f3ab393cb768fe57036bbc85800cd270a35939a8f85e682b7"
    },
}


def assert_outputs_as_020(name: str, out: Path, subs: dict[str, str]) -> None:
    """The files 0.2.0 wrote (on this kind of machine: :data:`OTHER_MACHINE`), byte for byte,
    but those of :data:`CHANGED_SINCE_020`."""
    import cv2

    golden = GOLDEN["cases"][name]["digests"]
    other = {**golden, **OTHER_MACHINE.get(name, {})}
    if other != golden and digests(out, subs) == {k: other[k] for k in golden}:
        golden = other  # all of this kind of machine's files, not a mix of the two
    ours = digests(out, subs)
    assert sorted(ours) == sorted(golden)
    changed = [prefix for prefix, _why in CHANGED_SINCE_020.get(name, ())]
    for rel in list(ours):
        if any(rel.startswith(p) for p in changed):
            assert cv2.imread(str(out / rel)) is not None, rel
            assert ours.pop(rel) != golden[rel], f"{rel} is 0.2.0's again: update the list"
    assert ours == {k: v for k, v in golden.items() if k in ours}


@pytest.mark.parametrize("name", sorted(CASES))
def test_same_bytes_and_record_as_020(name, data, tmp_path):
    case = _case(name)
    out = tmp_path / name
    run(expand(case["new"], data, out))
    subs = substitutions(data, out)
    golden = GOLDEN["cases"][name]
    assert_outputs_as_020(name, out, subs)
    rec = record(out, subs)
    assert rec["run"]["command"] == golden["record"]["run"]["command"]
    assert rec["run"]["settings"] == golden["record"]["run"]["settings"]
    assert rec["frames"] == golden["record"]["frames"]


@pytest.mark.parametrize("name", sorted(CASES))
def test_a_folder_made_by_020_resumes(name, data, tmp_path):
    """Today's outputs with 0.2.0's record (run record, outputs and statistics per frame; the
    input identities are this machine's): the same command is a no-op."""
    case = _case(name)
    out = tmp_path / name
    args = expand(case["new"], data, out)
    first = run(args)
    golden = GOLDEN["cases"][name]["record"]
    rec = out / ".sparsetools"
    if golden:
        subs = {v: k for k, v in substitutions(data, out).items()}  # placeholders back
        old_run = json.loads(_unsubst(json.dumps(golden["run"]), subs))
        (rec / "run.json").write_text(json.dumps(old_run, indent=1, sort_keys=True) + "\n")
        lines = []
        for line in (rec / "frames.jsonl").read_text().splitlines():
            d = json.loads(line)
            d.pop("output_ids", None)  # 0.2.0 recorded no output identities
            old = json.loads(_unsubst(json.dumps(golden["frames"][d["key"]]), subs))
            lines.append(json.dumps({**d, **old}, sort_keys=True))
        (rec / "frames.jsonl").write_text("\n".join(lines) + "\n")
    before = digests(out, {})
    again = run(args)
    tasks = first.get("segments", first["frames"])
    assert again["processed"] == 0 and again["skipped_existing"] == tasks
    assert digests(out, {}) == before


def _unsubst(text: str, subs: dict[str, str]) -> str:
    for placeholder, path in subs.items():
        text = text.replace(placeholder, path)
    return text


_RENAMED = sorted(n for n, c in CASES.items() if c["old"] != c["new"])


@pytest.mark.parametrize("name", _RENAMED)
def test_the_old_spellings_still_work_and_warn_once(name, data, tmp_path):
    """0.2.0's spelling of each renamed option writes the same bytes, with one deprecation
    line per old spelling used."""
    case = _case(name)
    out = tmp_path / name
    r = CliRunner().invoke(cli, [*expand(case["old"], data, out), "--json"])
    assert r.exit_code == 0, r.output
    subs = substitutions(data, out)
    assert_outputs_as_020(name, out, subs)
    warned = [ln for ln in r.stderr.splitlines() if "deprecated:" in ln]
    old_only = [a for a in case["old"] if a.startswith("-") and a not in case["new"]]
    crop = [a for a in case["old"] if "," in a and a.count(",") == 3]  # TOP,LEFT,H,W text
    assert len(warned) == len(old_only) + len(crop), r.stderr
    assert len(set(warned)) == len(warned)
