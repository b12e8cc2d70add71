"""Hardening, round 2, the `train` / `eval` part: nothing of the user's replaced, checkpoints and
configurations validated before anything is built from them, one `Error:` line (and nothing
else on stderr) for every bad checkpoint, no torch needed for `eval --pred`.

Every case here failed before the fix (a replaced user file, a traceback, torch's warnings on
stderr, an attempted allocation of terabytes, ``ModuleNotFoundError``) and passes after it,
except three marked "guard": behaviour that already held and must keep holding beside the new
refusals (a run that stopped in its first epoch starts again; an edited config.json does not
matter to --resume; pickles inside torch's zip or legacy format were already refused).
"""

from __future__ import annotations

import json
import pickle
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_helpers import assert_no_traceback, assert_one_error_line, invoke

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))

from sparsetools.io.image import write_depth_png  # noqa: E402
from test_train import make_dataset  # noqa: E402

TINY = ["--width", "4", "--batch-size", "4", "--epochs", "1", "--threads", "1", "--pictures", "1"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("hardening_ds"), n_seq=5, frames=2)


@pytest.fixture(scope="module")
def run_dir(dataset, tmp_path_factory) -> Path:
    """A one-step run (``last.pt``, ``best.pt``) to corrupt copies of."""
    run = tmp_path_factory.mktemp("hardening_run") / "run"
    r = invoke(["train", dataset, "-o", run, *TINY, "--max-steps", "1"])
    assert r.exit_code == 0, r.output
    return run


def tampered(run_dir: Path, tmp_path: Path, change) -> Path:
    """A copy of the run whose two checkpoints went through ``change(raw_dict)``."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    for name in ("last.pt", "best.pt"):
        raw = torch.load(run / name, weights_only=True)
        change(raw)
        torch.save(raw, run / name)
    return run


def run_cli(*args) -> subprocess.CompletedProcess:
    """``sparsetools ARGS`` in a fresh interpreter: what a user sees on stderr, torch's own
    warnings included (pytest would capture those in-process)."""
    return subprocess.run(
        [sys.executable, "-m", "sparsetools.cli.main", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
    )


# -- 2. user files: eval -o and train -o ---------------------------------------------------------


def test_eval_never_replaces_a_file_it_did_not_write(dataset, run_dir, tmp_path):
    mine = tmp_path / "mine.json"
    mine.write_text("my notes\n")
    r = invoke(["eval", "--checkpoint", run_dir, dataset, "-o", mine])
    line = assert_one_error_line(r, "was not written by this command")
    assert "mine.json" in line and "--overwrite" in line
    assert mine.read_text() == "my notes\n" and not (tmp_path / "mine.csv").exists()
    # the CSV sibling is a result file too
    (tmp_path / "other.csv").write_text("a,b\n")
    r = invoke(["eval", "--checkpoint", run_dir, dataset, "-o", tmp_path / "other.json"])
    assert "other.csv" in assert_one_error_line(r, "--overwrite")
    assert (tmp_path / "other.csv").read_text() == "a,b\n"
    assert not (tmp_path / "other.json").exists()  # refused before anything was written
    # --overwrite replaces them; eval then replaces its own results without it
    r = invoke(["eval", "--checkpoint", run_dir, dataset, "-o", mine, "--overwrite", "--json"])
    assert r.exit_code == 0, r.output
    assert "rmse" in json.loads(mine.read_text())["metrics"]
    r = invoke(["eval", "--checkpoint", run_dir, dataset, "-o", mine, "--garg-crop", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(mine.read_text())["garg_crop"] is True


def test_eval_default_output_beside_the_checkpoint_is_checked_too(dataset, run_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    mine = run / f"eval_{Path(dataset).name}_test.json"  # the default name for this dataset
    mine.write_text("{}\n")
    r = invoke(["eval", "--checkpoint", run, dataset])
    assert mine.name in assert_one_error_line(r, "--overwrite")
    assert mine.read_text() == "{}\n"


def test_eval_pred_never_replaces_a_file_it_did_not_write(tmp_path):
    for d in ("pred", "gt"):
        write_depth_png(tmp_path / d / "000001.png", np.full((6, 8), 20.0))
    mine = tmp_path / "m.csv"
    mine.write_text("mine\n")
    r = invoke(["eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt", "-o", mine])
    assert "m.csv" in assert_one_error_line(r, "was not written by this command")
    assert mine.read_text() == "mine\n"
    r = invoke(["eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt", "-o", mine,
                "--overwrite"])  # fmt: skip
    assert r.exit_code == 0 and mine.read_text().startswith("id,")


@pytest.mark.parametrize("name", ["curves.png", "config.json", "predictions"])
def test_train_never_replaces_files_in_a_folder_that_holds_no_run(dataset, tmp_path, name):
    out = tmp_path / "out"
    out.mkdir()
    target = out / name
    if name == "predictions":
        target.mkdir()
        (target / "epoch_001.png").write_bytes(b"mine")
    else:
        target.write_bytes(b"mine")
    r = invoke(["train", dataset, "-o", out, *TINY, "--max-steps", "1"])
    assert name in assert_one_error_line(r, "was not written by a training run")
    assert sorted(p.name for p in out.iterdir()) == [name]


def test_train_starts_again_over_a_run_that_stopped_before_its_first_checkpoint(
    dataset, run_dir, tmp_path
):
    """Guard: the refusal above leaves a run's own config.json alone."""
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(run_dir / "config.json", out / "config.json")  # what such a run leaves
    r = invoke(["train", dataset, "-o", out, *TINY, "--max-steps", "1"])
    assert r.exit_code == 0, r.output
    assert (out / "last.pt").is_file()


# -- 3. checkpoints and configurations -----------------------------------------------------------


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("width", "4", "width must be an integer"),
        ("width", [4], "width must be an integer"),
        ("width", -4, "width must be an integer from 1 to 256"),
        ("width", True, "width must be an integer"),
        ("width", 10**9, "width must be an integer from 1 to 256"),  # ~1e22 parameters
        ("width", 257, "from 1 to 256"),
        ("width", 8, "do not fit its configuration"),  # in range, but not these weights
        ("final_layer", "yes", "final_layer must be true or false"),
        ("input_mode", ["rgbd"], "unknown input mode"),
        ("lidar_encoder", "sfe", "do not fit its configuration"),
        ("depth_range", "far", "depth_range"),
    ],
)
def test_bad_model_config_is_one_line_for_eval_and_resume(
    dataset, run_dir, tmp_path, key, value, match
):
    def change(raw):
        raw["model_config"][key] = value

    run = tampered(run_dir, tmp_path, change)
    assert_one_error_line(invoke(["eval", "--checkpoint", run, dataset]), match)
    r = invoke(["train", dataset, "-o", run, "--resume", "--epochs", "2", "--threads", "1"])
    assert_one_error_line(r, match)


def test_model_config_that_is_not_a_mapping_is_one_line(dataset, run_dir, tmp_path):
    def change(raw):
        raw["model_config"] = ["rgbd", 4]

    run = tampered(run_dir, tmp_path, change)
    assert_one_error_line(invoke(["eval", "--checkpoint", run, dataset]), "model_config")


def _set_config(key, value):
    def change(raw):
        if key is None:
            raw["config"] = value
        elif value is KeyError:
            del raw["config"][key]
        else:
            raw["config"][key] = value

    return change


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (_set_config(None, "garbage"), "must be a mapping"),
        (_set_config(None, [1, 2, 3]), "must be a mapping"),
        (_set_config("width", "abc"), "width must be an integer"),
        (_set_config("lr", [1]), "lr must be a number"),
        (_set_config("epochs", True), "epochs must be an integer"),
        (_set_config("crop", "64x64"), "crop must be null or two integers"),
        (_set_config("dataset", KeyError), "lacks 'dataset'"),
        (_set_config("width", 8), "its training configuration says width 8"),
        (_set_config("selfsup", "on"), "must be a mapping"),
    ],
)
def test_resume_with_a_corrupt_config_is_one_line(dataset, run_dir, tmp_path, change, match):
    run = tampered(run_dir, tmp_path, change)
    r = invoke(["train", dataset, "-o", run, "--resume", "--epochs", "2", "--threads", "1"])
    assert_one_error_line(r, match)


@pytest.mark.parametrize(
    ("entry", "value", "match"),
    [
        ("rng", {}, "no valid torch RNG state"),
        ("rng", {"torch": torch.zeros(3)}, "no valid torch RNG state"),
        ("optimizer", {"state": {}, "param_groups": "all"}, "optimizer state"),
        ("history", "not a list", "incomplete checkpoint"),
        ("epoch", -1, "incomplete checkpoint"),
        ("version", "2", "version must be an integer"),
    ],
)
def test_resume_with_a_corrupt_training_state_is_one_line(
    dataset, run_dir, tmp_path, entry, value, match
):
    def change(raw):
        raw[entry] = value

    run = tampered(run_dir, tmp_path, change)
    r = invoke(["train", dataset, "-o", run, "--resume", "--epochs", "2", "--threads", "1"])
    assert_one_error_line(r, match)


def test_resume_with_an_optimizer_of_other_parameters_is_one_line(dataset, run_dir, tmp_path):
    def change(raw):
        raw["optimizer"]["param_groups"][0]["params"] = [0, 1]  # two parameters, not ~80

    run = tampered(run_dir, tmp_path, change)
    r = invoke(["train", dataset, "-o", run, "--resume", "--epochs", "2", "--threads", "1"])
    assert_one_error_line(r, "optimizer state does not fit")


def test_resume_uses_the_checkpoint_not_an_edited_config_json(dataset, run_dir, tmp_path):
    """Guard: ``last.pt`` holds the run's configuration; a config.json edited to garbage is
    rewritten from it."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    (run / "config.json").write_text("{garbage")
    r = invoke(["train", dataset, "-o", run, "--resume", "--epochs", "2", "--threads", "1"])
    assert r.exit_code == 0, r.output
    assert json.loads((run / "config.json").read_text())["width"] == 4


class _Opens:
    """Unpickling this (unsafely) would create a file: proof that code ran."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("kind", ["legacy-torch", "plain-pickle", "zip-with-object"])
def test_pickle_checkpoints_are_one_line_and_run_nothing(dataset, run_dir, tmp_path, kind):
    """plain-pickle printed torch's UserWarning before the error; the other two are guards."""
    marker = tmp_path / "code-ran"
    raw = torch.load(run_dir / "best.pt", weights_only=True)
    raw["extra"] = _Opens(str(marker))
    bad = tmp_path / "bad.pt"
    if kind == "legacy-torch":
        torch.save(raw, bad, _use_new_zipfile_serialization=False)
    elif kind == "plain-pickle":
        with open(bad, "wb") as f:
            pickle.dump(raw, f, protocol=4)  # torch warned about the protocol before the error
    else:
        torch.save(raw, bad)
    r = run_cli("eval", "--checkpoint", bad, dataset)
    assert r.returncode == 1, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.stderr
    assert "not a readable torch checkpoint" in lines[0]
    assert not marker.exists()


def test_legacy_format_of_a_valid_checkpoint_is_refused(dataset, run_dir, tmp_path):
    raw = torch.load(run_dir / "best.pt", weights_only=True)
    torch.save(raw, tmp_path / "old.pt", _use_new_zipfile_serialization=False)
    r = invoke(["eval", "--checkpoint", tmp_path / "old.pt", dataset])
    assert_one_error_line(r, "legacy pickle file")


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--width", "100000"], "width must be at most 256"),
        (["--seed", "-1"], "seed must be in [0, 2^63)"),
    ],
)
def test_train_options_out_of_bounds_are_one_line(dataset, tmp_path, args, match):
    r = invoke(["train", dataset, "-o", tmp_path / "run", *TINY, "--max-steps", "1", *args])
    assert_one_error_line(r, match)
    assert not (tmp_path / "run").exists()


# -- 3. without torch ------------------------------------------------------------------------------

_NO_TORCH = textwrap.dedent(
    """
    import importlib.abc, sys

    class NoTorch(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "torch" or name.startswith("torch."):
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, NoTorch())
    from sparsetools.cli.main import main

    main(sys.argv[1:])
    """
)


def without_torch(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", _NO_TORCH, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_train_and_eval_checkpoint_without_torch_name_the_extra(dataset, tmp_path):
    hint = "pip install 'sparsetools[train]'"
    r = without_torch("train", dataset, "-o", tmp_path / "run")
    assert (r.returncode, r.stderr) == (1, f"Error: train needs PyTorch: {hint}\n")
    assert not (tmp_path / "run").exists()
    r = without_torch("eval", "--checkpoint", tmp_path, dataset)
    assert (r.returncode, r.stderr) == (1, f"Error: eval --checkpoint needs PyTorch: {hint}\n")
    r = without_torch("train", "--help")
    assert r.returncode == 0 and "--input [rgb|rgbd|rgbdm|d|rgbdc|rgbdu]" in r.stdout


def test_eval_of_depth_files_needs_no_torch_and_gives_the_same_numbers(tmp_path):
    rng = np.random.default_rng(0)
    for i in range(3):
        gt = rng.uniform(2, 70, (12, 20)) * (rng.random((12, 20)) < 0.7)
        write_depth_png(tmp_path / "gt" / f"{i:06d}.png", gt)
        write_depth_png(tmp_path / "pred" / f"{i:06d}.png", np.clip(gt * 1.1 + 0.5, 1, 80))
    args = ["eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt", "--json"]
    r = without_torch(*args, "--garg-crop", "-o", tmp_path / "out" / "m.json")
    assert r.returncode == 0 and r.stderr == "", r.stderr
    alone = json.loads(r.stdout)
    with_torch = invoke([*args, "--garg-crop"])
    assert with_torch.exit_code == 0
    assert alone["metrics"] == json.loads(with_torch.stdout)["metrics"]
    # and the files it wrote hold the same per-image numbers as the straight metrics
    from sparsetools.io.depth_files import read_depth_file
    from sparsetools.ops.metrics import depth_metrics

    saved = json.loads((tmp_path / "out" / "m.json").read_text())
    for row in saved["per_image"]:
        ref = depth_metrics(
            read_depth_file(tmp_path / "pred" / f"{row['id']}.png"),
            read_depth_file(tmp_path / "gt" / f"{row['id']}.png"),
            garg_crop=True,
        )
        assert row["rmse"] == ref["rmse"] and row["delta1"] == ref["delta1"]


# -- 7. -q / --debug after the subcommand ----------------------------------------------------------


def test_quiet_and_debug_after_train_and_eval(dataset, run_dir, tmp_path):
    r = invoke(["train", dataset, "-o", tmp_path / "run", *TINY, "--max-steps", "1", "-q",
                "--debug"])  # fmt: skip
    assert r.exit_code == 0, r.output
    r = invoke(["eval", "--checkpoint", tmp_path / "run", dataset, "-q", "--debug"])
    assert r.exit_code == 0, r.output
    # --debug after the subcommand shows the traceback of an error
    r = invoke(["eval", "--checkpoint", tmp_path / "absent.pt", dataset, "--debug"])
    assert r.exit_code == 2 and "does not exist" in r.stderr  # click's own check comes first
    (tmp_path / "junk.pt").write_bytes(b"junk")
    r = invoke(["eval", "--checkpoint", tmp_path / "junk.pt", dataset, "--debug"])
    assert r.exit_code == 1 and "Traceback" in r.stderr
    r = invoke(["eval", "--checkpoint", tmp_path / "junk.pt", dataset, "-q"])
    assert_no_traceback(r)
