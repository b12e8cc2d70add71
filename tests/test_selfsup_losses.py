"""Self-supervised losses: SSIM, photometric error, smoothness, auto-mask, SBM, the batch loss."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sparsetools.errors import ParameterError
from sparsetools.train.config import SelfSupSettings
from sparsetools.train.losses import l1_loss
from sparsetools.train.selfsup.geometry import warp_frame
from sparsetools.train.selfsup.losses import selfsup_loss
from sparsetools.train.selfsup.masks import (
    StatisticsMask,
    auto_mask,
    percentile,
    temporal_change,
)
from sparsetools.train.selfsup.photometric import (
    photometric_error,
    ssim,
    ssim_dissimilarity,
)
from sparsetools.train.selfsup.smoothness import edge_aware_smoothness
from test_selfsup_scene import video


def ssim_reference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SSIM of two (H, W) images, window by window with explicit loops (reflect padding)."""
    c1, c2 = 0.01**2, 0.03**2
    pa, pb = np.pad(a, 1, mode="reflect"), np.pad(b, 1, mode="reflect")
    out = np.empty_like(a)
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            x, y = pa[i : i + 3, j : j + 3].ravel(), pb[i : i + 3, j : j + 3].ravel()
            mx, my = x.mean(), y.mean()
            vx, vy = ((x - mx) ** 2).mean(), ((y - my) ** 2).mean()
            cxy = ((x - mx) * (y - my)).mean()
            out[i, j] = ((2 * mx * my + c1) * (2 * cxy + c2)) / (
                (mx**2 + my**2 + c1) * (vx + vy + c2)
            )
    return out


def t(x):
    return torch.from_numpy(np.asarray(x, dtype=np.float64))


# -- SSIM and photometric error --------------------------------------------------------------------
def test_ssim_matches_reference():
    rng = np.random.default_rng(0)
    a = rng.random((2, 3, 5, 7))
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    got = ssim(t(a), t(b)).numpy()
    for i in range(2):
        for c in range(3):
            np.testing.assert_allclose(got[i, c], ssim_reference(a[i, c], b[i, c]), atol=1e-12)
    # identical images: SSIM 1, dissimilarity 0
    np.testing.assert_allclose(ssim(t(a), t(a)).numpy(), 1.0, atol=1e-12)
    assert float(ssim_dissimilarity(t(a), t(a)).abs().max()) < 1e-12


def test_photometric_error_hand_values():
    # constant images: variances and covariance are 0, SSIM = (2 ab + C1) / (a^2 + b^2 + C1)
    c1 = 0.01**2
    a_vals, b_vals = (0.2, 0.5, 0.9), (0.5, 0.5, 0.3)
    a = np.stack([np.full((4, 4), v) for v in a_vals])[None]
    b = np.stack([np.full((4, 4), v) for v in b_vals])[None]
    per_channel = [
        0.85 / 2 * (1 - (2 * x * y + c1) / (x * x + y * y + c1)) + 0.15 * abs(x - y)
        for x, y in zip(a_vals, b_vals, strict=True)
    ]
    pe = photometric_error(t(a), t(b))
    assert pe.shape == (1, 1, 4, 4)
    np.testing.assert_allclose(pe.numpy(), np.mean(per_channel), atol=1e-12)
    # alpha = 0: plain L1, channel mean
    np.testing.assert_allclose(
        photometric_error(t(a), t(b), alpha=0.0).numpy(),
        np.mean(np.abs(np.subtract(a_vals, b_vals))),
    )
    assert float(photometric_error(t(a), t(a)).abs().max()) < 1e-12
    with pytest.raises(ParameterError):
        photometric_error(t(a), t(b[:, :2]))
    with pytest.raises(ParameterError):
        photometric_error(t(a[..., :1]), t(b[..., :1]))  # 4x1: no 3x3 window


def test_photometric_error_of_textured_images_matches_reference():
    rng = np.random.default_rng(1)
    a, b = rng.random((1, 3, 6, 6)), rng.random((1, 3, 6, 6))
    ref = np.mean(
        [
            0.85 * np.clip((1 - ssim_reference(a[0, c], b[0, c])) / 2, 0, 1)
            + 0.15 * np.abs(a[0, c] - b[0, c])
            for c in range(3)
        ],
        axis=0,
    )
    np.testing.assert_allclose(photometric_error(t(a), t(b))[0, 0].numpy(), ref, atol=1e-12)


# -- smoothness -----------------------------------------------------------------------------------
def smoothness_reference(d: np.ndarray, img: np.ndarray) -> float:
    """monodepth2's formula with explicit loops over the pixel pairs; d (H, W), img (C, H, W)."""
    d = d / (d.mean() + 1e-7)
    h, w = d.shape
    sx = [
        abs(d[i, j + 1] - d[i, j]) * math.exp(-np.abs(img[:, i, j + 1] - img[:, i, j]).mean())
        for i in range(h)
        for j in range(w - 1)
    ]
    sy = [
        abs(d[i + 1, j] - d[i, j]) * math.exp(-np.abs(img[:, i + 1, j] - img[:, i, j]).mean())
        for i in range(h - 1)
        for j in range(w)
    ]
    return float(np.mean(sx) + np.mean(sy))


def test_smoothness_matches_reference_and_hand_values():
    rng = np.random.default_rng(2)
    d, img = rng.uniform(0.1, 1, (4, 5)), rng.random((3, 4, 5))
    got = float(edge_aware_smoothness(t(d)[None, None], t(img)[None]))
    assert got == pytest.approx(smoothness_reference(d, img), rel=1e-12)
    # hand value: disparity [[1, 3]] (mean 2 -> [[0.5, 1.5]]), flat image: |1.5 - 0.5| = 1 in x;
    # a 2x2 image repeating the row has no y differences
    d2 = np.array([[1.0, 3.0], [1.0, 3.0]])
    assert float(
        edge_aware_smoothness(t(d2)[None, None], torch.zeros(1, 3, 2, 2, dtype=torch.float64))
    ) == pytest.approx(1.0, rel=1e-6)
    # an image edge of height 1 where the disparity jumps weighs it by exp(-1)
    img2 = np.zeros((3, 2, 2))
    img2[:, :, 1] = 1.0
    assert float(edge_aware_smoothness(t(d2)[None, None], t(img2)[None])) == pytest.approx(
        math.exp(-1), rel=1e-6
    )


def test_smoothness_properties():
    rng = np.random.default_rng(3)
    d, img = t(rng.uniform(0.1, 1, (2, 1, 6, 7))), t(rng.random((2, 3, 6, 7)))
    base = float(edge_aware_smoothness(d, img))
    # mean normalisation: scaling the disparity changes nothing
    assert float(edge_aware_smoothness(7.5 * d, img)) == pytest.approx(base, rel=1e-6)
    # constant disparity is perfectly smooth
    assert float(edge_aware_smoothness(torch.full_like(d, 0.3), img)) == pytest.approx(
        0.0, abs=1e-12
    )
    with pytest.raises(ParameterError):
        edge_aware_smoothness(d[:, :, :1], img[:, :, :1])


# -- auto-mask and SBM ----------------------------------------------------------------------------
def test_percentile_is_nearest_rank():
    rng = np.random.default_rng(4)
    x = rng.random(1001)
    for q in (0, 10, 37.5, 50, 100):
        assert float(percentile(t(x), q)) == np.percentile(x, q, method="inverted_cdf")


def test_sbm_threshold_is_an_ewma_of_the_percentile():
    rng = np.random.default_rng(5)
    sbm = StatisticsMask(beta=0.98, q=10)
    expected = None
    for _ in range(5):
        change = rng.random((2, 2, 4, 4))
        stat = np.percentile(change, 10, method="inverted_cdf")
        expected = stat if expected is None else 0.98 * expected + 0.02 * stat
        sbm.update(t(change))
        assert sbm.threshold == pytest.approx(expected, rel=1e-12)
    change = t(rng.random((1, 2, 4, 4)))
    np.testing.assert_array_equal(sbm.mask(change).numpy(), change.numpy() > expected)
    with pytest.raises(ParameterError):
        StatisticsMask(beta=1.0)


def test_stopped_sequence_is_masked():
    """Identical frames (a stopped camera): the SBM masks every pixel, and so does the
    auto-mask for any warp that moves the (textured) image."""
    frame = video(1, 32, 48)[0]
    img = t(frame.rgb.transpose(2, 0, 1) / 255.0)[None]
    sources = torch.stack([img, img], dim=1)
    change = temporal_change(img, sources)
    assert float(change.abs().max()) == 0
    sbm = StatisticsMask()
    sbm.update(change)
    assert not bool(sbm.mask(change).any())
    # a network that believes the camera moves: its warp is worse than no warp at all
    depth = t(np.maximum(frame.depth, 1.0))[None, None]
    T = torch.eye(4, dtype=torch.float64)[None].clone()
    T[0, 2, 3] = -0.5
    K = t(frame.K)[None]
    warped = warp_frame(img, depth, T, K).image
    reprojection = torch.cat([photometric_error(warped, img)] * 2, dim=1)
    identity = torch.cat([photometric_error(img, img)] * 2, dim=1)
    mask = auto_mask(reprojection, identity, generator=torch.Generator().manual_seed(0))
    assert mask.shape == (1, 1, 32, 48)
    assert float(mask.double().mean()) < 0.1
    # an exact tie (both errors 0) is broken at random, as monodepth2 does: the minimum of
    # two noisy identity errors is < 0 with probability 3/4, so a quarter of the pixels stay
    tie = auto_mask(identity, identity, generator=torch.Generator().manual_seed(0))
    assert 0.18 < float(tie.double().mean()) < 0.32


def test_moving_object_is_masked_and_the_static_scene_kept():
    """A patch that moves with the camera: unchanged between frames, so both masks drop it,
    while the static street (warped with the true depth and pose) is kept."""
    frames = video(3, 48, 64, speed=1.0, patch=True)
    prev, tgt, nxt = frames
    imgs = [t(f.rgb.transpose(2, 0, 1) / 255.0)[None] for f in frames]
    depth = t(tgt.depth)[None, None]
    reproj, ident, inside = [], [], []
    for src, f in ((imgs[0], prev), (imgs[2], nxt)):
        warp = warp_frame(
            src, depth, t(np.linalg.inv(f.T_world_cam) @ tgt.T_world_cam)[None], t(tgt.K)[None]
        )
        reproj.append(photometric_error(warp.image, imgs[1]))
        ident.append(photometric_error(src, imgs[1]))
        inside.append(warp.inside)
    mask = auto_mask(
        torch.cat(reproj, 1), torch.cat(ident, 1), generator=torch.Generator().manual_seed(1)
    )[0, 0].numpy()
    h, w = tgt.depth.shape
    r0, c0, size = h // 3, w // 3, max(3, h // 4)
    patch = np.zeros((h, w), bool)
    patch[r0 : r0 + size, c0 : c0 + size] = True
    interior = np.zeros_like(patch)
    interior[r0 + 2 : r0 + size - 2, c0 + 2 : c0 + size - 2] = True
    assert not mask[interior].any()
    static = (inside[0] | inside[1])[0, 0].numpy() & ~patch & (tgt.depth > 0)
    static[: h // 8] = False  # far back wall and its sky edge barely move
    assert mask[static].mean() > 0.8
    # SBM: the patch does not change between frames, the street does
    change = temporal_change(imgs[1], torch.stack([imgs[0], imgs[2]], dim=1))
    sbm = StatisticsMask(q=10)
    sbm.update(change)
    kept = sbm.mask(change)[0].numpy()
    assert not kept[:, interior].any()
    assert kept[:, static].mean() > 0.7


# -- the batch loss ------------------------------------------------------------------------------
def _batch(frames, *, depth_scale=1.0):
    prev, tgt, nxt = frames
    stack = np.stack([f.rgb for f in frames]).transpose(0, 3, 1, 2) / 255.0
    K = t(tgt.K)[None]
    T = (
        t(np.linalg.inv(prev.T_world_cam) @ tgt.T_world_cam)[None],
        t(np.linalg.inv(nxt.T_world_cam) @ tgt.T_world_cam)[None],
    )
    depth = np.clip(np.where(tgt.depth > 0, tgt.depth, 100.0) * depth_scale, 0.1, 100.0)
    # the sigmoid output whose depth is the given depth: sigma = (1/d - 1/max) / (1/min - 1/max)
    sigma = (1 / depth - 1 / 100.0) / (1 / 0.1 - 1 / 100.0)
    disps = [t(sigma)[None, None]]
    for s in (1, 2, 3):
        disps.append(torch.nn.functional.interpolate(disps[0], scale_factor=0.5**s, mode="area"))
    return disps, t(stack)[None], K, T, t(tgt.depth)[None, None]


def test_batch_loss_prefers_the_true_depth():
    frames = video(3, 48, 64, speed=1.0)
    settings = SelfSupSettings(scales=1)
    disps, fr, K, T, gt = _batch(frames)
    true = selfsup_loss(disps, fr, K, T, settings, generator=torch.Generator().manual_seed(0))
    disps_w, *_ = _batch(frames, depth_scale=0.5)
    wrong = selfsup_loss(disps_w, fr, K, T, settings, generator=torch.Generator().manual_seed(0))
    assert true.photometric < 0.5 * wrong.photometric
    assert 0 < true.mask_fraction <= 1 and true.sparse == 0
    # the total at one scale: masked photometric term + smoothness
    assert float(true.total) == pytest.approx(
        true.masked_photometric + 1e-3 * true.smoothness, rel=1e-9
    )
    # the sparse term: L1 of the depth on the valid sparse pixels, weighted
    sparse = gt.clone()
    sparse[..., 1::2, :] = 0
    s2 = SelfSupSettings(scales=1, sparse_loss="l1", sparse_weight=0.5)
    with_sparse = selfsup_loss(
        disps_w, fr, K, T, s2, sparse=sparse, generator=torch.Generator().manual_seed(0)
    )
    from sparsetools.train.model import disparity_to_depth

    expected = float(l1_loss(disparity_to_depth(disps_w[0], 0.1, 100.0), sparse))
    assert with_sparse.sparse == pytest.approx(expected, rel=1e-9)
    assert float(with_sparse.total) == pytest.approx(float(wrong.total) + 0.5 * expected, rel=1e-9)
    # four scales: the total is the mean over scales
    four = selfsup_loss(
        disps, fr, K, T, SelfSupSettings(), generator=torch.Generator().manual_seed(0)
    )
    assert math.isfinite(float(four.total)) and four.photometric == pytest.approx(true.photometric)


def test_batch_loss_gradients_reach_depth_and_pose():
    frames = video(3, 32, 48)
    disps, fr, K, T, _ = _batch(frames)
    disps = [d.clone().requires_grad_(True) for d in disps]
    T = tuple(x.clone().requires_grad_(True) for x in T)
    terms = selfsup_loss(
        disps, fr, K, T, SelfSupSettings(), generator=torch.Generator().manual_seed(0)
    )
    terms.total.backward()
    assert all(d.grad is not None and torch.isfinite(d.grad).all() for d in disps)
    assert all(x.grad is not None and float(x.grad.abs().sum()) > 0 for x in T)
