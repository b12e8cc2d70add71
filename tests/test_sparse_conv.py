"""Sparse convolutions (train/sparse_conv.py) against torch's dense conv2d on the zero-filled map.

Every reference here is dense torch code written in this file: ``F.conv2d`` on the map with
zeros at the inactive pixels, sampled at the active output sites (float64, 1e-10).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from sparsetools.errors import ParameterError
from sparsetools.train.sparse_conv import (
    SparseActivation,
    SparseBatchNorm,
    SparseConv2d,
    SparseTensor,
    SubmanifoldConv2d,
    SubmanifoldDepthwiseConv2d,
    dense_conv_weight,
    sparse_add,
    sparse_conv2d,
    sparse_global_avg,
    submanifold_conv2d,
    submanifold_depthwise_conv2d,
    to_dense,
)

TOL = 1e-10


def conv_weight_ref(w: torch.Tensor) -> torch.Tensor:
    """(k*k, C_in, C_out) taps in row-major kernel order -> nn.Conv2d's (C_out, C_in, k, k)."""
    k = math.isqrt(w.shape[0])
    out = torch.empty(w.shape[2], w.shape[1], k, k, dtype=w.dtype)
    for ky in range(k):
        for kx in range(k):
            out[:, :, ky, kx] = w[ky * k + kx].T
    return out


def depthwise_weight_ref(w: torch.Tensor) -> torch.Tensor:
    """(k*k, C, m) -> grouped conv weight (C*m, 1, k, k): output c*m + j reads channel c."""
    k = math.isqrt(w.shape[0])
    C, m = w.shape[1], w.shape[2]
    out = torch.empty(C * m, 1, k, k, dtype=w.dtype)
    for c in range(C):
        for j in range(m):
            for ky in range(k):
                for kx in range(k):
                    out[c * m + j, 0, ky, kx] = w[ky * k + kx, c, j]
    return out


def random_map(seed, B, C, H, W, density, dtype=torch.float64):
    """Dense (B, C, H, W) map, zero outside a random mask, and that mask (B, H, W)."""
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(B, H, W, generator=g) < density
    dense = torch.randn(B, C, H, W, generator=g, dtype=dtype) * mask[:, None]
    return dense, mask


def at_sites(dense: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """(N, C) values of a dense (B, C, H, W) map at (b, y, x) sites."""
    b, y, x = coords[:, 0], coords[:, 1], coords[:, 2]
    return dense.permute(0, 2, 3, 1)[b, y, x]


def downsampled_sites(mask: torch.Tensor) -> set[tuple[int, int, int]]:
    """unique(floor(C / 2)) of the active sites, by a Python set."""
    return {(int(b), int(y) // 2, int(x) // 2) for b, y, x in torch.nonzero(mask)}


CASES = [  # (seed, B, C_in, H, W, density)
    (0, 2, 3, 7, 9, 0.3),
    (1, 1, 2, 1, 1, 1.0),  # a single pixel
    (2, 2, 1, 5, 1, 0.6),  # one column
    (3, 3, 4, 11, 13, 0.05),  # very sparse
    (4, 2, 2, 6, 8, 1.0),  # fully dense
    (5, 1, 3, 17, 5, 0.5),
]


def corner_mask(B, H, W):
    """Only the four corners and the border middles of every sample (border handling)."""
    m = torch.zeros(B, H, W, dtype=torch.bool)
    for y in (0, H // 2, H - 1):
        for x in (0, W // 2, W - 1):
            if y in (0, H - 1) or x in (0, W - 1):
                m[:, y, x] = True
    return m


def masked_case(seed, B, C, H, W, mask):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, C, H, W, generator=g, dtype=torch.float64) * mask[:, None], mask


def special_cases():
    yield masked_case(10, 2, 3, 6, 7, corner_mask(2, 6, 7))
    empty_sample = torch.rand(3, 5, 6, generator=torch.Generator().manual_seed(11)) < 0.4
    empty_sample[1] = False
    yield masked_case(11, 3, 2, 5, 6, empty_sample)
    single = torch.zeros(2, 9, 8, dtype=torch.bool)
    single[1, 4, 7] = True
    yield masked_case(12, 2, 3, 9, 8, single)


def all_cases():
    for seed, B, C, H, W, d in CASES:
        yield random_map(seed, B, C, H, W, d)
    yield from special_cases()


@pytest.mark.parametrize("k", [1, 3, 5])
def test_submanifold_equals_conv2d_at_active_sites(k):
    for case, (dense, mask) in enumerate(all_cases()):
        C = dense.shape[1]
        torch.manual_seed(case)
        conv = SubmanifoldConv2d(C, 4, k).double()
        x = SparseTensor.from_dense(dense, mask=mask)
        y = conv(x)
        ref = F.conv2d(dense, conv_weight_ref(conv.weight.detach()), conv.bias, padding=k // 2)
        assert torch.equal(y.coords, x.coords)
        assert y.feats.shape == (int(mask.sum()), 4)
        if y.num_sites:
            assert (y.feats - at_sites(ref, x.coords)).abs().max().item() < TOL


@pytest.mark.parametrize("k", [2, 3])
def test_strided_equals_conv2d_at_downsampled_sites(k):
    for case, (dense, mask) in enumerate(all_cases()):
        _, C, H, W = dense.shape
        torch.manual_seed(case)
        conv = SparseConv2d(C, 5, k).double()
        x = SparseTensor.from_dense(dense, mask=mask, stride=2)
        y = conv(x)
        if k == 2:  # conv2d(k=2, s=2) on the map padded bottom/right to even size
            ref = F.conv2d(
                F.pad(dense, (0, W % 2, 0, H % 2)), conv_weight_ref(conv.weight.detach()), stride=2
            )
        else:
            ref = F.conv2d(dense, conv_weight_ref(conv.weight.detach()), stride=2, padding=1)
        ref = ref + conv.bias.detach()[None, :, None, None]
        assert y.spatial_shape == ((H + 1) // 2, (W + 1) // 2) == tuple(ref.shape[2:])
        assert y.stride == 4
        got = {tuple(c) for c in y.coords.tolist()}
        assert got == downsampled_sites(mask)
        assert y.num_sites == len(got)  # unique
        if y.num_sites:
            assert (y.feats - at_sites(ref, y.coords)).abs().max().item() < TOL


def test_strided_k2_outputs_are_exactly_the_windows_with_an_active_input():
    dense, mask = random_map(20, 2, 2, 9, 11, 0.15)
    x = SparseTensor.from_dense(dense, mask=mask)
    y = SparseConv2d(2, 3, 2)(x.replace_feats(x.feats.float()))
    window_has_input = F.max_pool2d(F.pad(mask[:, None].float(), (0, 1, 0, 1)), 2)[:, 0] > 0
    assert {tuple(c) for c in y.coords.tolist()} == {
        tuple(c) for c in torch.nonzero(window_has_input).tolist()
    }


def test_depthwise_equals_grouped_conv2d():
    for case, (dense, mask) in enumerate(all_cases()):
        C = dense.shape[1]
        torch.manual_seed(case)
        conv = SubmanifoldDepthwiseConv2d(C, 2, 3).double()
        x = SparseTensor.from_dense(dense, mask=mask)
        y = conv(x)
        w = depthwise_weight_ref(conv.weight.detach())
        ref = F.conv2d(dense, w, conv.bias, padding=1, groups=C)
        assert y.num_channels == 2 * C
        if y.num_sites:
            assert (y.feats - at_sites(ref, x.coords)).abs().max().item() < TOL


def test_dense_conv_weight_matches_the_reference_layout():
    w = torch.randn(9, 3, 4, dtype=torch.float64)
    assert torch.equal(dense_conv_weight(w), conv_weight_ref(w))
    assert torch.equal(dense_conv_weight(w, depthwise=True), depthwise_weight_ref(w))


def test_gradients_equal_dense_gradients():
    dense, mask = random_map(30, 2, 3, 8, 7, 0.4)
    conv = SubmanifoldConv2d(3, 2, 3).double()
    x = SparseTensor.from_dense(dense, mask=mask)
    f = x.feats.clone().requires_grad_(True)
    g = torch.randn(x.num_sites, 2, dtype=torch.float64)
    (conv(x.replace_feats(f)).feats * g).sum().backward()
    d = dense.clone().requires_grad_(True)
    w = conv_weight_ref(conv.weight.detach()).requires_grad_(True)
    ref = F.conv2d(d, w, padding=1)
    grad_map = torch.zeros_like(ref)
    b, yy, xx = x.coords.T
    grad_map[b, :, yy, xx] = g
    (ref * grad_map).sum().backward()
    assert (f.grad - at_sites(d.grad, x.coords)).abs().max().item() < TOL
    assert (conv_weight_ref(conv.weight.grad) - w.grad).abs().max().item() < TOL


def small_tensor(seed=40, C=2, stride=1):
    dense, mask = random_map(seed, 2, C, 5, 6, 0.45)
    mask[0, 0, 0] = mask[1, 4, 5] = True  # corners
    return SparseTensor.from_dense(dense * mask[:, None] + 0.0, mask=mask, stride=stride)


@pytest.mark.parametrize(
    "fn, shape",
    [
        (submanifold_conv2d, (9, 2, 3)),
        (sparse_conv2d, (4, 2, 3)),
        (sparse_conv2d, (9, 2, 3)),
        (submanifold_depthwise_conv2d, (9, 2, 2)),
    ],
)
def test_gradcheck_convs(fn, shape):
    x = small_tensor()
    g = torch.Generator().manual_seed(1)
    f = torch.randn(x.num_sites, 2, generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.randn(*shape, generator=g, dtype=torch.float64, requires_grad=True)
    n_bias = shape[2] * (shape[1] if fn is submanifold_depthwise_conv2d else 1)
    b = torch.randn(n_bias, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f, w, b: fn(x.replace_feats(f), w, b).feats, (f, w, b))


def test_gradcheck_batch_norm():
    x = small_tensor()
    bn = SparseBatchNorm(2).double()
    f = x.feats.clone().requires_grad_(True)
    w = torch.tensor([0.7, 1.8], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([-0.4, 0.9], dtype=torch.float64, requires_grad=True)

    def run(f, w, b):
        params = {"weight": w, "bias": b}
        return torch.func.functional_call(bn, params, (x.replace_feats(f),)).feats

    assert torch.autograd.gradcheck(run, (f, w, b))


def test_batch_norm_uses_the_statistics_of_the_active_sites():
    x = small_tensor()
    bn = SparseBatchNorm(2).double()
    y = bn(x).feats
    f = x.feats
    mean = f.mean(0)
    var = ((f - mean) ** 2).mean(0)
    assert (y - (f - mean) / torch.sqrt(var + bn.eps)).abs().max().item() < TOL
    n = f.shape[0]
    assert (bn.running_mean - 0.1 * mean).abs().max() < TOL  # momentum 0.1 from 0
    assert (bn.running_var - (0.9 + 0.1 * var * n / (n - 1))).abs().max() < TOL


def test_batch_norm_with_one_or_no_site():
    one = SparseTensor.from_coords(
        torch.tensor([[0, 1, 1]]), torch.tensor([[2.0, -1.0]]), batch_size=1, spatial_shape=(3, 3)
    )
    bn = SparseBatchNorm(2)
    y = bn(one)  # training, one site: running statistics, left unchanged
    assert torch.allclose(y.feats, one.feats / math.sqrt(1 + bn.eps))
    assert torch.equal(bn.running_mean, torch.zeros(2))
    none = SparseTensor.from_coords(
        torch.zeros(0, 3, dtype=torch.int64),
        torch.zeros(0, 2),
        batch_size=2,
        spatial_shape=(3, 3),
    )
    assert bn(none).feats.shape == (0, 2)


def test_global_average_per_sample_and_empty_sample():
    dense, mask = random_map(50, 3, 4, 6, 5, 0.5)
    mask[2] = False
    x = SparseTensor.from_dense(dense * mask[:, None], mask=mask)
    avg = sparse_global_avg(x)
    for b in range(3):
        sites = mask[b]
        ref = dense[b][:, sites].mean(1) if sites.any() else torch.zeros(4, dtype=torch.float64)
        assert (avg[b] - ref).abs().max().item() < TOL
    assert torch.equal(avg[2], torch.zeros(4, dtype=torch.float64))


@pytest.mark.parametrize("stride", [1, 2, 8])
def test_s2d_of_d2s_is_the_identity(stride):
    dense, mask = random_map(60, 2, 3, 7, 10, 0.3)
    x = SparseTensor.from_dense(dense, mask=mask, stride=stride)
    assert torch.equal(x.to_dense(), dense)
    assert torch.equal(to_dense(x), dense)
    # default mask: any channel non-zero, as train/sparse.py's D2S
    assert torch.equal(SparseTensor.from_dense(dense, stride=stride).to_dense(), dense)


def test_to_dense_at_a_finer_scale_and_padded():
    dense, mask = random_map(61, 2, 3, 5, 7, 0.4)
    x = SparseTensor.from_dense(dense, mask=mask, stride=4)
    up = to_dense(x, stride=1)
    ref = dense.repeat_interleave(4, dim=2).repeat_interleave(4, dim=3)
    assert torch.equal(up, ref)
    cropped = to_dense(x, stride=2, shape=(9, 13))
    assert torch.equal(cropped, dense.repeat_interleave(2, 2).repeat_interleave(2, 3)[..., :9, :13])
    padded = to_dense(x, shape=(8, 16))
    assert torch.equal(padded[..., :5, :7], dense) and padded[..., 5:, :].abs().sum() == 0
    with pytest.raises(ParameterError, match="stride"):
        to_dense(x, stride=3)


def test_site_order_does_not_matter():
    dense, mask = random_map(70, 2, 3, 8, 9, 0.4)
    x = SparseTensor.from_dense(dense, mask=mask)
    perm = torch.randperm(x.num_sites, generator=torch.Generator().manual_seed(0))
    shuffled = SparseTensor.from_coords(
        x.coords[perm], x.feats[perm], batch_size=2, spatial_shape=(8, 9)
    )
    assert torch.equal(shuffled.coords, x.coords) and torch.equal(shuffled.feats, x.feats)
    torch.manual_seed(0)
    conv = SubmanifoldConv2d(3, 4).double()
    down = SparseConv2d(4, 2, 3).double()
    a = down(conv(x)).to_dense()
    b = down(conv(shuffled)).to_dense()
    assert torch.equal(a, b)
    assert torch.equal(a, down(conv(x)).to_dense())  # repeated call: bit-identical


def test_bad_coordinates_are_refused():
    feats = torch.zeros(2, 1)
    with pytest.raises(ParameterError, match="unique"):
        SparseTensor.from_coords(
            torch.tensor([[0, 1, 1], [0, 1, 1]]), feats, batch_size=1, spatial_shape=(3, 3)
        )
    with pytest.raises(ParameterError, match="outside"):
        SparseTensor.from_coords(
            torch.tensor([[0, 1, 1], [0, 3, 0]]), feats, batch_size=1, spatial_shape=(3, 3)
        )
    with pytest.raises(ParameterError, match="outside"):
        SparseTensor.from_coords(
            torch.tensor([[1, 1, 1], [0, 0, 0]]), feats, batch_size=1, spatial_shape=(3, 3)
        )
    with pytest.raises(ParameterError, match="row-major"):
        SparseTensor(torch.tensor([[0, 2, 1], [0, 1, 1]]), feats, 1, (3, 3))
    with pytest.raises(ParameterError, match="int64"):
        SparseTensor(torch.tensor([[0, 1, 1]], dtype=torch.int32), feats[:1], 1, (3, 3))


def test_layer_argument_errors():
    x = small_tensor()
    with pytest.raises(ParameterError, match="odd"):
        SubmanifoldConv2d(2, 2, 2)
    with pytest.raises(ParameterError, match="2 or 3"):
        SparseConv2d(2, 2, 4)
    with pytest.raises(ParameterError, match="stride"):
        SparseConv2d(2, 2, 2, stride=3)
    with pytest.raises(ParameterError, match="input channels"):
        SubmanifoldConv2d(3, 2).double()(x)
    with pytest.raises(ParameterError, match="in_channels"):
        SubmanifoldConv2d(0, 2)


def test_kernel_maps_are_cached_and_shared_by_tensors_on_the_same_sites():
    x = small_tensor()
    c1, c2 = SubmanifoldConv2d(2, 3).double(), SubmanifoldConv2d(3, 3).double()
    act = SparseActivation(torch.nn.LeakyReLU(0.1))
    y = c2(act(c1(x)))
    assert y.cache is x.cache and list(x.cache.submanifold) == [3]
    kmap = x.cache.submanifold[3]
    c2(y)
    assert x.cache.submanifold[3] is kmap  # looked up once
    a = SparseConv2d(2, 3, 2).double()(x)
    b = SparseConv2d(2, 3, 3).double()(x)
    assert a.coords is b.coords and a.cache is b.cache
    assert torch.equal(sparse_add(a, b).feats, a.feats + b.feats)
    with pytest.raises(ParameterError, match="different sites"):
        sparse_add(a, x.replace_feats(x.feats[:, :1].repeat(1, 3)))


def test_pair_counts_match_shifted_masks():
    dense, mask = random_map(80, 2, 1, 9, 12, 0.35)
    x = SparseTensor.from_dense(dense, mask=mask)
    SubmanifoldConv2d(1, 1)(x.replace_feats(x.feats.float()))
    kmap = x.cache.submanifold[3]
    m = mask.numpy()
    for (dy, dx), n in zip(kmap.offsets, kmap.pair_counts, strict=True):
        if (dy, dx) == (0, 0):
            continue
        shifted = np.zeros_like(m)  # shifted[p] = m[p + d]
        ys, xs = (
            slice(max(0, -dy), m.shape[1] - max(0, dy)),
            slice(max(0, -dx), m.shape[2] - max(0, dx)),
        )
        yd, xd = (
            slice(max(0, dy), m.shape[1] + min(0, dy)),
            slice(max(0, dx), m.shape[2] + min(0, dx)),
        )
        shifted[:, ys, xs] = m[:, yd, xd]
        assert n == int((m & shifted).sum()), (dy, dx)


def test_initialisation_matches_nn_conv2d():
    torch.manual_seed(0)
    ours = SubmanifoldConv2d(16, 32, 3)
    ref = torch.nn.Conv2d(16, 32, 3)
    bound = 1 / math.sqrt(16 * 9)
    a, b = ours.weight, ref.weight  # 4608 draws each: max and std pin the distribution
    assert a.abs().max() <= bound and abs(a.abs().max().item() - b.abs().max().item()) < 0.01
    assert abs(a.std().item() - b.std().item()) < 0.05 * b.std().item()
    assert ours.bias.abs().max() <= bound and ours.bias.std() > 0.3 * bound
    dw = SubmanifoldDepthwiseConv2d(8, 2, 3)  # fan-in 9, as nn.Conv2d(8, 16, 3, groups=8)
    assert dw.weight.abs().max() <= 1 / 3 and dw.weight.abs().max() > 0.3


def test_dtype_and_empty_batch():
    dense, mask = random_map(90, 2, 2, 4, 5, 0.5, dtype=torch.float32)
    x32 = SparseTensor.from_dense(dense, mask=mask)
    assert SubmanifoldConv2d(2, 3)(x32).feats.dtype == torch.float32
    empty = SparseTensor.from_dense(torch.zeros(2, 2, 4, 5))
    y = SparseConv2d(2, 3, 3)(SubmanifoldConv2d(2, 2)(empty))
    assert y.feats.shape == (0, 3) and y.spatial_shape == (2, 3)
    assert torch.equal(y.to_dense(), torch.zeros(2, 3, 2, 3))
    assert torch.equal(sparse_global_avg(y), torch.zeros(2, 3))
