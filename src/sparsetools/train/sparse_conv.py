"""Sparse 2-D convolutions on EffisDepth sparse tensors, in plain torch (any device).

The layers compute at the active sites of a :class:`~sparsetools.train.sparse_tensor.SparseTensor`
only, so their cost grows with the number of sites N, not with the image area (METHODS.md
section 9). The tensor type and the site-wise operations live in
:mod:`sparsetools.train.sparse_tensor` and are re-exported here, so one import gives the whole
sparse toolbox.

Neighbours: the key of ``p + d`` (masked where ``p + d`` leaves the image, as its key would
alias a pixel of the next row) is looked up in the sorted keys with
:func:`torch.searchsorted`, giving per kernel tap the (input row, output row) pairs of a
:class:`KernelMap`, cached on the coordinates (:class:`CoordinateCache`, shared by every
tensor on the same sites, so stacked convolutions at one scale look neighbours up once).

Convolution: ``out(p) = bias + sum_k W_k F(p + k)`` over taps whose input is active, per tap
gather -> matmul -> ``index_add_``. A row occurs at most once per tap, so no row is added
into twice by one scatter: deterministic on every device. Weights are ``(k*k, C_in, C_out)``,
taps in the row-major order of a dense kernel (``weight[ky * k + kx] == conv2d_weight[:, :,
ky, kx].T``, :func:`dense_conv_weight`), initialised like ``nn.Conv2d`` (uniform in
``+-1/sqrt(fan_in)``). Dense equivalents (``x0`` the zero-filled map; float64 tests, 1e-10):
submanifold (odd k) == ``conv2d(x0, padding=k // 2)`` at the input sites; strided k=2 ==
``conv2d(x0 padded bottom/right to even, stride=2)`` and strided k=3 == ``conv2d(x0, stride=2,
padding=1)``, both at the sites ``unique(floor(C / 2))`` of size ``(ceil(H/2), ceil(W/2))``;
depthwise == ``conv2d(x0, groups=C, padding=k // 2)``. Details: docs/sfe.md.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn
from torch.autograd.function import once_differentiable

from ..errors import ParameterError
from .sparse_tensor import (
    CoordinateCache,
    KernelMap,
    SparseTensor,
    positive_int,
    site_keys,
    sparse_add,
    sparse_cat,
    sparse_global_avg,
    to_dense,
)

__all__ = [
    "CoordinateCache",
    "KernelMap",
    "SparseActivation",
    "SparseBatchNorm",
    "SparseConv2d",
    "SparseTensor",
    "SubmanifoldConv2d",
    "SubmanifoldDepthwiseConv2d",
    "dense_conv_weight",
    "sparse_add",
    "sparse_cat",
    "sparse_conv2d",
    "sparse_global_avg",
    "strided_kernel_map",
    "submanifold_conv2d",
    "submanifold_depthwise_conv2d",
    "submanifold_kernel_map",
    "to_dense",
]


# -- kernel maps --------------------------------------------------------------------------------
def _taps(kernel_size: int, start: int) -> tuple[tuple[int, int], ...]:
    r = range(start, start + kernel_size)
    return tuple((dy, dx) for dy in r for dx in r)


def _lookup(keys, base, taps, shape) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
    """Per tap, (input row, base row) pairs where ``base + tap`` is an active input site.

    ``base`` (M, 3) ``(b, y, x)`` in input pixels; ``keys`` the sorted input keys.
    """
    H, W = shape
    d = torch.tensor(taps, dtype=torch.int64, device=base.device)  # (K, 2)
    y = base[None, :, 1] + d[:, 0:1]  # (K, M)
    x = base[None, :, 2] + d[:, 1:2]
    inside = (y >= 0) & (y < H) & (x >= 0) & (x < W)
    query = (base[None, :, 0] * H + y) * W + x
    n = keys.numel()
    if n == 0 or base.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=base.device)
        return (empty,) * len(taps), (empty,) * len(taps)
    pos = torch.searchsorted(keys, query).clamp_(max=n - 1)
    hit = inside & (keys[pos] == query)
    # one nonzero over all taps: rows come out grouped by tap, in increasing base order
    tap, row = torch.nonzero(hit, as_tuple=True)
    counts = torch.bincount(tap, minlength=len(taps)).tolist()
    return tuple(torch.split(pos[tap, row], counts)), tuple(torch.split(row, counts))


def submanifold_kernel_map(x: SparseTensor, kernel_size: int) -> KernelMap:
    """Kernel map of an odd ``kernel_size`` submanifold convolution on ``x`` (cached)."""
    cached = x.cache.submanifold.get(kernel_size)
    if cached is not None:
        return cached
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ParameterError(f"submanifold kernel_size must be odd, got {kernel_size}")
    taps = _taps(kernel_size, -(kernel_size // 2))
    centre = taps.index((0, 0))
    others = taps[:centre] + taps[centre + 1 :]
    ins, outs = _lookup(x.cache.keys, x.coords, others, x.spatial_shape) if others else ((), ())
    empty = torch.zeros(0, dtype=torch.int64, device=x.coords.device)  # centre: identity
    ins, outs = (*ins[:centre], empty, *ins[centre:]), (*outs[:centre], empty, *outs[centre:])
    kmap = KernelMap(kernel_size, 1, taps, ins, outs, x.num_sites, identity_tap=centre)
    x.cache.submanifold[kernel_size] = kmap
    return kmap


def _downsampled(x: SparseTensor) -> tuple[torch.Tensor, CoordinateCache, tuple[int, int]]:
    H, W = x.spatial_shape
    shape = ((H + 1) // 2, (W + 1) // 2)
    if x.cache.downsampled is None:
        c = x.coords
        coarse = torch.stack([c[:, 0], c[:, 1] // 2, c[:, 2] // 2], dim=1)
        keys = torch.unique(site_keys(coarse, shape))  # sorted: canonical order
        hw = shape[0] * shape[1]
        coords = torch.stack([keys // hw, (keys % hw) // shape[1], keys % shape[1]], dim=1)
        x.cache.downsampled = (coords, CoordinateCache(keys=keys))
    coords, cache = x.cache.downsampled
    return coords, cache, shape


def strided_kernel_map(x: SparseTensor, kernel_size: int) -> KernelMap:
    """Kernel map of a stride-2 convolution (kernel 2 or 3) from ``x`` to the coarser scale."""
    cached = x.cache.strided.get(kernel_size)
    if cached is not None:
        return cached
    if kernel_size not in (2, 3):
        raise ParameterError(f"strided kernel_size must be 2 or 3, got {kernel_size}")
    coords, _, _ = _downsampled(x)
    # kernel 2 reads 2o + {0, 1}; kernel 3 (padding 1) reads 2o + {-1, 0, 1}
    taps = _taps(kernel_size, 0 if kernel_size == 2 else -1)
    base = torch.stack([coords[:, 0], 2 * coords[:, 1], 2 * coords[:, 2]], dim=1)
    ins, outs = _lookup(x.cache.keys, base, taps, x.spatial_shape)
    kmap = KernelMap(kernel_size, 2, taps, ins, outs, int(coords.shape[0]))
    x.cache.strided[kernel_size] = kmap
    return kmap


# -- convolutions ---------------------------------------------------------------------------
def _tap(f: torch.Tensor, w: torch.Tensor, depthwise: bool) -> torch.Tensor:
    """One tap: rows (M, C_in) times ``w`` -> (M, C_out); a depthwise ``w`` is (C, m)."""
    if depthwise:
        return (f.unsqueeze(2) * w).reshape(f.shape[0], w.shape[0] * w.shape[1])
    return f @ w


class _GatherMatmulScatter(torch.autograd.Function):
    """``out[o] += tap_k(F[i])`` over the pairs of every tap, with a hand-written backward.

    One autograd node per convolution instead of three per tap, and the input gradient
    accumulates in one buffer instead of one zero-filled buffer per tap (no double backward).
    """

    @staticmethod
    def forward(ctx, feats, weight, kmap: KernelMap, depthwise: bool):
        c_out = weight.shape[1] * weight.shape[2] if depthwise else weight.shape[2]
        if kmap.identity_tap is not None:
            out = _tap(feats, weight[kmap.identity_tap], depthwise)
        else:
            out = feats.new_zeros((kmap.n_out, c_out))
        for k, (i_in, i_out) in enumerate(zip(kmap.in_index, kmap.out_index, strict=True)):
            if k != kmap.identity_tap and i_in.numel():
                out.index_add_(0, i_out, _tap(feats.index_select(0, i_in), weight[k], depthwise))
        ctx.save_for_backward(feats, weight)
        ctx.kmap, ctx.depthwise = kmap, depthwise
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        feats, weight = ctx.saved_tensors
        kmap, depthwise = ctx.kmap, ctx.depthwise
        need_f, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_f = torch.zeros_like(feats) if need_f else None
        grad_w = torch.zeros_like(weight) if need_w else None
        for k, (i_in, i_out) in enumerate(zip(kmap.in_index, kmap.out_index, strict=True)):
            identity = k == kmap.identity_tap
            if not identity and not i_in.numel():
                continue
            f_k = feats if identity else (feats.index_select(0, i_in) if need_w else None)
            g_k = grad_out if identity else grad_out.index_select(0, i_out)
            if depthwise:
                g_k = g_k.reshape(g_k.shape[0], weight.shape[1], weight.shape[2])
                if need_w:
                    grad_w[k] = (f_k.unsqueeze(2) * g_k).sum(0)
                g_in = (g_k * weight[k]).sum(2) if need_f else None
            else:
                if need_w:
                    grad_w[k] = f_k.T @ g_k
                g_in = g_k @ weight[k].T if need_f else None
            if need_f and identity:
                grad_f += g_in
            elif need_f:
                grad_f.index_add_(0, i_in, g_in)
        return grad_f, grad_w, None, None


def _conv(x: SparseTensor, weight, bias, *, strided: bool, depthwise: bool) -> SparseTensor:
    k = math.isqrt(int(weight.shape[0]))
    if weight.dim() != 3 or k * k != weight.shape[0]:
        raise ParameterError(f"weight must be (k*k, C_in, C_out), got {tuple(weight.shape)}")
    if x.num_channels != weight.shape[1]:
        raise ParameterError(
            f"layer expects {weight.shape[1]} input channels, got {x.num_channels}"
        )
    kmap = strided_kernel_map(x, k) if strided else submanifold_kernel_map(x, k)
    out = _GatherMatmulScatter.apply(x.feats, weight, kmap, depthwise)
    if bias is not None:
        out = out + bias
    if not strided:
        return x.replace_feats(out)
    coords, cache, shape = _downsampled(x)
    return SparseTensor(coords, out, x.batch_size, shape, 2 * x.stride, cache)


def submanifold_conv2d(x: SparseTensor, weight, bias=None) -> SparseTensor:
    """Submanifold convolution: outputs on the sites of ``x`` (sharing its cache).

    Parameters
    ----------
    x : SparseTensor, C_in channels
    weight : (k*k, C_in, C_out) tensor, k odd
    bias : (C_out,) tensor, optional
    """
    return _conv(x, weight, bias, strided=False, depthwise=False)


def submanifold_depthwise_conv2d(x: SparseTensor, weight, bias=None) -> SparseTensor:
    """Depthwise submanifold convolution: output channel ``c * m + j`` reads channel ``c``.

    Parameters
    ----------
    x : SparseTensor, C channels
    weight : (k*k, C, m) tensor, k odd
    bias : (C * m,) tensor, optional
    """
    return _conv(x, weight, bias, strided=False, depthwise=True)


def sparse_conv2d(x: SparseTensor, weight, bias=None) -> SparseTensor:
    """Stride-2 convolution onto the sites ``unique(floor(C / 2))``.

    Parameters
    ----------
    x : SparseTensor, C_in channels, stride s, spatial shape (H, W)
    weight : (k*k, C_in, C_out) tensor, k 2 or 3
    bias : (C_out,) tensor, optional

    Returns
    -------
    SparseTensor at stride 2 s, spatial shape ``(ceil(H / 2), ceil(W / 2))``.
    """
    return _conv(x, weight, bias, strided=True, depthwise=False)


class _SparseConvBase(nn.Module):
    """Weight ``(k*k, a, b)`` and optional bias, initialised like ``nn.Conv2d`` (fan-in)."""

    def __init__(
        self, k, shape, c_out, bias, fan_in, *, odd=True, names=("in_channels", "out_channels")
    ):
        super().__init__()
        shape = tuple(positive_int(n, v) for n, v in zip(names, shape, strict=True))
        if odd and (int(k) != k or k < 1 or k % 2 == 0):
            raise ParameterError(f"kernel_size must be odd for a submanifold conv, got {k!r}")
        self.kernel_size, self.in_channels, self.out_channels = int(k), shape[0], c_out
        self.weight = nn.Parameter(torch.empty(k * k, *shape))
        self.bias = nn.Parameter(torch.empty(c_out)) if bias else None
        # nn.Conv2d: kaiming_uniform_(a=sqrt(5)) = U(+-1/sqrt(fan_in)); its bias alike
        bound = 1.0 / math.sqrt(fan_in * k * k)
        with torch.no_grad():
            for p in (self.weight, self.bias):
                if p is not None:
                    p.uniform_(-bound, bound)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, "
            f"bias={self.bias is not None}"
        )


class SubmanifoldConv2d(_SparseConvBase):
    """Submanifold k x k convolution (k odd): outputs only at the input's active sites.

    ``out(p) = bias + sum_k W_k F(p + k)`` over the offsets with ``p + k`` active; equals
    ``conv2d(padding=k // 2)`` on the zero-filled map at the sites; initialised like
    ``nn.Conv2d(in_channels, out_channels, k)``.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, *, bias=True):
        super().__init__(kernel_size, (in_channels, out_channels), out_channels, bias, in_channels)

    def forward(self, x: SparseTensor) -> SparseTensor:
        return submanifold_conv2d(x, self.weight, self.bias)


class SubmanifoldDepthwiseConv2d(_SparseConvBase):
    """Depthwise submanifold k x k convolution, ``multiplier`` outputs per channel.

    GhostNet's cheap operation; equals ``conv2d(groups=channels, padding=k // 2)`` with
    ``channels * multiplier`` outputs (fan-in ``k * k`` as in ``nn.Conv2d``).
    """

    def __init__(self, channels: int, multiplier: int = 1, kernel_size: int = 3, *, bias=True):
        shape, names = (channels, multiplier), ("channels", "multiplier")
        super().__init__(kernel_size, shape, channels * multiplier, bias, 1, names=names)

    def forward(self, x: SparseTensor) -> SparseTensor:
        return submanifold_depthwise_conv2d(x, self.weight, self.bias)


class SparseConv2d(_SparseConvBase):
    """Stride-2 sparse convolution (kernel 2 or 3) onto the sites ``unique(floor(C / 2))``.

    Kernel 2 equals ``conv2d(kernel_size=2, stride=2)`` on the map zero-padded at the bottom
    and right to even size, kernel 3 ``conv2d(kernel_size=3, stride=2, padding=1)``, both at
    the active outputs.
    """

    def __init__(self, in_channels, out_channels, kernel_size=2, *, stride=2, bias=True):
        if kernel_size not in (2, 3):
            raise ParameterError(f"kernel_size must be 2 or 3, got {kernel_size!r}")
        if stride != 2:
            raise ParameterError(f"only stride 2 is supported, got {stride!r}")
        shape = (in_channels, out_channels)
        super().__init__(kernel_size, shape, out_channels, bias, in_channels, odd=False)

    def forward(self, x: SparseTensor) -> SparseTensor:
        return sparse_conv2d(x, self.weight, self.bias)


def dense_conv_weight(weight: torch.Tensor, *, depthwise: bool = False) -> torch.Tensor:
    """``nn.Conv2d`` weight ``(C_out, C_in, k, k)`` of a sparse ``(k*k, C_in, C_out)`` one;
    depthwise ``(k*k, C, m)`` -> ``(C * m, 1, k, k)`` for ``groups=C``."""
    k = math.isqrt(int(weight.shape[0]))
    if depthwise:
        return weight.reshape(k, k, -1).permute(2, 0, 1).unsqueeze(1)
    return weight.reshape(k, k, weight.shape[1], weight.shape[2]).permute(3, 2, 0, 1)


# -- normalisation, activations, pooling, S2D -----------------------------------------------------
class SparseBatchNorm(nn.BatchNorm1d):
    """``BatchNorm1d`` over the features of the active sites of the whole batch.

    With fewer than two sites in training mode (batch statistics undefined; torch raises)
    the running statistics normalise instead and are not updated; no sites: returned as is.
    """

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        f = x.feats
        if f.shape[0] == 0:
            return x
        if self.training and f.shape[0] < 2:
            m, v = self.running_mean, self.running_var
            return x.replace_feats(
                F.batch_norm(f, m, v, self.weight, self.bias, False, 0, self.eps)
            )
        return x.replace_feats(super().forward(f))


class SparseActivation(nn.Module):
    """An element-wise module (``nn.LeakyReLU(0.1)``, ``nn.ReLU()``, ...) on the features."""

    def __init__(self, fn: nn.Module):
        super().__init__()
        self.fn = fn

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace_feats(self.fn(x.feats))
