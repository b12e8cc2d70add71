"""`sparsetools train` and `sparsetools eval` through click: outputs, exit codes, messages."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch  # noqa: F401 - a required dependency of these tests
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.image import write_depth_png
from sparsetools.ops.metrics import METRIC_NAMES
from sparsetools.train.config import TrainConfig
from test_train import make_dataset

TINY = ["--width", "4", "--batch-size", "4", "--epochs", "1", "--threads", "1", "--pictures", "1"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("cli_train_ds"), n_seq=5, frames=2)


def run(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result


def one_line_error(result, code=1):
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 or (code == 2 and lines[-1].startswith("Error:")), result.stderr
    return lines[-1]


def snapshot(folder: Path) -> dict:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_train_then_eval(dataset, tmp_path):
    before = snapshot(dataset)
    out = tmp_path / "run"
    r = run("train", dataset, "-o", out, *TINY, "--json")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["epochs_done"] == 1 and summary["best_epoch"] == 1
    for name in ("metrics.csv", "last.pt", "best.pt", "curves.png", "config.json"):
        assert (out / name).is_file()
    config = json.loads((out / "config.json").read_text())
    assert config["width"] == 4 and config["input_mode"] == "rgbd"

    r = run("eval", "--checkpoint", out / "best.pt", dataset)
    assert r.exit_code == 0, r.output
    for k in METRIC_NAMES:
        assert any(line.startswith(k + " ") for line in r.stdout.splitlines()), k
    # named after the dataset and split (another dataset's results get files of their own)
    saved = json.loads((out / f"eval_{dataset.name}_test.json").read_text())
    assert set(METRIC_NAMES) <= set(saved["metrics"])
    assert saved["run_id"] == config["run_id"] == summary["run_id"]
    assert (out / f"eval_{dataset.name}_test.csv").read_text().splitlines()[-1].startswith("mean,")

    r = run(
        "eval",
        "--checkpoint",
        out,
        dataset,
        "--split",
        "val",
        "--json",
        "--garg-crop",
        "-o",
        tmp_path / "res.csv",
    )
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["split"] == "val" and data["garg_crop"] is True
    assert sorted(Path(p).name for p in data["written"]) == ["res.csv", "res.json"]
    assert snapshot(dataset) == before  # inputs untouched


def test_resume_continues(dataset, tmp_path):
    out = tmp_path / "run"
    assert run("train", dataset, "-o", out, *TINY).exit_code == 0
    r = run("train", dataset, "-o", out, *TINY)  # the same command again: up to date
    assert r.exit_code == 0 and "up to date (nothing trained)" in r.stderr, r.output
    r = run("train", dataset, "-o", out, *TINY, "--seed", "5")
    assert "already holds a run" in one_line_error(r)
    r = run("train", dataset, "-o", out, "--resume", "--epochs", "2", "--threads", "1", "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["epochs_done"] == 2
    assert len((out / "metrics.csv").read_text().splitlines()) == 3
    r = run("train", dataset, "-o", out, "--resume", "--epochs", "3", "--input", "rgb")
    assert "input mode 'rgbd', not 'rgb'" in one_line_error(r)


def test_eval_pred_folders(tmp_path):
    for d in ("pred", "gt"):
        (tmp_path / d).mkdir()
    write_depth_png(tmp_path / "gt" / "000001.png", np.full((6, 8), 20.0))
    write_depth_png(tmp_path / "pred" / "000001.png", np.full((6, 8), 22.0))
    r = run("eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt", "--json")
    assert r.exit_code == 0, r.output
    m = json.loads(r.stdout)["metrics"]
    assert m["abs_rel"] == pytest.approx(0.1)
    assert m["rmse"] == pytest.approx(2.0)
    assert not list(tmp_path.glob("*.json"))  # nothing written without -o
    r = run("eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt", "-o", tmp_path / "m")
    assert r.exit_code == 0
    assert (tmp_path / "m.json").is_file() and (tmp_path / "m.csv").is_file()
    write_depth_png(tmp_path / "gt" / "000002.png", np.full((6, 8), 20.0))
    r = run("eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt", "-o", tmp_path / "x")
    assert "no prediction" in one_line_error(r)
    assert not (tmp_path / "x.json").exists()


def test_bad_input_messages(dataset, tmp_path):
    nogt = make_dataset(tmp_path / "nogt", n_seq=2, frames=1, gt=False, split={"train": 1.0})
    r = run("train", nogt, "-o", tmp_path / "r1", *TINY, "--val-split", "train")
    assert "no ground truth" in one_line_error(r)
    assert not (tmp_path / "r1").exists()
    r = run("train", dataset, "-o", tmp_path / "r2", *TINY, "--val-split", "validation")
    assert "no samples in split 'validation'" in one_line_error(r)
    r = run("train", dataset, "-o", tmp_path / "r3", *TINY, "--crop-size", "100x100")
    assert "larger than" in one_line_error(r)
    r = run("train", dataset, "-o", tmp_path / "r4", "--resume")
    assert "nothing to resume" in one_line_error(r)
    r = run("train", dataset, "-o", tmp_path / "r5", "--device", "cuda:7")
    if not __import__("torch").cuda.is_available():
        assert "CUDA is not available" in one_line_error(r)
    (tmp_path / "bad.pt").write_bytes(b"junk")
    r = run("eval", "--checkpoint", tmp_path / "bad.pt", dataset)
    assert "not a readable torch checkpoint" in one_line_error(r)


def test_usage_errors(dataset, tmp_path):
    r = run("train", dataset, "-o", tmp_path / "r", "--crop-size", "12by3")
    assert r.exit_code == 2 and "--crop-size" in r.output and "expected WxH" in r.output
    r = run("train", dataset, "-o", tmp_path / "r", "--crop", "12by3")  # the old spelling
    assert r.exit_code == 2 and "expected HxW" in r.output and "--crop-size takes WxH" in r.output
    r = run("train", dataset, "-o", tmp_path / "r", "--input", "depth")
    assert r.exit_code == 2
    r = run("eval", dataset)
    assert r.exit_code == 2 and "--checkpoint" in r.output
    r = run("eval", "--pred", tmp_path, "--checkpoint", tmp_path)
    assert r.exit_code == 2
    r = run("eval", "--pred", tmp_path)
    assert r.exit_code == 2 and "--gt" in r.output
    r = run("eval", "--pred", tmp_path, "--gt", tmp_path, "--min-depth", "90")
    assert r.exit_code == 2
    assert not (tmp_path / "r").exists()


def test_help_lists_examples():
    r = run("train", "--help")
    assert r.exit_code == 0 and "--final-layer / --no-final-layer" in r.output
    assert "[rgb|rgbd|rgbdm|d|rgbdc|rgbdu]" in r.output and "-q, --quiet" in r.output
    r = run("eval", "--help")
    assert r.exit_code == 0 and "--garg-crop" in r.output
    assert "--overwrite" in r.output and "--debug" in r.output


# -- renamed options: the old spellings work for one release, with one warning ---------------------
@pytest.fixture
def configs(monkeypatch):
    """The (TrainConfig, explicit fields) each `train` invocation asks for (nothing trained)."""
    from sparsetools.train import loop
    from sparsetools.train.epochs import TrainSummary

    asked = []

    def fake_train(config, *, resume=False, progress=False, explicit=None, on_epoch=None):
        asked.append((config, explicit))
        return TrainSummary(config.out_dir, config.input_mode, False, 0, 0, None, "rmse",
                            float("inf"), None, 0.0, 1)  # fmt: skip

    monkeypatch.setattr(loop, "train", fake_train)
    return asked


@pytest.mark.parametrize(
    ("old", "new", "field", "value"),
    [
        (["--workers", "2"], ["--loader-workers", "2"], "workers", 2),
        (["--crop", "16x32"], ["--crop-size", "32x16"], "crop", (16, 32)),  # (H, W) inside
    ],
)
def test_old_spellings_give_the_same_config_with_one_warning(
    dataset, tmp_path, configs, old, new, field, value
):
    out = tmp_path / "run"
    r_new = run("train", dataset, "-o", out, *new)
    assert r_new.exit_code == 0, r_new.output
    assert "deprecated" not in r_new.stderr
    r_old = run("train", dataset, "-o", out, *old, *TINY)
    assert r_old.exit_code == 0, r_old.output
    (config_new, explicit_new), (config_old, explicit_old) = configs[0], configs[1]
    assert getattr(config_new, field) == value
    assert config_old == TrainConfig(**{**config_new.__dict__, "width": 4, "batch_size": 4,
                                        "epochs": 1, "threads": 1, "pictures": 1})  # fmt: skip
    assert field in explicit_new and field in explicit_old  # compared on --resume alike
    warnings = [line for line in r_old.stderr.splitlines() if "deprecated" in line]
    assert warnings == [
        f"WARNING: deprecated: {old[0]} is now {new[0]} (the old spelling goes in 0.4)"
    ]
    # both spellings at once: a usage error, nothing run
    r = run("train", dataset, "-o", out, *old, *new)
    assert r.exit_code == 2 and f"{old[0]} is the old spelling of {new[0]}" in r.output
    assert len(configs) == 2


def test_crop_size_is_width_first(dataset, tmp_path):
    # 24x40 (HxW) images: a 32x16 crop (W 32, H 16) fits, a 16x32 one (W 16, H 32) does not
    r = run("train", dataset, "-o", tmp_path / "ok", *TINY, "--max-steps", "1", "--json",
            "--crop-size", "32x16")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "ok" / "config.json").read_text())["crop"] == [16, 32]
    r = run("train", dataset, "-o", tmp_path / "no", *TINY, "--crop-size", "16x32")
    assert "crop 16x32 (WxH) is larger than" in one_line_error(r)
    # --resume compares a crop given by either spelling, and says it as --crop-size does
    expected = "--crop-size: --resume continues the run's own settings: the crop is 32x16 (WxH)"
    r = run("train", dataset, "-o", tmp_path / "ok", "--resume", "--crop-size", "40x24")
    assert one_line_error(r) == f"Error: {expected} there, not 40x24 (WxH)"
    r = run("train", dataset, "-o", tmp_path / "ok", "--resume", "--crop", "24x40")
    assert r.exit_code == 1 and r.stderr.splitlines() == [
        "WARNING: deprecated: --crop is now --crop-size (the old spelling goes in 0.4)",
        f"Error: {expected} there, not 40x24 (WxH)",
    ]
