"""URL in `train` (issue 29 part 2): the learned densifier's D_c and U fed to the early-fusion
U-Net, refined as a residual (D_f = D_c + R(I, U)) or gated (lambda(U) D_c + (1 - lambda(U)) P).

The gate and the two readings of the head are checked against their formulas on hand-made
tensors; a tiny URL training is deterministic for a seed, resumes exactly and is evaluated
from its checkpoint alone; the command line refuses a missing or foreign densifier and the
URL options without ``--input rgbdu`` in one line. One torch thread throughout.
"""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import FormatError, ParameterError
from sparsetools.ops.uncertainty import uncertainty_gate as numpy_gate
from sparsetools.train.checkpoint import load_checkpoint, new_run_id
from sparsetools.train.config import SelfSupSettings, TrainConfig
from sparsetools.train.data import DepthDataset
from sparsetools.train.densifier import LearnedDensifier, SparseDensifier, save_densifier
from sparsetools.train.evaluate import evaluate_checkpoint
from sparsetools.train.loop import train
from sparsetools.train.model import DepthCompletionUNet, build_model
from sparsetools.train.predict import open_predictor
from sparsetools.train.url import gated_fusion, uncertainty_gate
from test_train import make_dataset

TINY = ["--width", "4", "--batch-size", "4", "--epochs", "1", "--threads", "1", "--pictures", "1"]
TIMING = {"seconds", "samples_per_s", "run_id"}


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def make_densifier(path: Path, *, seed: int = 0) -> Path:
    """An untrained densifier (width 2) whose head is drawn from ``seed``, so that D_c and U
    vary over the image: a valid ``densifier.pt`` in a second."""
    net = SparseDensifier(width=2)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        net.head.weight.copy_(0.3 * torch.randn(net.head.weight.shape, generator=g))
    path.parent.mkdir(parents=True, exist_ok=True)
    save_densifier(path, model=net, config={"max_depth": 80.0}, history=[], run_id=new_run_id())
    return path


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("url_ds"), n_seq=5, frames=2)


@pytest.fixture(scope="module")
def densifier(tmp_path_factory) -> Path:
    return make_densifier(tmp_path_factory.mktemp("url_densifier") / "densifier.pt")


def url_config(dataset, out, densifier, **kw) -> TrainConfig:
    base = dict(dataset=str(dataset), out_dir=str(out), input_mode="rgbdu", url="residual",
                densifier=str(densifier), width=4, epochs=2, batch_size=4, lr=2e-3, threads=1,
                pictures=1, seed=1)  # fmt: skip
    return TrainConfig(**{**base, **kw})


def metrics_rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(f)]


def cli_run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_error_line(result) -> str:
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
    return lines[0]


# -- the gate and the two readings of the head ---------------------------------------------------


@pytest.mark.parametrize("alpha,beta", [(0.8, 0.0), (2.5, -1.0), (0.3, 4.0)])
def test_gate_equals_the_formula(alpha, beta):
    u = torch.tensor([[-12.0, -3.0, -0.5, 0.0], [0.5, 1.0, 4.0, 12.0]], dtype=torch.float64)
    want = 1.0 / (1.0 + np.exp(alpha * (u.numpy() - beta)))
    got = uncertainty_gate(u, alpha=alpha, beta=beta).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    # the torch gate is the numpy one of ops/uncertainty.py
    np.testing.assert_allclose(got, numpy_gate(u.numpy(), alpha=alpha, beta=beta), rtol=1e-12)
    assert uncertainty_gate(torch.tensor([beta]), alpha=alpha, beta=beta).item() == 0.5


def test_gated_fusion_equals_the_formula_on_hand_made_tensors():
    coarse = torch.tensor([[[[10.0, 20.0], [30.0, 5.0]]]], dtype=torch.float64)
    pred = torch.tensor([[[[12.0, 10.0], [31.0, 9.0]]]], dtype=torch.float64)
    u = torch.tensor([[[[-2.0, 0.0], [1.5, 6.0]]]], dtype=torch.float64)
    lam = 1.0 / (1.0 + np.exp(0.8 * u.numpy()))
    want = lam * coarse.numpy() + (1 - lam) * pred.numpy()
    np.testing.assert_allclose(gated_fusion(coarse, pred, u).numpy(), want, rtol=1e-12)
    # U = beta: the mean; very sure: D_c; very unsure: P
    assert gated_fusion(coarse, pred, u, alpha=0.8, beta=0.0)[0, 0, 0, 1] == 15.0
    sure = gated_fusion(coarse, pred, torch.full_like(u, -60.0))
    unsure = gated_fusion(coarse, pred, torch.full_like(u, 60.0))
    assert torch.allclose(sure, coarse) and torch.allclose(unsure, pred)


def _inputs(seed: int = 0, h: int = 19, w: int = 27):
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(2, 3, h, w, generator=g)
    coarse = 2 + 40 * torch.rand(2, 1, h, w, generator=g)
    log_var = 8 * torch.rand(2, 1, h, w, generator=g) - 4
    return rgb, coarse, log_var


def test_gated_model_fuses_its_own_prediction_with_dc():
    """The head set to a constant b: P = 20 softplus(b) m everywhere, so the model's output must
    be lambda(U) D_c + (1 - lambda(U)) P with the model's alpha, beta."""
    torch.manual_seed(0)
    model = DepthCompletionUNet("rgbdu", width=4, url="gated", gate_alpha=1.5, gate_beta=0.5)
    model.eval()
    with torch.no_grad():
        model.head.weight.zero_()
        model.head.bias.fill_(0.7)
    rgb, coarse, log_var = _inputs()
    with torch.no_grad():
        out = model.run(rgb, None, coarse=coarse, log_var=log_var)
    p = 20.0 * np.log1p(np.exp(0.7))
    lam = 1.0 / (1.0 + np.exp(1.5 * (log_var.double().numpy() - 0.5)))
    want = lam * coarse.double().numpy() + (1 - lam) * p
    assert out.shape == coarse.shape
    np.testing.assert_allclose(out.numpy(), want, rtol=1e-5)


def test_residual_output_is_dc_when_the_residual_branch_outputs_zero():
    torch.manual_seed(0)
    model = DepthCompletionUNet("rgbdu", width=4, url="residual").eval()
    rgb, coarse, log_var = _inputs(1)
    with torch.no_grad():
        for p in model.parameters():  # everything but the head moves: R stays 0
            p.add_(0.1 * torch.randn_like(p))
        model.head.weight.zero_()
        model.head.bias.zero_()
        out = model.run(rgb, None, coarse=coarse, log_var=log_var)
        assert torch.equal(out, coarse)
        model.head.bias.fill_(0.05)  # R = 20 m x 0.05 = 1 m
        out = model.run(rgb, None, coarse=coarse, log_var=log_var)
    assert torch.allclose(out, coarse + 1.0, atol=1e-5)
    # an untrained residual model starts at D_c (its head starts at zero)
    fresh = DepthCompletionUNet("rgbdu", width=4, url="residual").eval()
    with torch.no_grad():
        assert torch.equal(fresh.run(rgb, None, coarse=coarse, log_var=log_var), coarse)


def test_model_refuses_url_settings_that_do_not_go_together():
    with pytest.raises(ParameterError, match="url"):
        DepthCompletionUNet("rgbdu", width=4)
    with pytest.raises(ParameterError, match="url"):
        DepthCompletionUNet("rgbd", width=4, url="residual")
    with pytest.raises(ParameterError, match="url"):
        DepthCompletionUNet("rgbdu", width=4, url="gated", final_layer=True)
    model = DepthCompletionUNet("rgbdu", width=4, url="gated", gate_alpha=2.0)
    rgb, coarse, _ = _inputs()
    with pytest.raises(ParameterError, match="coarse and log_var"):
        model.run(rgb, None, coarse=coarse)
    rebuilt = build_model(model.config())
    assert (rebuilt.url, rebuilt.gate) == ("gated", (2.0, 0.0))
    # models of the other modes keep their three (or five) keys
    assert "url" not in DepthCompletionUNet("rgbd", width=4).config()


# -- data, training, checkpoints, evaluation ----------------------------------------------------


def test_items_carry_the_densifier_maps_of_the_augmented_sparse_map(dataset, densifier):
    dn = LearnedDensifier(densifier)
    ds = DepthDataset(dataset, "train", augment=True, crop=(16, 32), seed=2, densifier=dn)
    ds.set_epoch(1)
    item = ds[0]
    coarse, log_var = dn.densify(item["sparse"][0].numpy())
    assert torch.equal(item["coarse"][0], torch.from_numpy(coarse))
    assert torch.equal(item["log_var"][0], torch.from_numpy(log_var))
    assert item["coarse"].shape == item["sparse"].shape == (1, 16, 32)
    assert float(item["log_var"].std()) > 0  # U varies: the gate is not a constant
    assert "coarse" not in DepthDataset(dataset, "train")[0]


def test_tiny_url_training_is_deterministic_and_finite(dataset, densifier, tmp_path):
    runs = {}
    for name, kw in (("a", {}), ("b", {}), ("seed", {"seed": 2}), ("gated", {"url": "gated"})):
        out = tmp_path / name
        summary = train(url_config(dataset, out, densifier, **kw))
        assert summary.extras["url"] == kw.get("url", "residual")
        runs[name] = metrics_rows(out)
    assert runs["a"] == runs["b"]
    assert runs["a"] != runs["seed"] and runs["a"] != runs["gated"]
    for rows in runs.values():
        assert all(
            np.isfinite(float(r[k])) for r in rows for k in ("train_loss", "val_loss", "rmse")
        )
    a = load_checkpoint(tmp_path / "a" / "last.pt")
    b = load_checkpoint(tmp_path / "b" / "last.pt")
    assert all(torch.equal(a.model[k], b.model[k]) for k in a.model)
    assert a.densifier["run_id"] == LearnedDensifier(densifier).run_id
    assert a.model_config["url"] == "residual" and a.config.densifier == str(densifier)


def test_url_run_resumes_exactly_and_evaluates_without_the_densifier_file(
    dataset, densifier, tmp_path
):
    own = make_densifier(tmp_path / "dn" / "densifier.pt", seed=5)
    full, cut = tmp_path / "full", tmp_path / "cut"
    train(url_config(dataset, full, own, url="gated", gate_beta=1.0))
    train(url_config(dataset, cut, own, url="gated", gate_beta=1.0, max_steps=2))
    shutil.rmtree(own.parent)  # the run carries its densifier
    train(url_config(dataset, cut, own, url="gated", gate_beta=1.0), resume=True)
    assert metrics_rows(full) == metrics_rows(cut)
    ckpt = load_checkpoint(cut / "best.pt")
    assert ckpt.model_config["gate_beta"] == 1.0 and ckpt.densifier is not None
    result = evaluate_checkpoint(cut / "best.pt", dataset, split="test")
    assert result.input_mode == "rgbdu" and np.isfinite(result.metrics["rmse"])
    depth = open_predictor(cut / "best.pt", dataset, split="test").predictor.depth(0)
    assert depth.shape == (24, 40) and np.isfinite(depth).all()


def test_checkpoints_without_their_densifier_are_refused(dataset, densifier, tmp_path):
    out = tmp_path / "run"
    train(url_config(dataset, out, densifier, epochs=1))
    raw = torch.load(out / "last.pt", weights_only=True)
    del raw["densifier"]
    torch.save(raw, tmp_path / "bare.pt")
    with pytest.raises(FormatError, match="without its densifier"):
        load_checkpoint(tmp_path / "bare.pt")
    cfg = url_config(dataset, tmp_path / "x", densifier)
    with pytest.raises(ParameterError, match="--densifier"):
        replace(cfg, densifier=None).validate()
    with pytest.raises(ParameterError, match="--url"):
        replace(cfg, input_mode="rgbd").validate()
    with pytest.raises(ParameterError, match="--self-supervised"):
        replace(cfg, selfsup=SelfSupSettings()).validate()


# -- the command line ----------------------------------------------------------------------------


def test_the_documented_route_runs(dataset, tmp_path):
    """train-densifier, then train --input rgbdu, then eval (docs/train.md, URL)."""
    dn = tmp_path / "densifier"
    r = cli_run("train-densifier", "-o", dn, "--sim-frames", "1", "--image-size", "160x48",
                "--steps", "2", "--tile-size", "64x32", "--width", "2", "--threads", "1",
                "--beam-counts", "64,4")  # fmt: skip
    assert r.exit_code == 0, r.output
    out = tmp_path / "url"
    r = cli_run("train", dataset, "-o", out, *TINY, "--input", "rgbdu", "--densifier", dn, "--json")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["input_mode"] == "rgbdu" and summary["url"] == "residual"
    config = json.loads((out / "config.json").read_text())
    assert (config["url"], config["gate_alpha"], config["gate_beta"]) == ("residual", 0.8, 0.0)
    r = cli_run("eval", "--checkpoint", out / "best.pt", dataset, "--split", "test", "--json")
    assert r.exit_code == 0, r.output


def test_cli_refuses_missing_and_foreign_densifiers_in_one_line(dataset, tmp_path):
    base = ["train", dataset, *TINY, "--input", "rgbdu", "--densifier"]
    line = one_error_line(cli_run(*base, tmp_path / "nope.pt", "-o", tmp_path / "a"))
    assert "nope.pt" in line and "no such densifier checkpoint" in line
    plain = tmp_path / "plain"
    assert cli_run("train", dataset, "-o", plain, *TINY).exit_code == 0
    line = one_error_line(cli_run(*base, plain / "best.pt", "-o", tmp_path / "b"))
    assert "not a sparsetools densifier checkpoint" in line
    text = tmp_path / "text.pt"
    text.write_text("not a checkpoint")
    assert "text.pt" in one_error_line(cli_run(*base, text, "-o", tmp_path / "c"))
    assert not any((tmp_path / n).exists() for n in ("a", "b", "c"))  # refused before training


@pytest.mark.parametrize(
    "args,named",
    [
        (["--url", "gated"], "--url"),
        (["--densifier", "DN"], "--densifier"),
        (["--gate-alpha", "2"], "--gate-alpha"),
        (["--input", "rgbd", "--gate-beta", "1"], "--gate-beta"),
        (["--input", "rgbdu", "--densifier", "DN", "--gate-alpha", "2"], "--url gated"),
        (["--input", "rgbdu", "--densifier", "DN", "--final-layer"], "--final-layer"),
        (["--input", "rgbdu"], "--densifier CHECKPOINT"),
    ],
)
def test_cli_refuses_url_options_without_the_mode_in_one_line(
    dataset, densifier, tmp_path, args, named
):
    args = [str(densifier) if a == "DN" else a for a in args]
    line = one_error_line(cli_run("train", dataset, "-o", tmp_path / "run", *TINY, *args))
    assert named in line
    assert not (tmp_path / "run").exists()
