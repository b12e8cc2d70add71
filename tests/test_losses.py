"""Losses against hand-computed values (BerHu, SILog, L1, MSE), masking and gradients."""

from __future__ import annotations

import math

import pytest
import torch

from sparsetools.errors import ParameterError
from sparsetools.train.losses import (
    berhu_loss,
    depth_loss,
    l1_loss,
    mse_loss,
    silog_loss,
)


def as_batch(values, dtype=torch.float64):
    """(1, 1, 1, N) tensor from a list."""
    return torch.tensor(values, dtype=dtype).reshape(1, 1, 1, -1)


def test_berhu_hand_computed():
    # e = 0, 1, 2, 9 -> c = 0.2 * 9 = 1.8
    # |e| <= c: 0, 1;  |e| > c: (4 + 3.24) / 3.6 = 2.0111.., (81 + 3.24) / 3.6 = 23.4
    gt = as_batch([1.0, 1.0, 1.0, 1.0])
    pred = as_batch([1.0, 2.0, 3.0, 10.0]).requires_grad_()
    loss = berhu_loss(pred, gt)
    assert loss.item() == pytest.approx((0 + 1 + 7.24 / 3.6 + 84.24 / 3.6) / 4, rel=1e-12)
    loss.backward()
    # c is detached: d/dp of |e| is sign(e)/N, of (e^2+c^2)/2c is (e/c)/N
    expected = [0.0, 1 / 4, (2 / 1.8) / 4, (9 / 1.8) / 4]
    assert pred.grad.flatten().tolist() == pytest.approx(expected, rel=1e-12)


def test_berhu_uses_absolute_error_and_counts_each_pixel_once():
    gt = as_batch([10.0, 10.0, 10.0, 10.0])
    over = berhu_loss(as_batch([10.0, 11.0, 12.0, 19.0]), gt)
    under = berhu_loss(as_batch([10.0, 9.0, 8.0, 1.0]), gt)
    assert over.item() == pytest.approx(under.item(), rel=1e-12)
    # the signed-error version would treat e = -9 as an L1 pixel: 0+1+2.011+9 ...
    assert under.item() == pytest.approx((0 + 1 + 7.24 / 3.6 + 84.24 / 3.6) / 4, rel=1e-12)
    # one pixel: |e| = max|e| > 0.2 max|e| -> quadratic branch only: (e^2 + c^2) / 2c
    one = berhu_loss(as_batch([7.0]), as_batch([2.0]))
    assert one.item() == pytest.approx((25 + 1) / 2, rel=1e-12)


def test_berhu_all_equal_errors():
    # |e| = 3 everywhere: c = 0.6, every pixel quadratic: (9 + 0.36) / 1.2 = 7.8
    loss = berhu_loss(as_batch([5.0, 6.0, 7.0]), as_batch([2.0, 3.0, 4.0]))
    assert loss.item() == pytest.approx(7.8, rel=1e-12)


def test_berhu_c_zero_perfect_prediction():
    gt = as_batch([3.0, 4.0, 5.0])
    pred = gt.clone().requires_grad_()
    loss = berhu_loss(pred, gt)
    assert loss.item() == 0.0
    loss.backward()
    assert torch.isfinite(pred.grad).all()
    assert (pred.grad == 0).all()


def test_berhu_float32_finite():
    gt = as_batch([3.0, 4.0], dtype=torch.float32)
    pred = gt.clone().requires_grad_()
    berhu_loss(pred, gt).backward()
    assert torch.isfinite(pred.grad).all()


def test_berhu_threshold_over_whole_batch_and_valid_pixels_only():
    # c comes from the max over the valid pixels of the batch, not per image;
    # invalid gt pixels (0, NaN) neither set c nor enter the mean.
    gt = torch.tensor(
        [[[[1.0, 1.0]]], [[[1.0, 0.0]]], [[[float("nan"), 1.0]]]], dtype=torch.float64
    )
    pred = torch.tensor([[[[2.0, 1.5]]], [[[11.0, 500.0]]], [[[900.0, 1.0]]]], dtype=torch.float64)
    # valid e: 1, 0.5, 10, 0 -> c = 2: 1, 0.5, (100 + 4) / 4 = 26, 0
    assert berhu_loss(pred, gt).item() == pytest.approx((1 + 0.5 + 26 + 0) / 4, rel=1e-12)


def test_l1_mse_hand_computed_and_masked():
    gt = as_batch([1.0, 2.0, 0.0, 4.0])
    pred = as_batch([2.0, 0.0, 100.0, 4.5])
    assert l1_loss(pred, gt).item() == pytest.approx((1 + 2 + 0.5) / 3)
    assert mse_loss(pred, gt).item() == pytest.approx((1 + 4 + 0.25) / 3)


def test_silog_hand_computed():
    # d = 0.1, -0.2, 0.3, 0: mean 0.05, mean d^2 0.035 -> 10 sqrt(0.035 - 0.85 * 0.0025)
    gt = as_batch([1.0, 2.0, 4.0, 8.0])
    d = as_batch([0.1, -0.2, 0.3, 0.0])
    pred = gt * torch.exp(d)
    expected = 10 * math.sqrt(0.035 - 0.85 * 0.05**2)
    assert silog_loss(pred, gt).item() == pytest.approx(expected, rel=1e-10)
    # lambda and alpha are parameters
    assert silog_loss(pred, gt, lam=1.0, alpha=1.0).item() == pytest.approx(
        math.sqrt(0.035 - 0.0025), rel=1e-10
    )


def test_silog_all_equal_and_perfect():
    gt = as_batch([1.0, 3.0, 7.0])
    # every d = 0.2: 10 sqrt(0.04 (1 - 0.85))
    shifted = silog_loss(gt * math.exp(0.2), gt)
    assert shifted.item() == pytest.approx(10 * math.sqrt(0.04 * 0.15), rel=1e-10)
    # scale invariant only for lambda = 1
    assert silog_loss(gt * math.exp(0.2), gt, lam=1.0).item() == pytest.approx(0.0, abs=1e-6)
    pred = gt.clone().requires_grad_()
    loss = silog_loss(pred, gt)
    assert loss.item() == 0.0
    loss.backward()
    assert torch.isfinite(pred.grad).all() and (pred.grad == 0).all()


def test_silog_nonpositive_prediction_is_finite():
    gt = as_batch([1.0, 2.0])
    pred = as_batch([-1.0, 0.0]).requires_grad_()
    loss = silog_loss(pred, gt)
    assert torch.isfinite(loss)
    loss.backward()
    assert torch.isfinite(pred.grad).all()


@pytest.mark.parametrize("name", ["l1", "mse", "berhu", "silog"])
def test_no_valid_pixel_gives_zero_loss_with_graph(name):
    gt = torch.zeros(2, 1, 3, 3)
    pred = torch.rand(2, 1, 3, 3, requires_grad=True)
    loss = depth_loss(name, pred, gt)
    assert loss.item() == 0.0
    loss.backward()
    assert (pred.grad == 0).all()


@pytest.mark.parametrize("name", ["l1", "mse", "berhu", "silog"])
def test_loss_decreases_toward_gt(name):
    gt = torch.rand(2, 1, 4, 5) * 30 + 1
    far = depth_loss(name, gt * 1.5 + 2, gt).item()
    near = depth_loss(name, gt * 1.05 + 0.1, gt).item()
    assert 0 < near < far


def test_bad_input():
    with pytest.raises(ParameterError, match="unknown loss"):
        depth_loss("huber", torch.ones(1, 1, 2, 2), torch.ones(1, 1, 2, 2))
    with pytest.raises(ParameterError, match="differ"):
        l1_loss(torch.ones(1, 1, 2, 2), torch.ones(1, 1, 2, 3))
