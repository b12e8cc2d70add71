"""EffisDepth sparse tensors in plain torch: the sites, their cache, S2D and site-wise ops.

A :class:`SparseTensor` holds the active sites of a batch of feature maps at one scale:
``coords`` (N, 3) int64 ``(batch, y, x)`` and ``feats`` (N, C) (METHODS.md section 9).
:mod:`sparsetools.train.sparse` (D2S/S2D) stores ``[x, y, b]``; the columns are reversed
here so that the row-major site key ``(b * H + y) * W + x`` orders sites like the pixels of
the dense map. Sites are kept unique and sorted by that key (D2S makes them so,
:meth:`SparseTensor.from_coords` sorts, layers keep the order): results never depend on the
order in which sites were given.

What one set of coordinates derives -- the sorted keys, the kernel maps of the convolutions
(:class:`KernelMap`, built by :mod:`sparsetools.train.sparse_conv`) and the x2 coarser sites
-- lives in a :class:`CoordinateCache` shared by every tensor on the same sites.

Site-wise operations: :func:`sparse_add`, :func:`sparse_cat`, :func:`sparse_global_avg`
(per-sample mean for squeeze-excitation) and :func:`to_dense` (S2D at any finer scale).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..errors import ParameterError
from .sparse import dense_to_sparse

__all__ = [
    "CoordinateCache",
    "KernelMap",
    "SparseTensor",
    "positive_int",
    "site_keys",
    "sparse_add",
    "sparse_cat",
    "sparse_global_avg",
    "to_dense",
]


@dataclass(frozen=True)
class KernelMap:
    """(input row, output row) pairs per tap of one kernel on one set of coordinates.

    ``offsets[k] = (dy, dx)``: an output at ``o`` reads the input at ``stride * o + offsets[k]``
    (taps in row-major kernel order); ``in_index[k]``, ``out_index[k]``: (M_k,) int64, each
    row at most once per tap; ``identity_tap``: the submanifold centre, pairs ``(i, i)`` for
    every site (one matmul, no index lists).
    """

    kernel_size: int
    stride: int
    offsets: tuple[tuple[int, int], ...]
    in_index: tuple[torch.Tensor, ...]
    out_index: tuple[torch.Tensor, ...]
    n_out: int
    identity_tap: int | None = None

    @property
    def pair_counts(self) -> tuple[int, ...]:
        """Number of (input, output) pairs per tap."""
        return tuple(int(i.numel()) for i in self.in_index)


@dataclass(eq=False)
class CoordinateCache:
    """What one set of coordinates derives, shared by every tensor on them: the sorted site
    keys, submanifold and stride-2 kernel maps by kernel size, and the x2 coarser sites
    ``unique(floor(C / 2))`` with their own cache."""

    keys: torch.Tensor | None = None
    submanifold: dict[int, KernelMap] = field(default_factory=dict)
    downsampled: tuple[torch.Tensor, CoordinateCache] | None = None
    strided: dict[int, KernelMap] = field(default_factory=dict)


def site_keys(coords: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    H, W = shape
    return (coords[:, 0] * H + coords[:, 1]) * W + coords[:, 2]


def _check_bounds(coords: torch.Tensor, batch_size: int, shape: tuple[int, int]) -> None:
    if coords.shape[0] == 0:
        return
    lo, hi = coords.min(dim=0).values.tolist(), coords.max(dim=0).values.tolist()
    if min(lo) < 0 or hi[0] >= batch_size or hi[1] >= shape[0] or hi[2] >= shape[1]:
        raise ParameterError(
            f"coords outside the batch: b in [{lo[0]}, {hi[0]}], y in [{lo[1]}, {hi[1]}], "
            f"x in [{lo[2]}, {hi[2]}] for batch_size={batch_size}, spatial_shape={shape}"
        )


@dataclass(frozen=True, eq=False)
class SparseTensor:
    """Active sites of a batch of 2-D feature maps at one scale (EffisDepth eq. 1).

    Attributes
    ----------
    coords : (N, 3) int64 tensor
        ``(batch, y, x)`` per site at this scale, unique, in row-major order.
    feats : (N, C) float tensor
        Features per site; layers compute in its dtype, on its device.
    batch_size : int
        B (samples may have no sites).
    spatial_shape : (H, W)
        Dense size at this scale (``ceil(H0 / stride)`` of the input size H0).
    stride : int
        Scale: 1 at the input resolution, 2, 4, ... after strided convolutions.
    cache : CoordinateCache
        Keys and kernel maps of these coordinates (not part of the value).
    """

    coords: torch.Tensor
    feats: torch.Tensor
    batch_size: int
    spatial_shape: tuple[int, int]
    stride: int = 1
    cache: CoordinateCache = field(default_factory=CoordinateCache, repr=False, compare=False)

    def __post_init__(self) -> None:
        shape = tuple(int(s) for s in self.spatial_shape)
        for name, value in (("spatial_shape", shape), ("batch_size", int(self.batch_size))):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "stride", int(self.stride))
        c, f = self.coords, self.feats
        if not isinstance(c, torch.Tensor) or c.dim() != 2 or c.shape[1] != 3:
            raise ParameterError("coords must be an (N, 3) int64 tensor (batch, y, x)")
        if c.dtype != torch.int64:
            raise ParameterError(f"coords must be int64, got {c.dtype}")
        if not isinstance(f, torch.Tensor) or f.dim() != 2 or f.shape[0] != c.shape[0]:
            raise ParameterError(f"feats must be an (N, C) tensor with N = {c.shape[0]}")
        if len(shape) != 2 or min(shape) < 1 or self.batch_size < 1 or self.stride < 1:
            raise ParameterError(
                "need batch_size >= 1, spatial_shape (H, W) >= 1 and stride >= 1, got "
                f"{self.batch_size}, {shape}, {self.stride}"
            )
        if self.cache.keys is None:  # new coordinates: check them once
            _check_bounds(c, self.batch_size, shape)
            keys = site_keys(c, shape)
            if keys.numel() > 1 and not bool((keys[1:] > keys[:-1]).all()):
                raise ParameterError(
                    "coords must be unique and in row-major (batch, y, x) order: use "
                    "SparseTensor.from_coords for sites in any order"
                )
            self.cache.keys = keys

    @classmethod
    def from_dense(
        cls, dense: torch.Tensor, *, mask: torch.Tensor | None = None, stride: int = 1
    ) -> SparseTensor:
        """D2S of a ``(B, C, H, W)`` map (EffisDepth eq. 2) at scale ``stride``.

        ``mask`` (B, H, W) bool marks the active sites; default: any channel non-zero (or
        NaN). Uses :func:`sparsetools.train.sparse.dense_to_sparse`, whose ``[x, y, b]``
        columns are reversed; its row-major output order is already the canonical order.
        """
        if not isinstance(dense, torch.Tensor) or dense.dim() != 4:
            raise ParameterError("dense must be a (B, C, H, W) tensor")
        xyb, feats = dense_to_sparse(dense, channels_last=False, mask=mask)
        B, _, H, W = dense.shape
        return cls(xyb.flip(1).contiguous(), feats, B, (H, W), stride)

    @classmethod
    def from_coords(
        cls,
        coords: torch.Tensor,
        feats: torch.Tensor,
        *,
        batch_size: int,
        spatial_shape: tuple[int, int],
        stride: int = 1,
    ) -> SparseTensor:
        """Sparse tensor from (N, 3) ``(batch, y, x)`` sites in any order (sorted here).

        Duplicate or out-of-range sites raise :class:`ParameterError`.
        """
        coords = torch.as_tensor(coords).to(torch.int64)
        if coords.dim() != 2 or coords.shape[1] != 3:
            raise ParameterError(f"coords must be (N, 3), got shape {tuple(coords.shape)}")
        if feats.dim() != 2 or feats.shape[0] != coords.shape[0]:
            raise ParameterError("feats must be (N, C) with one row per site of coords")
        _check_bounds(coords, int(batch_size), tuple(spatial_shape))
        order = torch.argsort(site_keys(coords, tuple(spatial_shape)), stable=True)
        return cls(coords[order], feats[order], batch_size, spatial_shape, stride)

    @property
    def num_sites(self) -> int:
        return int(self.coords.shape[0])

    @property
    def num_channels(self) -> int:
        return int(self.feats.shape[1])

    def replace_feats(self, feats: torch.Tensor) -> SparseTensor:
        """The same sites (and cache) with new ``(N, C')`` features."""
        return SparseTensor(
            self.coords, feats, self.batch_size, self.spatial_shape, self.stride, self.cache
        )

    def to_dense(self) -> torch.Tensor:
        """S2D at this scale (EffisDepth eq. 3): ``(B, C, H, W)``, zeros at inactive pixels."""
        return to_dense(self)


def positive_int(name: str, value: int) -> int:
    if int(value) != value or value < 1:
        raise ParameterError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


# -- site-wise operations and S2D --------------------------------------------------------------
def _same_sites(a: SparseTensor, b: SparseTensor) -> None:
    same = a.coords is b.coords or (
        (a.spatial_shape, a.batch_size, a.coords.shape)
        == (b.spatial_shape, b.batch_size, b.coords.shape)
        and torch.equal(a.coords, b.coords)
    )
    if not same:
        raise ParameterError("sparse tensors are on different sites")


def sparse_add(a: SparseTensor, b: SparseTensor) -> SparseTensor:
    """Feature sum of two tensors on the same sites (residual connections)."""
    _same_sites(a, b)
    return a.replace_feats(a.feats + b.feats)


def sparse_cat(parts: list[SparseTensor]) -> SparseTensor:
    """Channel concatenation of tensors on the same sites."""
    for p in parts[1:]:
        _same_sites(parts[0], p)
    return parts[0].replace_feats(torch.cat([p.feats for p in parts], dim=1))


def sparse_global_avg(x: SparseTensor) -> torch.Tensor:
    """(B, C) per-sample mean of the features over its active sites (0 without sites).

    A one-hot (B, N) matmul: deterministic on every device, unlike a scatter-add over the
    batch index.
    """
    b = x.coords[:, 0]
    onehot = b.unsqueeze(0) == torch.arange(x.batch_size, device=b.device).unsqueeze(1)
    onehot = onehot.to(x.feats.dtype)
    return (onehot @ x.feats) / onehot.sum(dim=1, keepdim=True).clamp_(min=1)


def to_dense(
    x: SparseTensor, *, stride: int | None = None, shape: tuple[int, int] | None = None
) -> torch.Tensor:
    """S2D: ``(B, C, H', W')`` zeros with each site's features at its pixel(s).

    Parameters
    ----------
    x : SparseTensor at stride s
    stride : int, optional
        Output scale: s (default) or a finer one dividing s, where each site fills its
        ``(s / stride)^2`` block (nearest upsampling).
    shape : (H', W'), optional
        Default ``x.spatial_shape * (s / stride)``; a larger one pads zeros at the bottom and
        right (e.g. for a U-Net padding to a multiple of 16), a smaller one crops.
    """
    s = x.stride if stride is None else positive_int("stride", stride)
    if x.stride % s:
        raise ParameterError(f"stride must divide the tensor's stride {x.stride}, got {s}")
    f = x.stride // s
    H, W = (int(v) for v in (shape or (x.spatial_shape[0] * f, x.spatial_shape[1] * f)))
    if H < 1 or W < 1:
        raise ParameterError(f"shape must be positive, got {shape}")
    B, C = x.batch_size, x.num_channels
    b, y, xx, feats = x.coords[:, 0], x.coords[:, 1], x.coords[:, 2], x.feats
    if f > 1:
        d = torch.arange(f, device=b.device)
        y = (y[:, None, None] * f + d[None, :, None]).expand(-1, f, f).reshape(-1)
        xx = (xx[:, None, None] * f + d[None, None, :]).expand(-1, f, f).reshape(-1)
        b, feats = b.repeat_interleave(f * f), feats.repeat_interleave(f * f, dim=0)
    keep = (y < H) & (xx < W)
    if not bool(keep.all()):
        b, y, xx, feats = b[keep], y[keep], xx[keep], feats[keep]
    # flat (B, C, H, W) offsets: writes straight into channels-first memory, no permute copy
    index = (b * (C * H * W) + y * W + xx)[:, None] + torch.arange(C, device=b.device) * (H * W)
    out = feats.new_zeros(B * C * H * W)
    out.index_put_((index.reshape(-1),), feats.reshape(-1))
    return out.view(B, C, H, W)
