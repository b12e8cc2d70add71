"""The speed changes of training keep its results: bit for bit where the maths is unchanged,
to rounding where the summation order changed on purpose (channels-last convolutions), and
within a stated tolerance across thread counts (issue 18)."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch

from sparsetools.train import loop as train_loop
from sparsetools.train.checkpoint import load_checkpoint
from sparsetools.train.config import TrainConfig
from sparsetools.train.data import DepthDataset, collate
from sparsetools.train.model import DepthCompletionUNet
from sparsetools.train.runtime import torch_settings
from test_train import make_dataset, read_rows

SEED = 3


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("speed_ds"))


def cfg(dataset, out, **kw) -> TrainConfig:
    base = dict(
        dataset=str(dataset),
        out_dir=str(out),
        width=4,
        epochs=1,
        batch_size=4,
        lr=3e-3,
        threads=1,
        pictures=0,
        seed=SEED,
    )
    base.update(kw)
    return TrainConfig(**base)


def plain_training(dataset, *, steps: int, batch_size: int = 4, lr: float = 3e-3):
    """The straightforward loop: public torch settings, one thread, a seeded permutation of
    the training samples, L1 on the valid ground truth below 80 m, Adam."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)  # with NaN-filled fresh memory
    try:
        torch.manual_seed(SEED)
        model = DepthCompletionUNet("rgbd", width=4)
        opt = torch.optim.Adam(model.parameters(), lr=lr)
        data = DepthDataset(dataset, "train", augment=True, seed=SEED)
        data.set_epoch(0)
        order = np.random.default_rng([SEED, 7919, 0]).permutation(len(data)).tolist()
        losses, sizes = [], []
        model.train()
        for k in range(steps):
            batch = collate([data[i] for i in order[k * batch_size : (k + 1) * batch_size]])
            pred = model.run(batch["rgb"], batch["sparse"])
            gt = batch["gt"]
            valid = torch.isfinite(gt) & (gt > 0) & (gt < 80.0)
            loss = (pred[valid] - gt[valid]).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            sizes.append(len(batch["rgb"]))
        return model.state_dict(), losses, sizes
    finally:
        torch.use_deterministic_algorithms(False)
        torch.set_num_threads(before)


def test_training_equals_a_plain_loop_bit_for_bit(dataset, tmp_path):
    """Deterministic mode without NaN-filled memory, the thread pinning, the background
    checkpoint writer and the copied last.pt change no bit of the weights or the loss."""
    run = tmp_path / "run"
    summary = train_loop.train(cfg(dataset, run, max_steps=3))
    assert summary.steps == 3
    weights, losses, sizes = plain_training(dataset, steps=3)
    saved = load_checkpoint(run / "last.pt").model
    assert saved.keys() == weights.keys()
    assert all(torch.equal(saved[k], weights[k]) for k in weights)
    row = read_rows(run)[0]
    mean = sum(v * n for v, n in zip(losses, sizes, strict=True)) / sum(sizes)
    assert float(row["train_loss"]) == mean  # metrics.csv writes floats exactly
    # best.pt is this epoch too: the same checkpoint contents under both names
    best = load_checkpoint(run / "best.pt")
    assert all(torch.equal(best.model[k], saved[k]) for k in saved)
    assert best.state.step == 3 and not list(run.glob(".tmp-*"))


def test_threads_and_resume_record_the_count(dataset, tmp_path, monkeypatch):
    """Without --threads the run records the count it chose; --resume reuses it, also on a
    machine with another default (another count would change the last bits), and an explicit
    --threads wins."""
    monkeypatch.setattr(train_loop, "default_threads", lambda: 2)
    run = tmp_path / "run"
    first = train_loop.train(cfg(dataset, run, threads=None))
    assert first.threads == 2 and first.to_dict()["threads"] == 2
    assert json.loads((run / "config.json").read_text())["threads"] == 2
    monkeypatch.setattr(train_loop, "default_threads", lambda: 1)  # another machine
    again = train_loop.train(cfg(dataset, run, threads=None, epochs=2), resume=True)
    assert again.threads == 2 and again.epochs_done == 2
    third = train_loop.train(cfg(dataset, run, threads=1, epochs=3), resume=True)
    assert third.threads == 1
    # a fresh run without a count takes this machine's default
    assert train_loop.train(cfg(dataset, tmp_path / "new", threads=None)).threads == 1


def _randomised(width=4, mode="rgbdm", final_layer=True):
    torch.manual_seed(1)
    model = DepthCompletionUNet(mode, width=width, final_layer=final_layer)
    with torch.no_grad():  # the zero-initialised head and adjustment would hide the network
        model.head.weight.normal_(0, 0.5)
        model.adjust.weight.normal_(0, 0.1)
    return model


def _forward_backward(model, rgb, sparse, gt):
    model.train()
    model.zero_grad()
    out = model.run(rgb, sparse)
    (out - gt).abs().mean().backward()
    return out.detach().double(), [p.grad.double() for p in model.parameters()]


def test_channels_last_matches_float64_within_the_documented_tolerance():
    """The model runs its convolutions channels-last (model.py); in float32 that is another
    summation order than NCHW: outputs within 1e-4 of the largest output and gradients
    within 5 % in norm of the same network in float64."""
    model = _randomised()
    assert model.stem[0].weight.is_contiguous(memory_format=torch.channels_last)
    assert model.decoder[0].up.conv1.weight.is_contiguous(memory_format=torch.channels_last)
    exact = copy.deepcopy(model).double()
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(2, 3, 37, 53, generator=g)  # odd size: padding and crop
    sparse = torch.where(torch.rand(2, 1, 37, 53, generator=g) < 0.1, 30.0, 0.0)
    gt = 5 + 40 * torch.rand(2, 1, 37, 53, generator=g)
    out, grads = _forward_backward(model, rgb, sparse, gt)
    ref, ref_grads = _forward_backward(exact, rgb.double(), sparse.double(), gt.double())
    assert out.shape == ref.shape == (2, 1, 37, 53)
    assert float(ref.std()) > 1.0  # the comparison is not between constants
    assert not torch.equal(out, ref)  # float32 against float64: a tolerance test
    assert float((out - ref).abs().max()) <= 1e-4 * float(ref.abs().max())
    rel = [float((a - r).norm() / r.norm()) for a, r in zip(grads, ref_grads, strict=True)]
    assert max(rel) <= 0.05


def test_checkpoint_weights_load_into_either_layout(dataset, tmp_path):
    """Weights saved from the channels-last model load into an NCHW one and back, equal
    (checkpoints of 0.2.0, written NCHW, load the same way)."""
    train_loop.train(cfg(dataset, tmp_path / "run", max_steps=1))
    saved = load_checkpoint(tmp_path / "run" / "last.pt").model
    nchw = DepthCompletionUNet("rgbd", width=4).to(memory_format=torch.contiguous_format)
    nchw.load_state_dict(saved)
    back = DepthCompletionUNet("rgbd", width=4)
    back.load_state_dict({k: v.contiguous() for k, v in nchw.state_dict().items()})
    assert back.stem[0].weight.is_contiguous(memory_format=torch.channels_last)
    assert all(torch.equal(back.state_dict()[k], saved[k]) for k in saved)


LR = 1e-3
#: Largest relative drift of the weights between runs with 1 and 2 threads (see below);
#: measured 0.05-0.065 (2 and 3 threads against 1), while a real change of the training --
#: the learning rate 1 % off, one batch flipped -- drifts 0.17 to 1.4.
THREAD_DRIFT = 0.1


def _two_steps(threads: int, *, lr: float = LR):
    g = torch.Generator().manual_seed(5)
    rgb = torch.rand(4, 3, 48, 80, generator=g)
    sparse = torch.where(torch.rand(4, 1, 48, 80, generator=g) < 0.1, 25.0, 0.0)
    gt = 5 + 40 * torch.rand(4, 1, 48, 80, generator=g)
    with torch_settings(threads, torch.device("cpu")):
        torch.manual_seed(0)
        model = DepthCompletionUNet("rgbd", width=8)
        start = {k: p.detach().clone() for k, p in model.named_parameters()}
        opt = torch.optim.Adam(model.parameters(), lr=lr)
        losses, first_grads = [], None
        for _ in range(2):
            loss = (model.run(rgb, sparse) - gt).abs().mean()
            opt.zero_grad()
            loss.backward()
            if first_grads is None:
                first_grads = [p.grad.clone() for p in model.parameters()]
            opt.step()
            losses.append(float(loss.detach()))
    weights = {k: p.detach().clone() for k, p in model.named_parameters()}
    return losses, first_grads, weights, start


def weight_drift(a: dict, b: dict, start: dict) -> float:
    """How far two trainings from the same ``start`` ended apart, relative to how far they
    moved: ||a - b|| / ||a - start|| over all parameters.

    Adam moves every weight by about the learning rate per step, whatever its gradient
    (it divides the gradient by its own RMS), so a per-weight bound cannot tell rounding from
    a real change: a weight whose gradient is near 0 flips its step between thread counts
    (measured: 0.4 % of the weights, each up to 1.5 x the learning rate). Over all weights,
    those flips are a small part of the movement; a real change moves many more.
    """
    diff = sum(float((a[k] - b[k]).double().square().sum()) for k in a)
    moved = sum(float((a[k] - start[k]).double().square().sum()) for k in a)
    return math.sqrt(diff / moved)


def test_thread_count_changes_the_results_only_within_the_documented_tolerance():
    """What runtime.py documents: the first forward pass is the same bits with 1 and 2
    threads, its weight gradients agree to rounding, and after two Adam steps the weights
    differ by a small part of their movement (only weights with near-zero gradients flip)."""
    l1, g1, w1, start = _two_steps(1)
    l2, g2, w2, _ = _two_steps(2)
    assert l1[0] == l2[0]
    for a, b in zip(g1, g2, strict=True):
        assert float((a - b).norm()) <= 1e-4 * float(b.norm()) + 1e-12
    assert math.isclose(l1[1], l2[1], rel_tol=1e-5)
    assert weight_drift(w1, w2, start) <= THREAD_DRIFT
    # and a repeat with the same count is exact
    l1b, _, w1b, _ = _two_steps(1)
    assert l1b == l1 and all(torch.equal(w1[k], w1b[k]) for k in w1)


def test_the_thread_tolerance_is_exceeded_by_a_real_difference():
    """The tolerance above can fail: training with a learning rate 1 % off, on the same
    thread count, drifts beyond it (issue 23: the former bound, 2 steps x 2 x lr, was Adam's
    largest possible step and held for any two trainings)."""
    _, _, w1, start = _two_steps(1)
    _, _, w_off, _ = _two_steps(1, lr=1.01 * LR)
    assert weight_drift(w1, w_off, start) > THREAD_DRIFT
