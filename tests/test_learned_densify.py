"""The learned densifier (SpaDe-style, with uncertainty; issue 29 part 1): its loss, URL's gate,
the network's shapes, deterministic training, U rising on corrupted input, and the commands
``train-densifier`` and ``densify --method learned``."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from tests._cli import one_line_error, run

from sparsetools.errors import FormatError, ParameterError
from sparsetools.ops.uncertainty import (
    GAUSSIAN_MAE_PER_SIGMA,
    calibration_bins,
    gated_fusion,
    sigma_from_log_var,
    uncertainty_gate,
)
from sparsetools.train.densifier import (
    SparseDensifier,
    classical_base,
    densifier_loss,
    heteroscedastic_loss,
    load_densifier,
    push_pull,
)
from sparsetools.train.densifier_train import (
    DensifierTrainConfig,
    fit_densifier,
    simulate_frames,
)

SYNTH = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# -- the loss -------------------------------------------------------------------------------------


def _t(values) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64).reshape(1, 1, 1, -1)


def test_heteroscedastic_loss_equals_the_hand_computed_value():
    # pixels: e = 1, U = 0 | e = -2, U = log 4 | no truth | truth beyond max_depth
    depth = _t([2.0, 3.0, 7.0, 9.0])
    log_var = _t([0.0, math.log(4.0), 5.0, 5.0])
    gt = _t([1.0, 5.0, 0.0, 90.0])
    # 0.5 exp(-U) e^2 + 0.5 U: 0.5 * 1 * 1 + 0 = 0.5 and 0.5 * (1/4) * 4 + 0.5 log 4
    # = 0.5 + 0.693147..., mean over the two valid pixels
    by_hand = (0.5 + (0.5 + 0.5 * math.log(4.0))) / 2  # = 0.8465735902799727
    got = heteroscedastic_loss(depth, log_var, gt, max_depth=80.0)
    assert float(got) == pytest.approx(by_hand, rel=1e-12)
    terms = densifier_loss(depth, log_var, gt, nll_weight=2.0, max_depth=80.0)
    assert float(terms["l1"]) == pytest.approx(1.5, rel=1e-12)  # (|1| + |-2|) / 2
    assert float(terms["loss"]) == pytest.approx(1.5 + 2.0 * by_hand, rel=1e-12)


def test_heteroscedastic_loss_without_truth_is_zero_and_differentiable():
    depth = torch.ones(1, 1, 2, 2, requires_grad=True)
    log_var = torch.zeros(1, 1, 2, 2, requires_grad=True)
    loss = densifier_loss(depth, log_var, torch.zeros(1, 1, 2, 2))["loss"]
    loss.backward()
    assert float(loss.detach()) == 0.0 and float(depth.grad.abs().sum()) == 0.0
    with pytest.raises(ParameterError):
        heteroscedastic_loss(depth, log_var, torch.zeros(1, 1, 2, 3))


def test_the_loss_is_minimal_where_exp_u_is_the_squared_error():
    """d/dU [0.5 exp(-U) e^2 + 0.5 U] = 0 at U = log e^2: the term learns the variance."""
    e = 3.0
    u = torch.tensor([math.log(e * e)], dtype=torch.float64, requires_grad=True)
    heteroscedastic_loss(_t([e + 10.0]), u.reshape(1, 1, 1, 1), _t([10.0])).backward()
    assert abs(float(u.grad)) < 1e-12


# -- the gate -------------------------------------------------------------------------------------


def test_gate_is_the_formula_half_at_beta_and_decreasing():
    u = np.linspace(-10, 10, 201)
    for alpha, beta in ((0.8, 0.0), (2.0, -1.5), (0.1, 3.0)):
        lam = uncertainty_gate(u, alpha=alpha, beta=beta)
        np.testing.assert_allclose(lam, 1.0 / (1.0 + np.exp(alpha * (u - beta))), rtol=1e-12)
        assert float(uncertainty_gate(np.array([beta]), alpha=alpha, beta=beta)[0]) == 0.5
        assert np.all(np.diff(lam) < 0)
    # defaults are the survey's alpha 0.8, beta 0; no overflow at extreme U; dtype kept
    lam32 = uncertainty_gate(np.array([-1e4, 0.0, 1.0, 1e4], np.float32))
    assert lam32.dtype == np.float32
    np.testing.assert_allclose(lam32, [1.0, 0.5, 1 / (1 + math.exp(0.8)), 0.0], rtol=1e-6)


def test_gate_refuses_bad_arguments():
    with pytest.raises(ParameterError, match="alpha"):
        uncertainty_gate(np.zeros(3), alpha=0.0)
    with pytest.raises(ParameterError, match="log-var"):
        uncertainty_gate(np.array([0.0, np.nan]))
    with pytest.raises(ParameterError, match="log-var"):
        uncertainty_gate([0.0, 1.0])


def test_gated_fusion_and_sigma():
    coarse, other = np.full((2, 3), 10.0), np.full((2, 3), 20.0)
    u = np.array([[-50.0, 0.0, 50.0], [0.0, 0.0, 0.0]])
    fused = gated_fusion(coarse, other, u)
    np.testing.assert_allclose(fused[0], [10.0, 15.0, 20.0])
    np.testing.assert_allclose(sigma_from_log_var(np.array([0.0, math.log(4.0)])), [1.0, 2.0])


def test_calibration_bins_of_gaussian_errors_match_sigma():
    rng = np.random.default_rng(0)
    sigma = np.repeat([0.5, 2.0, 8.0], 20000)
    gt = np.full(sigma.size, 30.0)
    pred = gt + rng.normal(0.0, sigma)
    bins = calibration_bins(pred, 2 * np.log(sigma), gt, edges=[0.25, 1.0, 4.0, 16.0])
    assert bins.count.tolist() == [20000, 20000, 20000]
    np.testing.assert_allclose(bins.sigma, [0.5, 2.0, 8.0])
    np.testing.assert_allclose(bins.mae / bins.sigma, GAUSSIAN_MAE_PER_SIGMA, rtol=0.02)
    np.testing.assert_allclose(bins.rmse / bins.sigma, 1.0, rtol=0.02)
    assert [r["count"] for r in bins.rows()] == [20000] * 3


# -- the network ----------------------------------------------------------------------------------


@pytest.mark.parametrize("height,width", [(375, 1242), (7, 13), (1, 1)])
def test_outputs_have_the_input_size(height, width):
    net = SparseDensifier(width=2).eval()
    sparse = torch.zeros(1, 1, height, width)
    sparse[..., ::3, ::2] = 12.5
    with torch.inference_mode():
        depth, log_var = net(sparse)
    assert depth.shape == log_var.shape == (1, 1, height, width)
    assert torch.isfinite(depth).all() and (depth > 0).all() and torch.isfinite(log_var).all()


def test_an_untrained_network_returns_its_base():
    """Zero head: D_c is the push-pull base (the measurement where there is one), U = 0."""
    net = SparseDensifier(width=2, reference_depth=10.0).eval()
    sparse = torch.zeros(1, 1, 9, 11)
    sparse[0, 0, 4, 5] = 25.0
    with torch.inference_mode():
        depth, log_var = net(sparse)
        empty, _ = net(torch.zeros(1, 1, 9, 11))
    assert float(depth[0, 0, 4, 5]) == pytest.approx(25.0, rel=1e-6)
    torch.testing.assert_close(depth, torch.full_like(depth, 25.0))  # one point fills the map
    torch.testing.assert_close(empty, torch.full_like(empty, 10.0))
    assert float(log_var.abs().max()) == 0.0


def test_push_pull_keeps_the_nearest_measurement_of_a_block():
    sparse = torch.zeros(1, 1, 4, 4)
    sparse[0, 0, 0, 0], sparse[0, 0, 1, 1] = 5.0, 40.0
    log_base, levels_up = push_pull(sparse, reference_depth=10.0)
    base = torch.exp(log_base)[0, 0]
    assert float(base[0, 1]) == pytest.approx(5.0) and float(base[1, 1]) == pytest.approx(40.0)
    assert float(levels_up[0, 0, 0, 0]) == 0 and float(levels_up[0, 0, 0, 1]) == 1


# -- training -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def frames():
    """Three small street frames (310x94) of two seeds, 64 and 16 beams (about 1 s)."""
    return simulate_frames(0, 2, width=310, height=94, beams=(64, 16)) + simulate_frames(
        1, 1, width=310, height=94, beams=(64, 16)
    )


def _small(**kw) -> DensifierTrainConfig:
    base = dict(beam_counts=(64, 16), tile_size=(96, 64), batch_size=4, width=4, threads=1,
                log_every=5)  # fmt: skip
    return DensifierTrainConfig(**{**base, **kw})


def test_training_is_deterministic_for_a_seed(frames):
    a, hist_a = fit_densifier(_small(steps=6, seed=3), frames)
    b, hist_b = fit_densifier(_small(steps=6, seed=3), frames)
    c, _ = fit_densifier(_small(steps=6, seed=4), frames)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)
    assert [r["loss"] for r in hist_a] == [r["loss"] for r in hist_b]
    assert [r["step"] for r in hist_a] == [5, 6]


def test_u_rises_where_the_input_was_made_wrong(frames):
    """A small model trained briefly (5 s) with corrupted rectangles, on a frame it did not
    see: each measured depth of a rectangle multiplied by exp(N(0, 0.5^2)) raises the mean U
    inside the rectangle well above the mean U outside it, both against the clean input (so
    the comparison is on the same pixels; the sky, far from any measurement, has a high U of
    its own)."""
    model, _ = fit_densifier(_small(steps=150, corrupt=0.6, seed=0, lr=4e-3), frames[:2])
    held_out = frames[2].sparse[64]  # 310x94; the LiDAR covers rows 40 and below

    def log_var(sparse):
        base = torch.from_numpy(classical_base(sparse))[None, None]
        with torch.inference_mode():
            return model(torch.from_numpy(sparse)[None, None], base)[1][0, 0].numpy()

    clean = log_var(held_out)
    rises = []
    for k, (top, left) in enumerate([(50, 30), (50, 130), (60, 220), (45, 80)]):
        region = np.zeros(held_out.shape, bool)
        region[top : top + 30, left : left + 70] = True
        factor = np.exp(np.random.default_rng(k).normal(0.0, 0.5, held_out.shape))
        wrong = np.where(region & (held_out > 0), held_out * factor, held_out).astype(np.float32)
        u = log_var(wrong)
        inside = float(u[region].mean() - clean[region].mean())
        outside = float(u[~region].mean() - clean[~region].mean())
        rises.append(inside - outside)
    # measured: 1.2-3.9 with seed 0, 0.6-1.4 with seeds 1-3 (-0.4..6.8 without --corrupt)
    assert min(rises) > 0.5, rises  # sigma inside rises by a factor exp(0.25) = 1.28 at least


def test_config_refuses_bad_values():
    with pytest.raises(ParameterError, match="beam-counts"):
        DensifierTrainConfig(beam_counts=(5,))
    with pytest.raises(ParameterError, match="corrupt"):
        DensifierTrainConfig(corrupt=1.5)
    with pytest.raises(ParameterError, match="tile-size"):
        DensifierTrainConfig(tile_size=(8, 64))


# -- the commands ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("densifier") / "run"
    r = run("train-densifier", "-o", out, "--sim-frames", "1", "--image-size", "160x48",
            "--steps", "3", "--tile-size", "64x32", "--width", "2", "--threads", "1",
            "--beam-counts", "64,4", "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["steps"] == 3 and summary["frames"] == 1
    assert {p.name for p in out.iterdir()} == {"densifier.pt", "metrics.csv", "config.json",
                                               ".sparsetools"}  # fmt: skip
    return out / "densifier.pt"


@pytest.fixture(scope="module")
def sparse_maps(tmp_path_factory) -> Path:
    """The sample scans projected at a quarter size (310x94): a ``project`` output folder."""
    out = tmp_path_factory.mktemp("sparse") / "depth"
    r = run("project", SYNTH / "velodyne", "--calib", SYNTH / "calib", "--image-size",
            "1242x375", "--resize", "0.25", "-o", out)  # fmt: skip
    assert r.exit_code == 0, r.output
    return out


def test_train_densifier_reruns_and_refuses_a_taken_folder(checkpoint, tmp_path):
    same = ("train-densifier", "-o", checkpoint.parent, "--sim-frames", "1", "--image-size",
            "160x48", "--steps", "3", "--tile-size", "64x32", "--width", "2", "--threads", "1",
            "--beam-counts", "64,4")  # fmt: skip
    before = checkpoint.stat().st_mtime_ns
    r = run(*same)
    assert r.exit_code == 0 and "up to date" in r.stdout
    assert checkpoint.stat().st_mtime_ns == before  # nothing trained or written again
    other = [a if a != "3" else "1" for a in same]  # --steps 1, every other option the same
    line = one_line_error(run(*other))
    assert "made with --steps 3, not 1" in line and "--overwrite" in line
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "notes.txt").write_text("mine")
    line = one_line_error(run("train-densifier", "-o", tmp_path / "taken", "--steps", "1"))
    assert "no record" in line and (tmp_path / "taken" / "notes.txt").read_text() == "mine"
    r = run("train-densifier", SYNTH, "-o", checkpoint.parent / "x", "--sim-frames", "3")
    assert r.exit_code == 2 and "--sim-frames" in r.stderr


def test_checkpoint_reads_back_checked(checkpoint):
    ckpt = load_densifier(checkpoint.parent)  # the run folder means its densifier.pt
    assert ckpt.model_config == {"width": 2, "reference_depth": 10.0}
    assert ckpt.config["steps"] == 3 and len(ckpt.run_id) == 32


def test_densify_learned_writes_depth_mask_and_uncertainty_and_resumes(
    checkpoint, sparse_maps, tmp_path
):
    out = tmp_path / "dense"
    args = ["densify", sparse_maps, "-o", out, "--method", "learned", "--densifier", checkpoint,
            "--uncertainty", "--json"]  # fmt: skip
    r = run(*args)
    assert r.exit_code == 0, r.output
    first = json.loads(r.stdout)
    assert first["processed"] == 3 and first["method"] == "learned"
    assert first["empty_pct"] == 0.0 and first["sigma_median_m"] > 0
    for stem in ("000000", "000001", "000002"):
        sparse = cv2.imread(str(sparse_maps / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        dense = cv2.imread(str(out / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        mask = cv2.imread(str(out / "mask" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        u = np.load(out / "uncertainty" / f"{stem}.npy")
        assert dense.dtype == np.uint16 and dense.shape == sparse.shape and (dense > 0).all()
        assert mask.dtype == np.uint8 and np.array_equal(mask == 255, sparse > 0)
        assert u.dtype == np.float32 and u.shape == sparse.shape and np.isfinite(u).all()
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*")
              if p.is_file() and ".sparsetools" not in p.parts}  # fmt: skip
    again = json.loads(run(*args).stdout)
    assert again["processed"] == 0 and again["skipped_existing"] == 3
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps  # nothing rewritten
    # other settings are refused, naming the option
    line = one_line_error(run(*args[:-2], "--json"))
    assert "--uncertainty" in line
    # two worker processes write the same bytes
    two = tmp_path / "two"
    r = run(*[two if a == out else a for a in args], "--workers", "2")
    assert r.exit_code == 0, r.output
    for p in stamps:
        assert (two / p.relative_to(out)).read_bytes() == p.read_bytes(), p


def test_densify_learned_refuses_missing_and_foreign_checkpoints(sparse_maps, tmp_path):
    out = tmp_path / "dense"
    missing = one_line_error(run("densify", sparse_maps, "-o", out, "--method", "learned",
                                 "--densifier", tmp_path / "nope.pt"))  # fmt: skip
    assert "no such densifier checkpoint" in missing
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint at all")
    line = one_line_error(run("densify", sparse_maps, "-o", out, "--method", "learned",
                              "--densifier", junk))  # fmt: skip
    assert "not a readable torch checkpoint" in line
    depth_ckpt = tmp_path / "depth.pt"
    torch.save({"format": "sparsetools-depth-checkpoint", "version": 2}, depth_ckpt)
    line = one_line_error(run("densify", sparse_maps, "-o", out, "--method", "learned",
                              "--densifier", depth_ckpt))  # fmt: skip
    assert "not a sparsetools densifier checkpoint" in line
    with pytest.raises(FormatError, match="weights"):
        bad = tmp_path / "bad.pt"
        torch.save({"format": "sparsetools-densifier-checkpoint", "version": 1,
                    "model_config": {"width": 2, "reference_depth": 10.0}, "model": {}}, bad)  # fmt: skip
        load_densifier(bad)
    assert not out.exists()


def test_densify_options_of_other_methods_are_refused(checkpoint, sparse_maps, tmp_path):
    r = run("densify", sparse_maps, "-o", tmp_path / "a", "--method", "learned")
    assert r.exit_code == 2 and "--densifier" in r.stderr
    r = run("densify", sparse_maps, "-o", tmp_path / "b", "--uncertainty")
    assert r.exit_code == 2 and "--method learned" in r.stderr
    r = run("densify", sparse_maps, "-o", tmp_path / "c", "--method", "learned", "--densifier",
            checkpoint, "--multiscale")  # fmt: skip
    assert r.exit_code == 2 and "--multiscale" in r.stderr


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


def test_without_torch_the_commands_say_one_line(tmp_path):
    hint = "pip install 'sparsetools[train]'"

    def without_torch(*args):
        return subprocess.run([sys.executable, "-c", _NO_TORCH, *map(str, args)],
                              capture_output=True, text=True, timeout=120)  # fmt: skip

    r = without_torch("train-densifier", "-o", tmp_path / "run")
    assert (r.returncode, r.stderr) == (1, f"Error: train-densifier needs PyTorch: {hint}\n")
    r = without_torch("densify", SYNTH / "depth_gt", "-o", tmp_path / "d", "--method", "learned",
                      "--densifier", tmp_path / "x.pt")  # fmt: skip
    assert r.returncode == 1
    assert r.stderr == f"Error: densify --method learned needs PyTorch: {hint}\n"
    assert not (tmp_path / "run").exists() and not (tmp_path / "d").exists()
