"""EffisDepth SFE (train/sfe.py): RR/SE/SGB against masked dense references, shapes, sizes.

The dense references are written here with ``F.conv2d``: a submanifold layer equals the dense
layer applied to the zero-filled map and multiplied by the active-site mask; BatchNorm is
compared in eval mode (fixed statistics) where the two normalise alike.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from sparsetools.errors import ParameterError
from sparsetools.train.sfe import (
    PAPER_WIDTHS,
    SMALL_WIDTHS,
    UNET_SCALES,
    DenseLidarEncoder,
    EncoderLayout,
    RRLayer,
    SELayer,
    SlenderGroupBlock,
    SparseFeatureExtractor,
    count_parameters,
    paper_sized,
    unet_encoder_widths,
)
from sparsetools.train.sparse_conv import SparseTensor, to_dense

TOL = 1e-10
SLOPE = 0.1


def conv_weight_ref(w):
    k = math.isqrt(w.shape[0])
    return w.detach().reshape(k, k, w.shape[1], w.shape[2]).permute(3, 2, 0, 1)


def sparse_map(seed, B=2, C=3, H=9, W=11, density=0.3):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(B, H, W, generator=g) < density
    dense = torch.randn(B, C, H, W, generator=g, dtype=torch.float64) * mask[:, None]
    return dense, mask


def randomise_bn(module, seed=0):
    """Non-trivial BN statistics and affine parameters, then eval mode."""
    g = torch.Generator().manual_seed(seed)
    for m in module.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            n = m.num_features
            m.running_mean.copy_(torch.randn(n, generator=g))
            m.running_var.copy_(torch.rand(n, generator=g) + 0.5)
            m.weight.data.copy_(torch.rand(n, generator=g) + 0.5)
            m.bias.data.copy_(torch.randn(n, generator=g))
    return module.eval()


def bn_ref(bn, x):
    return F.batch_norm(x, bn.running_mean, bn.running_var, bn.weight, bn.bias, False, 0.0, bn.eps)


def rr_ref(rr, x, mask):
    conv, bn, _ = rr.primary
    k = conv.kernel_size
    y = F.conv2d(x, conv_weight_ref(conv.weight), padding=k // 2) * mask
    y = F.leaky_relu(bn_ref(bn, y), SLOPE) * mask
    if rr.cheap is not None:
        w = rr.cheap.weight.detach()  # (k*k, C, m) -> grouped (C*m, 1, k, k)
        kk = math.isqrt(w.shape[0])
        wd = w.reshape(kk, kk, -1).permute(2, 0, 1).unsqueeze(1)
        cheap = F.conv2d(y, wd, padding=kk // 2, groups=y.shape[1]) * mask
        y = torch.cat([y, cheap], dim=1)
    return y[:, : rr.out_channels]


def se_ref(se, x, mask):
    count = mask.sum(dim=(2, 3)).clamp(min=1)
    squeezed = x.sum(dim=(2, 3)) / count
    gate = torch.sigmoid(se.fc2(torch.relu(se.fc1(squeezed))))
    return x * gate[:, :, None, None]


def sgb_ref(block, x, mask):
    """Masked dense SGB, stride 1."""
    rr, bn, _, se = block.main
    y = se_ref(se, F.leaky_relu(bn_ref(bn, rr_ref(rr, x, mask)), SLOPE) * mask, mask)
    if block.shortcut is None:
        res = x
    else:
        conv, bn2 = block.shortcut
        res = bn_ref(bn2, F.conv2d(x, conv_weight_ref(conv.weight))) * mask
    return F.leaky_relu(y + res, SLOPE) * mask


def test_rr_layer_equals_masked_dense_reference_and_stays_on_the_sites():
    dense, mask = sparse_map(0)
    m = mask[:, None].double()
    for out, ratio in ((8, 2), (7, 2), (6, 3), (5, 1)):
        torch.manual_seed(out)
        rr = randomise_bn(RRLayer(3, out, ratio=ratio).double())
        x = SparseTensor.from_dense(dense, mask=mask)
        y = rr(x)
        assert torch.equal(y.coords, x.coords) and y.num_channels == out
        assert (y.to_dense() - rr_ref(rr, dense, m)).abs().max().item() < TOL


def test_se_layer_equals_dense_reference_with_an_empty_sample():
    dense, mask = sparse_map(1, B=3, C=6)
    mask[1] = False
    dense = dense * mask[:, None]
    se = SELayer(6, reduction=2).double()
    x = SparseTensor.from_dense(dense, mask=mask)
    y = se(x)
    assert torch.equal(y.coords, x.coords) and y.num_channels == 6
    assert (y.to_dense() - se_ref(se, dense, mask[:, None])).abs().max().item() < TOL


def test_gradcheck_se_layer():
    dense, mask = sparse_map(2, B=2, C=4, H=5, W=6, density=0.4)
    x = SparseTensor.from_dense(dense, mask=mask)
    se = SELayer(4, reduction=2).double()
    f = x.feats.clone().requires_grad_(True)
    params = {k: v.detach().clone().requires_grad_(True) for k, v in se.named_parameters()}
    names = list(params)

    def run(f, *p):
        out = torch.func.functional_call(
            se, dict(zip(names, p, strict=True)), (x.replace_feats(f),)
        )
        return out.feats

    assert torch.autograd.gradcheck(run, (f, *params.values()))


@pytest.mark.parametrize("c_in, c_out", [(4, 4), (3, 6)])
def test_sgb_equals_masked_dense_reference(c_in, c_out):
    dense, mask = sparse_map(3, C=c_in)
    torch.manual_seed(c_out)
    block = randomise_bn(SlenderGroupBlock(c_in, c_out).double())
    assert (block.shortcut is None) == (c_in == c_out)
    x = SparseTensor.from_dense(dense, mask=mask)
    y = block(x)
    assert torch.equal(y.coords, x.coords)
    ref = sgb_ref(block, dense, mask[:, None].double())
    assert (y.to_dense() - ref).abs().max().item() < TOL


def test_strided_sgb_downsamples_first_and_stays_on_the_coarse_sites():
    dense, mask = sparse_map(4, C=3, H=13, W=10)
    torch.manual_seed(0)
    block = randomise_bn(SlenderGroupBlock(3, 5, stride=4).double())
    x = SparseTensor.from_dense(dense, mask=mask)
    y = block(x)
    assert y.stride == 4 and y.spatial_shape == (4, 3)
    coarse = {(int(b), int(yy) // 4, int(xx) // 4) for b, yy, xx in torch.nonzero(mask)}
    assert {tuple(c) for c in y.coords.tolist()} == coarse
    # reference: two k=2 s=2 convs (bottom/right zero padding), masked, then the SGB
    h, m = dense, mask[:, None].double()
    for conv, bn in ((block.down[0], block.down[1]), (block.down[3], block.down[4])):
        h = F.pad(h, (0, h.shape[-1] % 2, 0, h.shape[-2] % 2))
        m = F.max_pool2d(F.pad(m, (0, m.shape[-1] % 2, 0, m.shape[-2] % 2)), 2)
        h = F.leaky_relu(bn_ref(bn, F.conv2d(h, conv_weight_ref(conv.weight), stride=2)), SLOPE)
        h = h * m
    assert (y.to_dense() - sgb_ref(block, h, m)).abs().max().item() < TOL


ODD = (37, 53)


def depth_map(seed, B=2, H=ODD[0], W=ODD[1], density=0.05, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    valid = torch.rand(B, 1, H, W, generator=g) < density
    return (torch.rand(B, 1, H, W, generator=g, dtype=dtype) * 70 + 2) * valid


def test_sfe_output_shapes_at_every_scale_for_odd_sizes_and_dense_twin_alike():
    depth = depth_map(0)
    sfe = SparseFeatureExtractor(widths=SMALL_WIDTHS)
    dense = DenseLidarEncoder(widths=SMALL_WIDTHS)
    want = [
        (2, c, -(-ODD[0] // s), -(-ODD[1] // s))
        for c, s in zip(SMALL_WIDTHS, sfe.scales, strict=True)
    ]
    assert [tuple(o.shape) for o in sfe(depth)] == want
    assert [tuple(o.shape) for o in dense(depth)] == want
    assert sfe.output_shapes(*ODD) == [w[2:] for w in want]
    assert count_parameters(sfe) == count_parameters(dense)


def test_sfe_outputs_only_at_active_sites_of_each_scale():
    depth = depth_map(1)
    sfe = SparseFeatureExtractor(widths=SMALL_WIDTHS, blocks_per_scale=(1, 2, 1, 1, 1, 2))
    sparse = sfe.forward_sparse(depth)
    valid = (depth > 0).double()
    for s, x in zip(sfe.scales, sparse, strict=True):
        m = valid
        for _ in range(int(math.log2(s))):
            m = F.max_pool2d(F.pad(m, (0, m.shape[-1] % 2, 0, m.shape[-2] % 2)), 2)
        assert x.stride == s and x.num_sites == int(m.sum())
        out = x.to_dense()
        assert torch.all(out[(m == 0).expand_as(out)] == 0)


def test_sfe_on_an_empty_map_and_nan_or_negative_depth():
    sfe = SparseFeatureExtractor(widths=SMALL_WIDTHS)
    outs = sfe(torch.zeros(2, 1, *ODD))
    assert all(torch.isfinite(o).all() and o.abs().sum() == 0 for o in outs)
    depth = depth_map(2)
    bad = depth.clone()
    bad[0, 0, 0, :5] = float("nan")
    bad[0, 0, 1, :5] = -3.0
    bad[0, 0, 2, :5] = float("inf")
    clean = depth.clone()
    clean[0, 0, :3, :5] = 0
    sfe.eval()
    assert all(torch.equal(a, b) for a, b in zip(sfe(bad), sfe(clean), strict=True))


def test_sfe_is_deterministic_and_independent_of_site_order():
    depth = depth_map(3, dtype=torch.float64)
    torch.manual_seed(0)
    sfe = SparseFeatureExtractor(widths=SMALL_WIDTHS).double()
    a = sfe(depth)
    b = sfe(depth)
    assert all(torch.equal(u, v) for u, v in zip(a, b, strict=True))
    x = sfe.sparse_input(depth)
    perm = torch.randperm(x.num_sites, generator=torch.Generator().manual_seed(1))
    shuffled = SparseTensor.from_coords(
        x.coords[perm], x.feats[perm], batch_size=x.batch_size, spatial_shape=x.spatial_shape
    )
    c = [to_dense(t) for t in sfe.encode(shuffled)]
    assert all(torch.equal(u, v) for u, v in zip(a, c, strict=True))


def test_sfe_trains_in_float64_with_finite_gradients_everywhere():
    depth = depth_map(4, dtype=torch.float64)
    sfe = SparseFeatureExtractor(widths=SMALL_WIDTHS).double()
    outs = sfe(depth)
    assert all(o.dtype == torch.float64 for o in outs)
    sum((o**2).mean() for o in outs).backward()
    grads = [p.grad for p in sfe.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)


def test_input_features_are_depth_over_80_and_a_constant():
    depth = torch.zeros(1, 1, 3, 4)
    depth[0, 0, 1, 2] = 40.0
    x = SparseFeatureExtractor(widths=SMALL_WIDTHS).sparse_input(depth)
    assert x.coords.tolist() == [[0, 1, 2]] and x.feats.tolist() == [[0.5, 1.0]]
    d = DenseLidarEncoder(widths=SMALL_WIDTHS).dense_input(depth)
    assert d[0, :, 1, 2].tolist() == [0.5, 1.0] and d.sum().item() == 1.5


@pytest.mark.parametrize("maps", [1, 2])
def test_sparse_and_dense_inputs_agree_for_one_or_two_depth_maps(maps):
    g = torch.Generator().manual_seed(7)
    depth = (
        torch.rand(2, maps, 6, 7, generator=g) * 50 * (torch.rand(2, maps, 6, 7, generator=g) < 0.3)
    )
    depth[0, 0, 0, 0] = float("nan")
    depth[1, -1, 2, 3] = -1.0
    sfe = SparseFeatureExtractor(widths=(4,), scales=(1,), depth_channels=maps)
    dense = DenseLidarEncoder(widths=(4,), scales=(1,), depth_channels=maps)
    x = sfe.sparse_input(depth)
    assert x.num_sites == int(((depth > 0) & torch.isfinite(depth)).any(dim=1).sum())
    assert torch.equal(x.to_dense(), dense.dense_input(depth))
    assert [o.shape[1] for o in sfe(depth)] == [4]


def test_for_unet_matches_the_unet_encoder_levels():
    from sparsetools.train.model import DepthCompletionUNet

    for width in (4, 8, 32):
        assert unet_encoder_widths(width) == DepthCompletionUNet(width=width).widths
    unet = DepthCompletionUNet("rgbd", width=4)
    shapes = []
    hooks = [
        b.register_forward_hook(lambda m, i, o: shapes.append(tuple(o.shape))) for b in unet.encoder
    ]
    H, W = 37, 53
    unet(torch.zeros(1, 4, H, W))
    for h in hooks:
        h.remove()
    sfe = SparseFeatureExtractor.for_unet(4)
    assert sfe.scales == UNET_SCALES
    # the U-Net pads to a multiple of 16: give the SFE the padded depth map
    padded = F.pad(depth_map(5, B=1, H=H, W=W), (0, (-W) % 16, 0, (-H) % 16))
    assert [tuple(o.shape) for o in sfe(padded)] == shapes


def test_parameter_counts_paper_sized_and_large():
    n = count_parameters(paper_sized())
    assert n == 1_403_064 and abs(n - 1.4e6) / 1.4e6 < 0.01
    large = count_parameters(paper_sized(large=True))
    assert abs(large - 22.7e6) / 22.7e6 < 0.03
    assert count_parameters(SparseFeatureExtractor(widths=SMALL_WIDTHS)) < 0.1 * n
    # hand count of one SGB 8 -> 8: RR 3x3 8->4 (288) + BN 4 (8) + dw 3x3 4x1 (36),
    # BN 8 (16), SE 8->2->8 (16 + 2 + 16 + 8): 390
    assert count_parameters(SlenderGroupBlock(8, 8)) == 390
    assert PAPER_WIDTHS[-1] * 4 == paper_sized(large=True).out_channels[-1]
    for options in (
        {"widths": PAPER_WIDTHS},
        {"widths": unet_encoder_widths(8), "scales": UNET_SCALES},
        {"widths": (5, 7, 9), "scales": (2, 8, 16), "blocks_per_scale": (2, 1, 3), "ratio": 3},
    ):
        n_sparse = count_parameters(SparseFeatureExtractor(**options))
        assert n_sparse == count_parameters(DenseLidarEncoder(**options))


def test_layout_and_input_errors():
    with pytest.raises(ParameterError, match="powers of two"):
        EncoderLayout((8, 8), scales=(1, 3))
    with pytest.raises(ParameterError, match="one entry per scale"):
        EncoderLayout((8, 8, 8), scales=(1, 2))
    with pytest.raises(ParameterError, match="down_kernel"):
        EncoderLayout((8,), scales=(1,), down_kernel=4)
    with pytest.raises(ParameterError, match="power of two"):
        SlenderGroupBlock(4, 4, stride=3)
    with pytest.raises(ParameterError, match="ratio"):
        RRLayer(4, 4, ratio=0)
    sfe = SparseFeatureExtractor(widths=(4, 4), scales=(2, 4))
    with pytest.raises(ParameterError, match=r"\(B, 1, H, W\)"):
        sfe(torch.zeros(1, 2, 8, 8))
    with pytest.raises(ParameterError, match="floating"):
        sfe(torch.zeros(1, 1, 8, 8, dtype=torch.int64))
    # a first scale above 1 downsamples the stem output
    assert [tuple(o.shape) for o in sfe(depth_map(6, B=1, H=9, W=9))] == [
        (1, 4, 5, 5),
        (1, 4, 3, 3),
    ]


@pytest.mark.real
def test_sfe_on_a_real_4_beam_kitti_map(kitti_object):
    import sparsetools as st

    points = st.read_points(kitti_object / "velodyne" / "000001.bin")
    calib = st.load_calibration(kitti_object / "calib" / "000001.txt").with_size(1242, 375)
    beams = st.select_beams(points, st.recover_rings(points), n=4).points
    depth = torch.from_numpy(st.project_points(beams, calib))[None, None]
    sfe = SparseFeatureExtractor(widths=SMALL_WIDTHS)
    x = sfe.sparse_input(depth)
    assert 0.002 < x.num_sites / depth.numel() < 0.006  # 4 beams: well under 1 % of pixels
    assert torch.equal(x.to_dense()[:, :1], depth / 80.0)  # S2D(D2S) of the real map
    m = (depth > 0).float()
    for s, out in zip(sfe.scales, sfe.forward_sparse(depth), strict=True):
        assert out.num_sites == int((F.max_pool2d(m, s, ceil_mode=True) > 0).sum())
