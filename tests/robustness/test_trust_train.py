"""Provenance of training runs (issue 23): every run has a run id, in config.json, in every
checkpoint and in every metrics.csv row, and ``train --resume`` continues a checkpoint only in
its own run's folder. Before, ``--resume`` continued another run's ``last.pt`` placed in the
folder (another width, other inputs) and mixed the two runs' metrics in one metrics.csv.

Each refusal has a test here that goes red when its guard (in
``sparsetools.train.checkpoint.resume_run_id``) is disabled; docs/reliability.md lists them.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
import sys
from pathlib import Path

import pytest
import torch
from cli_helpers import assert_one_error_line, invoke

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))

from test_train import make_dataset  # noqa: E402

TINY = ["--width", "4", "--batch-size", "4", "--epochs", "1", "--threads", "1", "--pictures", "0"]
RUN_ID = re.compile(r"[0-9a-f]{32}")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("trust_train_ds"), n_seq=5, frames=2)


@pytest.fixture(scope="module")
def runs(dataset, tmp_path_factory) -> dict:
    """Two runs stopped after one step, inside their first epoch: ``a`` (width 4) and ``b``
    (width 8), with the summaries their commands printed."""
    root = tmp_path_factory.mktemp("trust_train_runs")
    out = {}
    for name, width in (("a", "4"), ("b", "8")):
        r = invoke(["train", dataset, "-o", root / name, *TINY, "--width", width,
                    "--max-steps", "1", "--json"])  # fmt: skip
        assert r.exit_code == 0, r.output
        out[name] = (root / name, json.loads(r.stdout))
    return out


def copy_run(runs: dict, name: str, tmp_path: Path) -> Path:
    run = tmp_path / name
    shutil.copytree(runs[name][0], run)
    return run


def run_id(run: Path) -> str:
    return json.loads((run / "config.json").read_text())["run_id"]


def metrics_rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def checkpoint_id(path: Path):
    return torch.load(path, weights_only=True).get("run_id")


def snapshot(folder: Path) -> dict:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def resume(dataset, run: Path, epochs: int = 1):
    return invoke(["train", dataset, "-o", run, "--resume", "--epochs", epochs, "--threads", 1])


def as_v020(run: Path, *, config: bool = True) -> None:
    """Make a run look written by sparsetools 0.2.0: no run id in its checkpoints, its
    metrics.csv (and, with ``config``, its config.json)."""
    for name in ("last.pt", "best.pt"):
        raw = torch.load(run / name, weights_only=True)
        raw.pop("run_id")
        torch.save(raw, run / name)
    rows = metrics_rows(run)
    columns = [c for c in rows[0] if c != "run_id"]
    with open(run / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, columns, extrasaction="ignore", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    if config:
        saved = json.loads((run / "config.json").read_text())
        saved.pop("run_id")
        (run / "config.json").write_text(json.dumps(saved))


# -- every run has its own id, everywhere -----------------------------------------------------------
def test_every_run_has_its_own_id_in_every_file(runs):
    (a, summary_a), (b, _) = runs["a"], runs["b"]
    ida = run_id(a)
    assert RUN_ID.fullmatch(ida) and ida != run_id(b)
    assert summary_a["run_id"] == ida
    assert checkpoint_id(a / "last.pt") == checkpoint_id(a / "best.pt") == ida
    assert {r["run_id"] for r in metrics_rows(a)} == {ida}


def test_resume_continues_under_the_run_id(runs, dataset, tmp_path):
    run = copy_run(runs, "a", tmp_path)
    ida = run_id(run)
    r = resume(dataset, run, epochs=2)
    assert r.exit_code == 0, r.output
    assert run_id(run) == ida and checkpoint_id(run / "last.pt") == ida
    rows = metrics_rows(run)
    assert len(rows) == 2 and {r["run_id"] for r in rows} == {ida}


def test_resume_without_config_json_uses_the_checkpoints_id(runs, dataset, tmp_path):
    run = copy_run(runs, "a", tmp_path)
    ida = run_id(run)
    (run / "config.json").unlink()
    assert resume(dataset, run).exit_code == 0
    assert run_id(run) == ida


# -- another run's files are refused ----------------------------------------------------------------
def test_resume_refuses_another_runs_last_pt(runs, dataset, tmp_path):
    """b's last.pt (width 8) in a's folder: refused before anything is written."""
    run = copy_run(runs, "a", tmp_path)
    shutil.copy(runs["b"][0] / "last.pt", run / "last.pt")
    before = snapshot(run)
    msg = assert_one_error_line(resume(dataset, run), "--resume continues a run in its own folder")
    assert run_id(run) in msg and run_id(runs["b"][0]) in msg
    assert snapshot(run) == before


def test_resume_refuses_a_metrics_csv_of_another_run(runs, dataset, tmp_path):
    run = copy_run(runs, "a", tmp_path)
    shutil.copy(runs["b"][0] / "metrics.csv", run / "metrics.csv")
    before = snapshot(run)
    msg = assert_one_error_line(resume(dataset, run), "metrics.csv belongs to run")
    assert run_id(runs["b"][0]) in msg and run_id(run) in msg
    assert snapshot(run) == before


def test_resume_refuses_a_config_json_of_another_run(runs, dataset, tmp_path):
    run = copy_run(runs, "a", tmp_path)
    ida = run_id(run)
    shutil.copy(runs["b"][0] / "config.json", run / "config.json")
    before = snapshot(run)
    msg = assert_one_error_line(resume(dataset, run), "config.json to run")
    assert ida in msg and run_id(runs["b"][0]) in msg
    assert snapshot(run) == before


@pytest.mark.parametrize("value", [None, "line one\nline two", 5])
def test_resume_refuses_a_config_json_naming_no_run_or_a_strange_one(
    runs, dataset, tmp_path, value
):
    """A readable config.json must name the checkpoint's run (0.2.0's named none); whatever it
    holds instead is shown on one line."""
    run = copy_run(runs, "a", tmp_path)
    saved = json.loads((run / "config.json").read_text())
    if value is None:
        saved.pop("run_id")
    else:
        saved["run_id"] = value
    (run / "config.json").write_text(json.dumps(saved))
    assert_one_error_line(resume(dataset, run), "config.json to run")


def test_resume_refuses_a_best_pt_of_another_run(runs, dataset, tmp_path):
    """best.pt is what `eval RUN` evaluates: another run's would pass for this run's best."""
    run = copy_run(runs, "a", tmp_path)
    shutil.copy(runs["b"][0] / "best.pt", run / "best.pt")
    before = snapshot(run)
    msg = assert_one_error_line(resume(dataset, run), "best.pt belongs to run")
    assert run_id(runs["b"][0]) in msg and run_id(run) in msg
    assert snapshot(run) == before


def test_a_checkpoint_of_0_2_0_in_a_run_of_this_version_is_refused(runs, dataset, tmp_path):
    old = copy_run(runs, "b", tmp_path)
    as_v020(old)
    run = copy_run(runs, "a", tmp_path)
    shutil.copy(old / "last.pt", run / "last.pt")
    msg = assert_one_error_line(resume(dataset, run), "belongs to run")
    assert "none (sparsetools 0.2.0)" in msg and run_id(run) in msg


def test_a_malformed_run_id_is_refused(runs, dataset, tmp_path):
    run = copy_run(runs, "a", tmp_path)
    raw = torch.load(run / "last.pt", weights_only=True)
    raw["run_id"] = "../" * 20
    torch.save(raw, run / "last.pt")
    assert_one_error_line(resume(dataset, run), "run_id must be 32 hex digits")


# -- runs of 0.2.0 (no run id) still resume ---------------------------------------------------------
def test_a_run_of_0_2_0_resumes_and_gets_a_run_id(runs, dataset, tmp_path):
    run = copy_run(runs, "a", tmp_path)
    as_v020(run)
    r = resume(dataset, run)
    assert r.exit_code == 0, r.output
    rid = run_id(run)
    assert RUN_ID.fullmatch(rid) and checkpoint_id(run / "last.pt") == rid
    assert {r["run_id"] for r in metrics_rows(run)} == {rid}
    r = resume(dataset, run, epochs=2)  # and on: one run, one id
    assert r.exit_code == 0, r.output
    assert run_id(run) == rid and {r["run_id"] for r in metrics_rows(run)} == {rid}


def test_a_run_of_0_2_0_stopped_after_its_adoption_keeps_its_new_id(runs, dataset, tmp_path):
    """A 0.2.0 run resumed by this version writes config.json with its new id first; stopped
    before its first epoch ended, its checkpoint and metrics.csv are still 0.2.0's: it resumes,
    under the id config.json names."""
    run = copy_run(runs, "a", tmp_path)
    rid = run_id(run)
    as_v020(run, config=False)
    r = resume(dataset, run)
    assert r.exit_code == 0, r.output
    assert run_id(run) == rid and checkpoint_id(run / "last.pt") == rid
