"""EffisDepth's Sparse Feature Extractor (SFE) and a dense LiDAR branch of the same widths.

EffisDepth (section 2.2-2.3) encodes the sparse LiDAR depth map with a stack of Slender Group
Blocks (SGB) that run on the valid pixels only (:mod:`sparsetools.train.sparse_conv`); the
output of each scale goes through S2D and is fused with the image encoder's feature map of the
same scale (METHODS.md section 9).

- :class:`RRLayer` (redundancy reduction, after GhostNet): a primary submanifold convolution
  makes ``ceil(out / ratio)`` "intrinsic" channels (then BN, activation), a cheap depthwise
  submanifold convolution makes ``ratio - 1`` more per intrinsic channel; concatenated and cut
  to ``out`` channels.
- :class:`SELayer`: squeeze-excitation with the squeeze a per-sample mean over active sites.
- :class:`SlenderGroupBlock`: main branch RR -> BN -> act -> SE, residual branch identity or
  1x1 submanifold conv + BN, summed, act; a strided block first downsamples with stride-2
  sparse convolutions (+ BN + act) to its own width, so its residual is the identity.
- :class:`SparseFeatureExtractor`: stem (3x3 submanifold conv + BN + act at scale 1), then per
  scale ``blocks_per_scale`` SGBs, the first strided when the scale changes. Input: a sparse
  depth map ``(B, 1, H, W)`` in metres, 0 (or NaN, inf, negative) = empty (``depth_channels=2``:
  two maps, e.g. two frames for a pose network); site features ``depth / depth_scale``
  (80 m: KITTI's cap, so features are in [0, 1]) and, with ``constant_channel``, a constant 1
  (lets the first layers tell how many neighbours are present). Output: one dense map
  ``(B, C_k, ceil(H / s_k), ceil(W / s_k))`` per scale, zero off the active sites.
- :class:`DenseLidarEncoder`: the same network with ``nn.Conv2d`` on the whole map (input
  channels ``depth / depth_scale`` and the validity mask; the SE squeezes over all pixels):
  the dense LiDAR branch baseline, with exactly the same parameter count.

Activations are LeakyReLU(0.1) as in the U-Net of :mod:`sparsetools.train.model` (a narrow
ReLU network can lose every feature of a region); SE uses ReLU and a sigmoid as in SENet.

Sizes (:func:`count_parameters`): the paper gives 1.4 M parameters for the SFE (22.7 M for
SFE-large, "4 times the feature maps") but not its widths; :func:`paper_sized` is a
reconstruction with :data:`PAPER_WIDTHS` that lands near 1.4 M. For the U-Net of
:mod:`sparsetools.train.model`, :meth:`SparseFeatureExtractor.for_unet` gives the encoder's
scales (1, 2, 4, 8, 16) and widths ``32-64-128-256-512 * width / 32``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import ParameterError
from .sparse_conv import (
    SparseActivation,
    SparseBatchNorm,
    SparseConv2d,
    SparseTensor,
    SubmanifoldConv2d,
    SubmanifoldDepthwiseConv2d,
    sparse_add,
    sparse_cat,
    sparse_global_avg,
)

__all__ = [
    "PAPER_SCALES",
    "PAPER_WIDTHS",
    "SMALL_WIDTHS",
    "UNET_SCALES",
    "DenseLidarEncoder",
    "EncoderLayout",
    "RRLayer",
    "SELayer",
    "SlenderGroupBlock",
    "SparseFeatureExtractor",
    "count_parameters",
    "paper_sized",
    "unet_encoder_widths",
]

#: Scales of the SFE in EffisDepth (ResNet encoder levels 1/2 .. 1/32 and full resolution).
PAPER_SCALES = (1, 2, 4, 8, 16, 32)
#: Reconstructed widths of the paper-sized SFE (the paper does not list them).
PAPER_WIDTHS = (16, 32, 64, 128, 192, 368)
#: Narrow widths for CPU benchmarks and tests (same scales as the paper).
SMALL_WIDTHS = (8, 8, 16, 32, 48, 64)
#: Scales of the encoder levels of :class:`sparsetools.train.model.DepthCompletionUNet`.
UNET_SCALES = (1, 2, 4, 8, 16)
_UNET_BASE_WIDTHS = (32, 64, 128, 256, 512)


def unet_encoder_widths(width: int = 32) -> tuple[int, ...]:
    """Widths of the U-Net's encoder levels for its ``width`` (same rounding as the model)."""
    if int(width) != width or width < 1:
        raise ParameterError(f"width must be a positive integer, got {width!r}")
    return tuple(max(1, round(b * int(width) / 32)) for b in _UNET_BASE_WIDTHS)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters (BatchNorm running statistics are buffers, not counted)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


@dataclass(frozen=True)
class EncoderLayout:
    """Architecture of a LiDAR encoder (shared by the sparse and the dense one).

    Attributes
    ----------
    widths : tuple of int
        Output channels per scale.
    scales : tuple of int
        Strides of the outputs: increasing powers of two.
    blocks_per_scale : tuple of int
        SGBs per scale (>= 1 each).
    ratio : int
        RR layer: the primary conv makes ``ceil(width / ratio)`` channels (GhostNet's s).
    se_reduction : int
        SE hidden width ``max(1, width // se_reduction)``.
    down_kernel : int
        Kernel of the stride-2 convolutions: 2 or 3 (see :mod:`.sparse_conv`).
    depth_scale : float, metres
        Input feature = depth / depth_scale.
    constant_channel : bool
        Add a constant 1 feature (the validity mask in the dense encoder).
    depth_channels : int
        Depth maps per input (1; 2 for a pose network that sees two frames' LiDAR: a site is
        active where any map has depth, features 0 for the maps without).
    negative_slope : float
        LeakyReLU slope.
    """

    widths: tuple[int, ...]
    scales: tuple[int, ...] = PAPER_SCALES
    blocks_per_scale: tuple[int, ...] | int = 1
    ratio: int = 2
    se_reduction: int = 4
    down_kernel: int = 2
    depth_scale: float = 80.0
    constant_channel: bool = True
    negative_slope: float = 0.1
    depth_channels: int = 1

    def __post_init__(self) -> None:
        widths = tuple(int(w) for w in self.widths)
        scales = tuple(int(s) for s in self.scales)
        blocks = self.blocks_per_scale
        blocks = (int(blocks),) * len(scales) if isinstance(blocks, int) else tuple(blocks)
        if not scales or len(widths) != len(scales) or len(blocks) != len(scales):
            raise ParameterError(
                f"widths ({len(widths)}), scales ({len(scales)}) and blocks_per_scale "
                f"({len(blocks)}) must have one entry per scale"
            )
        if min(widths) < 1 or min(blocks) < 1:
            raise ParameterError("widths and blocks_per_scale must be >= 1")
        prev = 1
        for s in scales:
            if s < prev or s & (s - 1) or (s == prev and s != scales[0]):
                raise ParameterError(f"scales must be increasing powers of two, got {scales}")
            prev = s
        if self.ratio < 1 or self.se_reduction < 1 or self.depth_channels < 1:
            raise ParameterError("ratio, se_reduction and depth_channels must be >= 1")
        if self.down_kernel not in (2, 3):
            raise ParameterError(f"down_kernel must be 2 or 3, got {self.down_kernel!r}")
        if not (self.depth_scale > 0 and math.isfinite(self.depth_scale)):
            raise ParameterError(f"depth_scale must be a positive number, got {self.depth_scale}")
        object.__setattr__(self, "widths", widths)
        object.__setattr__(self, "scales", scales)
        object.__setattr__(self, "blocks_per_scale", blocks)

    @property
    def in_channels(self) -> int:
        return self.depth_channels + (1 if self.constant_channel else 0)

    def block_plan(self) -> list[tuple[int, int, int, int]]:
        """``(scale index, c_in, c_out, stride)`` of every SGB in order (after the stem)."""
        plan, c, prev = [], self.widths[0], 1
        for i, (s, w, n) in enumerate(
            zip(self.scales, self.widths, self.blocks_per_scale, strict=True)
        ):
            for j in range(n):
                plan.append((i, c, w, s // prev if j == 0 else 1))
                c = w
            prev = s
        return plan


def _clean_depth(depth: torch.Tensor, channels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Checked ``(B, channels, H, W)`` depth with 0 where invalid, and the validity per map."""
    if not isinstance(depth, torch.Tensor) or depth.dim() != 4 or depth.shape[1] != channels:
        shape = tuple(depth.shape) if isinstance(depth, torch.Tensor) else type(depth).__name__
        raise ParameterError(f"depth must be a (B, {channels}, H, W) tensor in metres, got {shape}")
    if not depth.dtype.is_floating_point:
        raise ParameterError(f"depth must be floating point (metres), got {depth.dtype}")
    valid = torch.isfinite(depth) & (depth > 0)  # NaN, inf, 0 and negatives are empty
    return torch.where(valid, depth, torch.zeros_like(depth)), valid


# -- sparse blocks ---------------------------------------------------------------------------
def _sparse_act(slope: float) -> SparseActivation:
    return SparseActivation(nn.LeakyReLU(slope))


class RRLayer(nn.Module):
    """Redundancy-reduction layer (GhostNet module) on sparse tensors.

    Parameters
    ----------
    in_channels, out_channels : int
    ratio : int
        ``ceil(out / ratio)`` intrinsic channels from the primary ``kernel_size`` submanifold
        conv (+ BN + act), ``ratio - 1`` cheap depthwise maps of each, cut to ``out``.
    kernel_size, cheap_kernel_size : int (odd)
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        *,
        ratio: int = 2,
        kernel_size: int = 3,
        cheap_kernel_size: int = 3,
        negative_slope: float = 0.1,
    ):
        super().__init__()
        if int(ratio) != ratio or ratio < 1:
            raise ParameterError(f"ratio must be a positive integer, got {ratio!r}")
        self.out_channels = int(out_channels)
        intrinsic = math.ceil(self.out_channels / ratio)
        self.primary = nn.Sequential(
            SubmanifoldConv2d(in_channels, intrinsic, kernel_size, bias=False),
            SparseBatchNorm(intrinsic),
            _sparse_act(negative_slope),
        )
        self.cheap = (
            SubmanifoldDepthwiseConv2d(intrinsic, ratio - 1, cheap_kernel_size, bias=False)
            if ratio > 1 and intrinsic < self.out_channels
            else None
        )

    def forward(self, x: SparseTensor) -> SparseTensor:
        y = self.primary(x)
        if self.cheap is not None:
            y = sparse_cat([y, self.cheap(y)])
        return y.replace_feats(y.feats[:, : self.out_channels])


class SELayer(nn.Module):
    """Squeeze-excitation: per-sample mean over active sites -> FC -> ReLU -> FC -> sigmoid."""

    def __init__(self, channels: int, *, reduction: int = 4):
        super().__init__()
        hidden = max(1, int(channels) // int(reduction))
        self.fc1 = nn.Linear(channels, hidden)
        self.fc2 = nn.Linear(hidden, channels)

    def gate(self, squeezed: torch.Tensor) -> torch.Tensor:
        """(B, C) squeezed features -> (B, C) gates in (0, 1)."""
        return torch.sigmoid(self.fc2(F.relu(self.fc1(squeezed))))

    def forward(self, x: SparseTensor) -> SparseTensor:
        g = self.gate(sparse_global_avg(x))
        return x.replace_feats(x.feats * g.index_select(0, x.coords[:, 0]))


class SlenderGroupBlock(nn.Module):
    """SGB: ``act(SE(act(BN(RR(x)))) + shortcut(x))``, optionally downsampling first.

    Parameters
    ----------
    in_channels, out_channels : int
    stride : int
        1, or a power of two: ``log2(stride)`` x2 downsamplings (stride-2 sparse conv + BN +
        act, the first to ``out_channels``) before the block.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        *,
        stride: int = 1,
        ratio: int = 2,
        se_reduction: int = 4,
        down_kernel: int = 2,
        negative_slope: float = 0.1,
    ):
        super().__init__()
        if int(stride) != stride or stride < 1 or stride & (stride - 1):
            raise ParameterError(f"stride must be a power of two, got {stride!r}")
        c = int(in_channels)
        down = []
        while stride > 1:
            down += [
                SparseConv2d(c, out_channels, down_kernel, bias=False),
                SparseBatchNorm(out_channels),
                _sparse_act(negative_slope),
            ]
            c, stride = out_channels, stride // 2
        self.down = nn.Sequential(*down) if down else None
        self.main = nn.Sequential(
            RRLayer(c, out_channels, ratio=ratio, negative_slope=negative_slope),
            SparseBatchNorm(out_channels),
            _sparse_act(negative_slope),
            SELayer(out_channels, reduction=se_reduction),
        )
        self.shortcut = (
            None
            if c == out_channels
            else nn.Sequential(
                SubmanifoldConv2d(c, out_channels, 1, bias=False), SparseBatchNorm(out_channels)
            )
        )
        self.act = _sparse_act(negative_slope)

    def forward(self, x: SparseTensor) -> SparseTensor:
        if self.down is not None:
            x = self.down(x)
        res = x if self.shortcut is None else self.shortcut(x)
        return self.act(sparse_add(self.main(x), res))


class _LidarEncoder(nn.Module):
    """What both encoders share: the layout, the constructors, the output contract."""

    def __init__(
        self,
        *,
        widths: tuple[int, ...] = PAPER_WIDTHS,
        scales: tuple[int, ...] = PAPER_SCALES,
        blocks_per_scale: tuple[int, ...] | int = 1,
        ratio: int = 2,
        se_reduction: int = 4,
        down_kernel: int = 2,
        depth_scale: float = 80.0,
        constant_channel: bool = True,
        negative_slope: float = 0.1,
        depth_channels: int = 1,
    ):
        super().__init__()
        self.layout = EncoderLayout(
            tuple(widths),
            tuple(scales),
            blocks_per_scale,
            ratio,
            se_reduction,
            down_kernel,
            depth_scale,
            constant_channel,
            negative_slope,
            depth_channels,
        )

    @classmethod
    def for_unet(cls, width: int = 32, **options):
        """Encoder whose outputs match the U-Net's encoder levels (scales 1-16, its widths)."""
        return cls(widths=unet_encoder_widths(width), scales=UNET_SCALES, **options)

    @property
    def scales(self) -> tuple[int, ...]:
        return self.layout.scales

    @property
    def out_channels(self) -> tuple[int, ...]:
        return self.layout.widths

    def output_shapes(self, height: int, width: int) -> list[tuple[int, int]]:
        """``(ceil(H / s), ceil(W / s))`` per scale."""
        return [(-(-height // s), -(-width // s)) for s in self.scales]


class SparseFeatureExtractor(_LidarEncoder):
    """EffisDepth SFE: SGBs on the valid pixels of a sparse depth map, S2D per scale.

    Keyword arguments are the fields of :class:`EncoderLayout` (default: the reconstructed
    paper-sized SFE). ``forward(depth)`` takes ``(B, depth_channels, H, W)`` metres (0,
    negative, NaN or inf = empty) and returns the list ``[(B, C_k, ceil(H / s_k),
    ceil(W / s_k))]`` over the scales, in ``depth``'s dtype and device.

    Examples
    --------
    >>> sfe = SparseFeatureExtractor.for_unet(8)          # the U-Net's levels at --width 8
    >>> [tuple(f.shape) for f in sfe(torch.zeros(2, 1, 64, 96))][-1]
    (2, 128, 4, 6)

    """

    def __init__(self, **options):
        super().__init__(**options)
        lay = self.layout
        act = lay.negative_slope
        self.stem = nn.Sequential(
            SubmanifoldConv2d(lay.in_channels, lay.widths[0], 3, bias=False),
            SparseBatchNorm(lay.widths[0]),
            _sparse_act(act),
        )
        self._stage_of_block = []
        blocks = []
        for stage, c_in, c_out, stride in lay.block_plan():
            blocks.append(
                SlenderGroupBlock(
                    c_in,
                    c_out,
                    stride=stride,
                    ratio=lay.ratio,
                    se_reduction=lay.se_reduction,
                    down_kernel=lay.down_kernel,
                    negative_slope=act,
                )
            )
            self._stage_of_block.append(stage)
        self.blocks = nn.ModuleList(blocks)

    def sparse_input(self, depth: torch.Tensor) -> SparseTensor:
        """D2S of the depth map(s): sites where any map has depth, features
        ``depth / depth_scale`` per map (0 for a map without depth there) [, 1]."""
        lay = self.layout
        depth, valid = _clean_depth(depth, lay.depth_channels)
        x = SparseTensor.from_dense(depth, mask=valid.any(dim=1))
        feats = x.feats / lay.depth_scale
        if lay.constant_channel:
            feats = torch.cat([feats, torch.ones_like(feats[:, :1])], dim=1)
        return x.replace_feats(feats)

    def forward_sparse(self, depth: torch.Tensor) -> list[SparseTensor]:
        """The last block's output of every scale, as sparse tensors."""
        return self.encode(self.sparse_input(depth))

    def encode(self, x: SparseTensor) -> list[SparseTensor]:
        """Stem and blocks on input features already in sparse form (stride 1)."""
        if x.stride != 1 or x.num_channels != self.layout.in_channels:
            raise ParameterError(
                f"encode expects a stride-1 sparse tensor with {self.layout.in_channels} "
                f"channels, got stride {x.stride} and {x.num_channels} channels"
            )
        x = self.stem(x)
        outs: list[SparseTensor] = []
        for i, (stage, block) in enumerate(zip(self._stage_of_block, self.blocks, strict=True)):
            x = block(x)
            last = i + 1 == len(self.blocks) or self._stage_of_block[i + 1] != stage
            if last:
                outs.append(x)
        return outs

    def forward(self, depth: torch.Tensor) -> list[torch.Tensor]:
        return [s.to_dense() for s in self.forward_sparse(depth)]


# -- dense twin ----------------------------------------------------------------------------------
class _DenseRR(nn.Module):
    def __init__(self, c_in: int, c_out: int, ratio: int, slope: float):
        super().__init__()
        self.out_channels = c_out
        intrinsic = math.ceil(c_out / ratio)
        self.primary = nn.Sequential(
            nn.Conv2d(c_in, intrinsic, 3, padding=1, bias=False),
            nn.BatchNorm2d(intrinsic),
            nn.LeakyReLU(slope),
        )
        self.cheap = (
            nn.Conv2d(
                intrinsic, intrinsic * (ratio - 1), 3, padding=1, groups=intrinsic, bias=False
            )
            if ratio > 1 and intrinsic < c_out
            else None
        )

    def forward(self, x):
        y = self.primary(x)
        if self.cheap is not None:
            y = torch.cat([y, self.cheap(y)], dim=1)
        return y[:, : self.out_channels]


class _DenseSE(SELayer):
    def forward(self, x):
        return x * self.gate(x.mean(dim=(2, 3)))[:, :, None, None]


class _EvenPad(nn.Module):
    """Zero-pad bottom/right to even size, so a k=2 s=2 conv gives ceil(H / 2) rows."""

    def forward(self, x):
        return F.pad(x, (0, x.shape[-1] % 2, 0, x.shape[-2] % 2))


class _DenseSGB(nn.Module):
    def __init__(self, c_in, c_out, *, stride, ratio, se_reduction, down_kernel, slope):
        super().__init__()
        c, down = c_in, []
        while stride > 1:
            if down_kernel == 2:
                down += [_EvenPad(), nn.Conv2d(c, c_out, 2, stride=2, bias=False)]
            else:
                down += [nn.Conv2d(c, c_out, 3, stride=2, padding=1, bias=False)]
            down += [nn.BatchNorm2d(c_out), nn.LeakyReLU(slope)]
            c, stride = c_out, stride // 2
        self.down = nn.Sequential(*down) if down else None
        self.main = nn.Sequential(
            _DenseRR(c, c_out, ratio, slope),
            nn.BatchNorm2d(c_out),
            nn.LeakyReLU(slope),
            _DenseSE(c_out, reduction=se_reduction),
        )
        self.shortcut = (
            None
            if c == c_out
            else nn.Sequential(nn.Conv2d(c, c_out, 1, bias=False), nn.BatchNorm2d(c_out))
        )
        self.act = nn.LeakyReLU(slope)

    def forward(self, x):
        if self.down is not None:
            x = self.down(x)
        res = x if self.shortcut is None else self.shortcut(x)
        return self.act(self.main(x) + res)


class DenseLidarEncoder(_LidarEncoder):
    """The SFE's architecture with ``nn.Conv2d`` over the whole map (dense LiDAR branch).

    Same keyword arguments, input and output shapes and parameter count as
    :class:`SparseFeatureExtractor`; inputs are ``depth / depth_scale`` (0 where empty) and,
    with ``constant_channel``, the validity mask.
    """

    def __init__(self, **options):
        super().__init__(**options)
        lay = self.layout
        act = lay.negative_slope
        self.stem = nn.Sequential(
            nn.Conv2d(lay.in_channels, lay.widths[0], 3, padding=1, bias=False),
            nn.BatchNorm2d(lay.widths[0]),
            nn.LeakyReLU(act),
        )
        plan = lay.block_plan()
        self._stage_of_block = [p[0] for p in plan]
        self.blocks = nn.ModuleList(
            _DenseSGB(
                c_in,
                c_out,
                stride=stride,
                ratio=lay.ratio,
                se_reduction=lay.se_reduction,
                down_kernel=lay.down_kernel,
                slope=act,
            )
            for _, c_in, c_out, stride in plan
        )

    def dense_input(self, depth: torch.Tensor) -> torch.Tensor:
        """``(B, depth_channels [+ 1], H, W)``: depth / depth_scale (0 where empty) [, any valid]."""
        depth, valid = _clean_depth(depth, self.layout.depth_channels)
        x = depth / self.layout.depth_scale
        if self.layout.constant_channel:
            x = torch.cat([x, valid.any(dim=1, keepdim=True).to(depth.dtype)], dim=1)
        return x

    def forward(self, depth: torch.Tensor) -> list[torch.Tensor]:
        x = self.stem(self.dense_input(depth))
        outs = []
        for i, (stage, block) in enumerate(zip(self._stage_of_block, self.blocks, strict=True)):
            x = block(x)
            if i + 1 == len(self.blocks) or self._stage_of_block[i + 1] != stage:
                outs.append(x)
        return outs


def paper_sized(*, large: bool = False, **options) -> SparseFeatureExtractor:
    """The reconstructed EffisDepth SFE (:data:`PAPER_WIDTHS`, scales 1-32, one SGB each).

    ``large=True`` multiplies the widths by 4 (the paper's SFE-large has "4 times" the
    feature maps, 22.7 M parameters). The exact counts are in docs/sfe.md.
    """
    widths = tuple(4 * w for w in PAPER_WIDTHS) if large else PAPER_WIDTHS
    return SparseFeatureExtractor(widths=widths, scales=PAPER_SCALES, **options)
