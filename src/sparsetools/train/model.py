"""Early-fusion U-Net for depth completion (Ma & Karaman 2018; UltraDepth).

The camera image, the sparse depth and (optionally) its validity mask are concatenated at the
input ("early fusion") and go through one encoder-decoder:

- encoder: a 3x3 stem, then five levels of residual blocks (two 3x3 conv + BN + LeakyReLU,
  1x1 projection shortcut when the width changes) with widths ``32-64-128-256-512`` scaled by
  ``width / 32``; levels 2-5 start with a 2x2 max pooling (so the deepest level is at 1/16);
- decoder: four residual up-projection blocks (Laina et al. 2016: x2 nearest upsampling, then
  conv-BN-act-conv-BN plus a conv-BN shortcut, summed, act; 3x3 kernels instead of Laina's
  5x5 to keep CPU training fast), each followed by concatenation of the encoder feature map of
  the same resolution and a 3x3 conv-BN-act fusing them;
- activations: LeakyReLU(0.1) everywhere (UltraDepth). With plain ReLU in the decoder a narrow
  model (``width`` 4-8) can end up with every last-layer feature at 0 over a region (the near
  road, say), where the prediction then sticks at the head's bias with no gradient to leave it;
- head: a 1x1 convolution to one channel, a softplus times 20 m, so depth is positive (needed
  by the SILog loss), nearly linear in the head's output above a few metres, and the head works
  on O(1) numbers; its bias starts at 10 m;
- optional final 3x3 adjustment layer (UltraDepth): one 3x3 convolution that adds a
  correction to the coarse depth D. It sees D and the network input and, when the input holds
  sparse depth S with validity mask M, also M and M * D: then ``D + a (S - M D)`` is a linear
  function of its inputs, so the layer can put the measured depth in place of the prediction
  at (and next to) the LiDAR pixels, which the encoder-decoder learns only slowly. It starts at
  zero (the plain model).

URL (``url``, with ``input_mode='rgbdu'``; :mod:`sparsetools.train.url`): the input is the
image, the learned densifier's coarse depth ``D_c`` and its log-variance ``U``, and the head is
read as URL's residual (``D_f = D_c + R``, ``R`` = 20 m times the head's linear output, which
starts at zero: the untrained model returns ``D_c`` exactly) or as the model's own depth ``P``
gated against ``D_c`` (``lambda(U) D_c + (1 - lambda(U)) P``, the usual softplus head for
``P``). ``forward`` then takes ``coarse`` and ``log_var`` themselves, so the output is built
from the exact ``D_c``, not from its scaled input channel.

Inputs of any size: the network pads to a multiple of 16 at the bottom and right, and crops
the prediction back.

LiDAR encoder (``lidar_encoder``, EffisDepth's parallel-encoder layout; docs/sfe.md): with
``'sfe'`` the sparse depth map goes through a Sparse Feature Extractor
(:class:`sparsetools.train.sfe.SparseFeatureExtractor`) whose outputs have the widths and
scales of the encoder levels it feeds (``lidar_scales``, default 1/2 .. 1/16); with
``'dense'`` through its dense twin of the same parameter count
(:class:`~sparsetools.train.sfe.DenseLidarEncoder`). EffisDepth fuses at its ResNet levels,
1/2 .. 1/32, never at full resolution; fused at scale 1 too (the layout before 0.4, which
checkpoints without ``lidar_scales`` keep), each LiDAR pixel has a direct path to its own
output pixel, and self-supervised training with the sparse loss learns to copy the input
there instead of the scene (measured: docs/sfe.md). The LiDAR features of a level are ADDED
to that encoder level's output, before it becomes the skip and before the max pooling into level
i + 1: no layer of the U-Net changes and the LiDAR reaches the deeper levels and, through the
skips, the decoder; the SFE's features are exactly zero away from the LiDAR sites, so there the
image features pass unchanged. The map is padded like the image (bottom/right, zeros = empty).
``'none'`` (default) is plain early fusion; EffisDepth's layout feeds the image alone to the
U-Net (``input_mode='rgb'``), which :class:`~sparsetools.train.config.TrainConfig` requires.

For self-supervised training (``output='disparity'``) the softplus head and the adjustment
layer are replaced by monodepth2's multi-scale output: a 3x3 convolution (reflection padding)
and a sigmoid on each of the four decoder stages (scales 1, 1/2, 1/4, 1/8), read as depth by
:func:`disparity_to_depth`. By default the heads get torch's initialisation, as in monodepth2
(sigmoid about 0.5: about 0.2 m for the range 0.1-100 m), which suits camera-only training
(the pose network's small initial translations give that depth a useful parallax).
``initial_depth`` starts them at a given depth instead (zero weights, matching bias):
self-supervised training with a sparse-LiDAR loss uses 10 m, because there the scale becomes
metric, and pixels the LiDAR does not reach (near road, sky, tall buildings) stayed at about
0.2 m, where every warp is far worse than no warp, the auto-mask removes them and nothing
moves them (measured on the synthetic street videos).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import ParameterError
from .url import GATE_ALPHA, GATE_BETA, URL_MODES, URL_VARIANTS, gated_fusion

__all__ = [
    "DEFAULT_LIDAR_SCALES",
    "INPUT_CHANNELS",
    "LIDAR_ENCODERS",
    "LIDAR_SCALES",
    "OUTPUTS",
    "SPARSE_CHANNEL",
    "DepthCompletionUNet",
    "build_lidar_encoder",
    "build_model",
    "check_lidar_scales",
    "disparity_to_depth",
    "model_inputs",
    "pad_to_stride",
]

#: Number of input channels of each input mode.
INPUT_CHANNELS = {"rgb": 3, "rgbd": 4, "rgbdm": 5, "d": 1, "rgbdc": 5, "rgbdu": 5}
#: Channel of the sparse depth in each mode's input (None: the mode has none).
SPARSE_CHANNEL = {"rgb": None, "rgbd": 3, "rgbdm": 3, "d": 0, "rgbdc": 3, "rgbdu": None}
#: Encoder widths at ``width = 32``.
BASE_WIDTHS = (32, 64, 128, 256, 512)
#: What the network predicts: metric depth, or multi-scale sigmoid disparity.
OUTPUTS = ("depth", "disparity")
#: LiDAR branches fused into the encoder: none (early fusion only), the SFE, its dense twin.
LIDAR_ENCODERS = ("none", "sfe", "dense")
#: Downsampling factor of the deepest level.
STRIDE = 16
#: Scales of the encoder levels (1 = full resolution), the levels a LiDAR branch may feed.
LIDAR_SCALES = (1, 2, 4, 8, 16)
#: Levels a LiDAR branch feeds by default: EffisDepth's, never full resolution.
DEFAULT_LIDAR_SCALES = (2, 4, 8, 16)

_RGB_MEAN = 0.45
_RGB_STD = 0.225
#: Sparse depth is fed as depth / this (metres), so typical inputs are O(1).
_DEPTH_SCALE = 20.0
#: The densifier's U (log of square metres, within +-12) is fed as U / this.
_LOG_VAR_SCALE = 4.0
_INIT_DEPTH = 10.0
_SLOPE = 0.1
#: Offset of the seed of a LiDAR branch's weights from the global seed (one per network).
LIDAR_SEED_OFFSETS = {"depth": 7919, "pose": 7927}


def build_lidar_encoder(
    kind: str,
    *,
    widths: tuple[int, ...],
    scales: tuple[int, ...],
    depth_channels: int = 1,
    network: str = "depth",
) -> nn.Module | None:
    """The LiDAR branch ``kind`` (None for ``'none'``) with outputs of ``widths`` at ``scales``.

    Parameters
    ----------
    kind : {'none', 'sfe', 'dense'}
        :class:`~sparsetools.train.sfe.SparseFeatureExtractor` or its dense twin
        :class:`~sparsetools.train.sfe.DenseLidarEncoder` (one SGB per scale).
    widths, scales : tuple of int
        Output channels and strides (increasing powers of two) of the levels it feeds.
    depth_channels : int
        Depth maps per input (2 for a pose network's frame pair).
    network : {'depth', 'pose'}
        Which network it belongs to: selects its seed.

    Notes
    -----
    The weights are drawn from their own stream, seeded with ``torch.initial_seed() +
    LIDAR_SEED_OFFSETS[network]``, and the global RNG is left as it was: with one seed, the
    image networks start from the same weights whatever the LiDAR encoder (the ablations of
    docs/sfe.md compare like with like), and the SFE and its dense twin from the same stream.
    """
    if kind not in LIDAR_ENCODERS:
        raise ParameterError(
            f"unknown LiDAR encoder {kind!r}; choose one of {', '.join(LIDAR_ENCODERS)}",
            param="lidar_encoder",
        )
    if kind == "none":
        return None
    from .sfe import DenseLidarEncoder, SparseFeatureExtractor

    cls = SparseFeatureExtractor if kind == "sfe" else DenseLidarEncoder
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(torch.initial_seed() + LIDAR_SEED_OFFSETS[network])
        return cls(widths=tuple(widths), scales=tuple(scales), depth_channels=depth_channels)


def check_lidar_scales(scales) -> tuple[int, ...]:
    """``scales`` as a tuple of int if they are increasing values of :data:`LIDAR_SCALES`.

    Raises
    ------
    ParameterError
        Otherwise (naming ``lidar_scales``).
    """
    ok = isinstance(scales, (list, tuple)) and all(
        isinstance(s, int) and not isinstance(s, bool) for s in scales
    )
    if (
        not ok
        or not scales
        or list(scales) != sorted(set(scales))
        or set(scales) - set(LIDAR_SCALES)
    ):
        raise ParameterError(
            f"lidar_scales must be increasing values of {', '.join(map(str, LIDAR_SCALES))}, "
            f"got {scales!r}",
            param="lidar_scales",
        )
    return tuple(scales)


def pad_to_stride(x: torch.Tensor, stride: int = 16) -> torch.Tensor:
    """Zero-pad ``(B, C, H, W)`` at the bottom and right to multiples of ``stride``."""
    pad_h, pad_w = (-x.shape[-2]) % stride, (-x.shape[-1]) % stride
    return F.pad(x, (0, pad_w, 0, pad_h)) if pad_h or pad_w else x


def model_inputs(
    rgb: torch.Tensor,
    sparse: torch.Tensor | None,
    mode: str,
    confidence: torch.Tensor | None = None,
    *,
    coarse: torch.Tensor | None = None,
    log_var: torch.Tensor | None = None,
) -> torch.Tensor:
    """Stack the network input of ``mode``.

    Parameters
    ----------
    rgb : (B, 3, H, W) float, 0..1; unused for ``mode='d'``
    sparse : (B, 1, H, W) float, metres, 0 = no measurement; unused for ``mode='rgb'`` and
        ``'rgbdu'``
    mode : {'rgb', 'rgbd', 'rgbdm', 'd', 'rgbdc', 'rgbdu'}
    confidence : (B, 1, H, W) float, 0..1
        Confidence of the sparse depth (``dataset build --confidence``); ``mode='rgbdc'`` only.
    coarse : (B, 1, H, W) float, metres
        The learned densifier's ``D_c``; ``mode='rgbdu'`` only.
    log_var : (B, 1, H, W) float, log of square metres
        Its ``U = log sigma^2``; ``mode='rgbdu'`` only.

    Returns
    -------
    (B, C, H, W) float with C = ``INPUT_CHANNELS[mode]``: normalised rgb, depth / 20 m, then
    the validity mask (0/1, ``rgbdm``) or the confidence (``rgbdc``); ``d``: depth / 20 m alone;
    ``rgbdu``: normalised rgb, ``D_c`` / 20 m, ``U`` / 4.
    """
    if mode not in INPUT_CHANNELS:
        raise ParameterError(f"unknown input mode {mode!r}; choose one of {sorted(INPUT_CHANNELS)}")
    if mode == "rgb":
        return (rgb - _RGB_MEAN) / _RGB_STD
    if mode in URL_MODES:
        if coarse is None or log_var is None:
            raise ParameterError(f"input mode {mode!r} needs the densifier's coarse and log_var")
        rgb_n = (rgb - _RGB_MEAN) / _RGB_STD
        return torch.cat([rgb_n, coarse / _DEPTH_SCALE, log_var / _LOG_VAR_SCALE], dim=1)
    if sparse is None:
        raise ParameterError(f"input mode {mode!r} needs sparse depth")
    if mode == "d":
        return sparse / _DEPTH_SCALE
    parts = [(rgb - _RGB_MEAN) / _RGB_STD, sparse / _DEPTH_SCALE]
    if mode == "rgbdm":
        parts.append((sparse > 0).to(rgb.dtype))
    if mode == "rgbdc":
        if confidence is None:
            raise ParameterError("input mode 'rgbdc' needs the confidence map")
        parts.append(confidence.to(rgb.dtype))
    return torch.cat(parts, dim=1)


class ResidualBlock(nn.Module):
    """Two 3x3 conv-BN with LeakyReLU and an identity (or 1x1 conv-BN) shortcut."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.shortcut = (
            nn.Identity()
            if c_in == c_out
            else nn.Sequential(nn.Conv2d(c_in, c_out, 1, bias=False), nn.BatchNorm2d(c_out))
        )
        self.act = nn.LeakyReLU(_SLOPE)

    def forward(self, x):
        y = self.act(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.act(y + self.shortcut(x))


class UpProjection(nn.Module):
    """Residual up-projection block (Laina et al.): x2 upsampling, two branches summed."""

    def __init__(self, c_in: int, c_out: int, kernel: int = 3):
        super().__init__()
        pad = kernel // 2
        self.conv1 = nn.Conv2d(c_in, c_out, kernel, padding=pad, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.conv_short = nn.Conv2d(c_in, c_out, kernel, padding=pad, bias=False)
        self.bn_short = nn.BatchNorm2d(c_out)

    def forward(self, x):
        # nearest upsampling: deterministic backward on every device, unlike bilinear on CUDA
        x = F.interpolate(x, scale_factor=2, mode="nearest")
        y = F.leaky_relu(self.bn1(self.conv1(x)), _SLOPE)
        y = self.bn2(self.conv2(y))
        return F.leaky_relu(y + self.bn_short(self.conv_short(x)), _SLOPE)


class DecoderStage(nn.Module):
    """Up-projection, concatenation of the skip feature map, 3x3 conv-BN-LeakyReLU fusion."""

    def __init__(self, c_in: int, c_skip: int, c_out: int):
        super().__init__()
        self.up = UpProjection(c_in, c_out)
        self.fuse = nn.Sequential(
            nn.Conv2d(c_out + c_skip, c_out, 3, padding=1, bias=False),
            nn.BatchNorm2d(c_out),
            nn.LeakyReLU(_SLOPE),
        )

    def forward(self, x, skip):
        return self.fuse(torch.cat([self.up(x), skip], dim=1))


class DepthCompletionUNet(nn.Module):
    """Early-fusion U-Net: (B, C, H, W) input (see :func:`model_inputs`) -> depth.

    Parameters
    ----------
    input_mode : {'rgb', 'rgbd', 'rgbdm', 'd', 'rgbdc'}
        3, 4, 5, 1 or 5 input channels (:func:`model_inputs`).
    width : int
        Width of the first level; the levels are ``width * (1, 2, 4, 8, 16)`` (32 gives the
        paper's 32-64-128-256-512).
    final_layer : bool
        Add the final 3x3 adjustment layer (``output='depth'`` only).
    output : {'depth', 'disparity'}
        ``depth``: one (B, 1, H, W) map in metres (supervised training). ``disparity``
        (self-supervised training): a 3x3 convolution and a sigmoid on each of the four
        decoder stages, i.e. a list of four (B, 1, ceil(H / 2^s), ceil(W / 2^s)) maps in
        (0, 1) for scales s = 0 (full resolution), 1, 2, 3 (monodepth2's outputs), read as
        depth by :func:`disparity_to_depth` with ``depth_range``.
    depth_range : (min, max), metres
        Depth of sigmoid 1 and 0 (``output='disparity'``; monodepth2: 0.1, 100).
    initial_depth : float, optional, metres
        ``output='disparity'``: start every scale at this depth (zero weights, matching bias)
        instead of torch's default initialisation (sigmoid about 0.5, i.e. about 0.2 m).
    lidar_encoder : {'none', 'sfe', 'dense'}
        LiDAR branch whose features are added to the encoder levels of ``lidar_scales``
        (module docstring); ``forward`` then needs ``lidar``.
    lidar_scales : tuple of int
        Encoder levels the LiDAR branch feeds, by scale (increasing values of 1, 2, 4, 8,
        16; default 2-16 as EffisDepth).
    url : {'residual', 'gated'}, optional
        URL's reading of the head (module docstring); required by, and only for,
        ``input_mode='rgbdu'``; ``forward`` then needs ``coarse`` and ``log_var``.
    gate_alpha, gate_beta : float
        The gate of ``url='gated'`` (:func:`sparsetools.train.url.uncertainty_gate`).
    """

    def __init__(
        self,
        input_mode: str = "rgbd",
        *,
        width: int = 32,
        final_layer: bool = False,
        output: str = "depth",
        depth_range: tuple[float, float] = (0.1, 100.0),
        initial_depth: float | None = None,
        lidar_encoder: str = "none",
        lidar_scales: tuple[int, ...] = DEFAULT_LIDAR_SCALES,
        url: str | None = None,
        gate_alpha: float = GATE_ALPHA,
        gate_beta: float = GATE_BETA,
    ):
        super().__init__()
        scales = check_lidar_scales(lidar_scales)
        _check_url(input_mode, url, output=output, final_layer=final_layer)
        if input_mode not in INPUT_CHANNELS:
            raise ParameterError(
                f"unknown input mode {input_mode!r}; choose one of {sorted(INPUT_CHANNELS)}",
                param="input_mode",
            )
        if int(width) < 1:
            raise ParameterError(f"width must be >= 1, got {width}", param="width")
        if output not in OUTPUTS:
            raise ParameterError(f"unknown output {output!r}; choose depth or disparity")
        if output == "disparity" and final_layer:
            raise ParameterError(
                "the final adjustment layer needs output='depth'", param="final_layer"
            )
        lo, hi = (float(v) for v in depth_range)
        if not (0 < lo < hi and math.isfinite(hi)):
            raise ParameterError(
                f"depth_range must satisfy 0 < min < max < inf, got {depth_range}",
                param="depth_range",
            )
        self.input_mode = input_mode
        self.width = int(width)
        self.final_layer = bool(final_layer)
        self.output = output
        self.depth_range = (lo, hi)
        self.initial_depth = None if initial_depth is None else float(initial_depth)
        self.lidar_encoder = lidar_encoder
        self.lidar_scales = scales
        self.url = url
        self.gate = (float(gate_alpha), float(gate_beta))
        c_in = INPUT_CHANNELS[input_mode]
        widths = [max(1, round(b * self.width / 32)) for b in BASE_WIDTHS]
        self.widths = tuple(widths)
        # encoder level -> index of its LiDAR features (levels not fed are absent)
        self._lidar_level = {LIDAR_SCALES.index(s): k for k, s in enumerate(scales)}
        self.lidar_branch = build_lidar_encoder(
            lidar_encoder,
            widths=tuple(widths[LIDAR_SCALES.index(s)] for s in scales),
            scales=scales,
        )

        self.stem = nn.Sequential(
            nn.Conv2d(c_in, widths[0], 3, padding=1, bias=False),
            nn.BatchNorm2d(widths[0]),
            nn.LeakyReLU(_SLOPE),
        )
        self.encoder = nn.ModuleList(
            [ResidualBlock(widths[0], widths[0])]
            + [ResidualBlock(widths[i - 1], widths[i]) for i in range(1, len(widths))]
        )
        self.decoder = nn.ModuleList(
            [
                DecoderStage(widths[i], widths[i - 1], widths[i - 1])
                for i in range(len(widths) - 1, 0, -1)
            ]
        )
        if output == "disparity":
            # one head per decoder stage, finest first (scale 0 = full resolution)
            self.disparity_heads = nn.ModuleList(
                [
                    nn.Conv2d(widths[i], 1, 3, padding=1, padding_mode="reflect")
                    for i in range(len(widths) - 1)
                ]
            )
            if self.initial_depth is not None:  # see the module docstring
                start = min(max(self.initial_depth, lo), hi)
                sigma = min(max((1 / start - 1 / hi) / (1 / lo - 1 / hi), 1e-4), 1 - 1e-4)
                for head in self.disparity_heads:
                    nn.init.zeros_(head.weight)
                    nn.init.constant_(head.bias, math.log(sigma / (1 - sigma)))
        else:
            self.head = nn.Conv2d(widths[0], 1, 1)
            nn.init.zeros_(self.head.weight)
            if url == "residual":  # R = 0: the untrained model returns D_c
                nn.init.zeros_(self.head.bias)
            else:
                nn.init.constant_(self.head.bias, _inverse_softplus(_INIT_DEPTH / _DEPTH_SCALE))
            if self.final_layer:
                extra = 2 if SPARSE_CHANNEL[input_mode] is not None else 0  # M and M * D
                self.adjust = nn.Conv2d(1 + c_in + extra, 1, 3, padding=1)
                # starts as the identity on the coarse depth
                nn.init.zeros_(self.adjust.weight)
                nn.init.zeros_(self.adjust.bias)
        # channels-last convolutions: 1.25x faster forward + backward on CPU (oneDNN) at
        # width 32; another summation order than NCHW, equal to rounding (docs/scale.md)
        self.to(memory_format=torch.channels_last)

    @property
    def in_channels(self) -> int:
        return INPUT_CHANNELS[self.input_mode]

    def forward(
        self,
        x: torch.Tensor,
        lidar: torch.Tensor | None = None,
        *,
        coarse: torch.Tensor | None = None,
        log_var: torch.Tensor | None = None,
    ) -> torch.Tensor | list[torch.Tensor]:
        """Depth (or the disparity list) of the network input ``x``.

        Parameters
        ----------
        x : (B, C, H, W) float
            :func:`model_inputs` of the input mode.
        lidar : (B, 1, H, W) float, metres, 0 = empty
            Sparse depth for the LiDAR branch (needed with ``lidar_encoder`` 'sfe' or
            'dense', ignored without one).
        coarse, log_var : (B, 1, H, W) float, metres and log of square metres
            The densifier's ``D_c`` and ``U`` that URL refines (needed with ``url``, ignored
            without it).
        """
        if x.ndim != 4 or x.shape[1] != self.in_channels:
            raise ParameterError(
                f"model for input mode {self.input_mode!r} expects (B, {self.in_channels}, H, W), "
                f"got {tuple(x.shape)}"
            )
        h, w = x.shape[-2:]
        if self.url is not None and not all(
            t is not None and t.shape == (x.shape[0], 1, h, w) for t in (coarse, log_var)
        ):
            raise ParameterError(
                f"a URL model needs coarse and log_var of shape {(x.shape[0], 1, h, w)}",
                param="coarse",
            )
        x = pad_to_stride(x, STRIDE).contiguous(memory_format=torch.channels_last)
        lidar_feats = None
        if self.lidar_branch is not None:
            if lidar is None or lidar.ndim != 4 or lidar.shape[1] != 1:
                got = None if lidar is None else tuple(lidar.shape)
                raise ParameterError(
                    f"a model with the {self.lidar_encoder} LiDAR encoder needs lidar=(B, 1, H, W) "
                    f"sparse depth, got {got}",
                    param="lidar",
                )
            if lidar.shape[0] != x.shape[0] or lidar.shape[-2:] != (h, w):
                raise ParameterError(
                    f"lidar {tuple(lidar.shape)} does not match the input {(x.shape[0], h, w)}",
                    param="lidar",
                )
            lidar_feats = self.lidar_branch(pad_to_stride(lidar.to(x.dtype), STRIDE))
        feats = []
        y = self.stem(x)
        for i, block in enumerate(self.encoder):
            if i:
                y = F.max_pool2d(y, 2)
            y = block(y)
            if lidar_feats is not None and i in self._lidar_level:
                y = y + lidar_feats[self._lidar_level[i]]  # before the skip and the pooling
            feats.append(y)
        y = feats[-1]
        stages = []
        for stage, skip in zip(self.decoder, reversed(feats[:-1]), strict=True):
            y = stage(y, skip)
            stages.append(y)
        if self.output == "disparity":
            out = []
            for s, (head, feat) in enumerate(
                zip(self.disparity_heads, reversed(stages), strict=True)
            ):
                hs, ws = -(-h // 2**s), -(-w // 2**s)
                out.append(torch.sigmoid(head(feat))[:, :, :hs, :ws])
            return out
        if self.url == "residual":  # D_f = D_c + R(I, U)
            return coarse + _DEPTH_SCALE * self.head(y)[:, :, :h, :w]
        depth = _DEPTH_SCALE * F.softplus(self.head(y))
        if self.url == "gated":
            alpha, beta = self.gate
            return gated_fusion(coarse, depth[:, :, :h, :w], log_var, alpha=alpha, beta=beta)
        if self.final_layer:
            coarse = depth / _DEPTH_SCALE
            parts = [coarse, x]
            k = SPARSE_CHANNEL[self.input_mode]  # the channel of sparse depth / 20 m
            if k is not None:
                mask = (x[:, k : k + 1] > 0).to(x.dtype)
                parts += [mask, mask * coarse]
            depth = depth + self.adjust(torch.cat(parts, dim=1)) * _DEPTH_SCALE
        return depth[:, :, :h, :w]

    def predict_depth(
        self, x: torch.Tensor, lidar: torch.Tensor | None = None, **url_maps
    ) -> torch.Tensor:
        """(B, 1, H, W) depth in metres of the network input ``x`` (see :func:`model_inputs`).

        For ``output='disparity'`` the full-resolution (scale 0) disparity as depth;
        ``url_maps``: ``coarse`` and ``log_var`` of a URL model (:meth:`forward`).
        """
        out = self(x, lidar, **url_maps)
        if self.output == "disparity":
            return disparity_to_depth(out[0], *self.depth_range)
        return out

    def run(
        self,
        rgb: torch.Tensor,
        sparse: torch.Tensor | None,
        *,
        confidence: torch.Tensor | None = None,
        coarse: torch.Tensor | None = None,
        log_var: torch.Tensor | None = None,
    ) -> torch.Tensor | list:
        """``forward`` on a batch: the input of the model's mode, the sparse map to its branch.

        Parameters
        ----------
        rgb : (B, 3, H, W) float, 0..1
        sparse : (B, 1, H, W) float, metres, 0 = empty; may be None for a camera-only model
        confidence : (B, 1, H, W) float, 0..1; needed by (only) input mode ``'rgbdc'``
        coarse, log_var : (B, 1, H, W) float, metres and log of square metres
            The densifier's ``D_c`` and ``U``; needed by (only) input mode ``'rgbdu'``.
        """
        maps = {} if self.url is None else {"coarse": coarse, "log_var": log_var}
        x = model_inputs(rgb, sparse, self.input_mode, confidence, **maps)
        return self(x, sparse, **maps)

    def depth_of(
        self,
        rgb: torch.Tensor,
        sparse: torch.Tensor | None,
        *,
        confidence: torch.Tensor | None = None,
        coarse: torch.Tensor | None = None,
        log_var: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """:meth:`predict_depth` on a batch (as :meth:`run`): (B, 1, H, W) metres."""
        maps = {} if self.url is None else {"coarse": coarse, "log_var": log_var}
        x = model_inputs(rgb, sparse, self.input_mode, confidence, **maps)
        return self.predict_depth(x, sparse, **maps)

    def config(self) -> dict:
        """The constructor arguments (saved in checkpoints)."""
        cfg = {"input_mode": self.input_mode, "width": self.width, "final_layer": self.final_layer}
        if self.output != "depth":  # supervised checkpoints keep their original three keys
            cfg["output"] = self.output
            cfg["depth_range"] = list(self.depth_range)
            cfg["initial_depth"] = self.initial_depth
        if self.lidar_encoder != "none":  # older checkpoints have no such key: 'none'
            cfg["lidar_encoder"] = self.lidar_encoder
            # older checkpoints have no such key: every level (LIDAR_SCALES)
            cfg["lidar_scales"] = list(self.lidar_scales)
        if self.url is not None:  # only URL models have these keys
            cfg.update(url=self.url, gate_alpha=self.gate[0], gate_beta=self.gate[1])
        return cfg


def disparity_to_depth(sigma: torch.Tensor, min_depth: float, max_depth: float) -> torch.Tensor:
    """Depth of a sigmoid output: ``1 / (1/max + (1/min - 1/max) sigma)`` (monodepth2).

    Parameters
    ----------
    sigma : tensor in [0, 1]
    min_depth, max_depth : float, metres
        Depth at sigma = 1 and sigma = 0.

    Returns
    -------
    tensor of the same shape, metres, in [min_depth, max_depth].
    """
    lo, hi = 1.0 / max_depth, 1.0 / min_depth
    return 1.0 / (lo + (hi - lo) * sigma)


def _check_url(input_mode: str, url: str | None, *, output: str, final_layer: bool) -> None:
    """A URL reading only with a URL input mode, and the reverse; depth output, no final layer."""
    if url is not None and url not in URL_VARIANTS:
        raise ParameterError(
            f"unknown URL variant {url!r}; choose one of {', '.join(URL_VARIANTS)}", param="url"
        )
    if (input_mode in URL_MODES) != (url is not None):
        raise ParameterError(
            f"input mode {input_mode!r} with url={url!r}: URL's variants go with input mode "
            f"{URL_MODES[0]!r} (the densifier's D_c and U), and it needs one",
            param="url",
        )
    if url is not None and (output != "depth" or final_layer):
        raise ParameterError("a URL model has a depth output and no final layer", param="url")


def _inverse_softplus(y: float) -> float:
    return y + math.log(-math.expm1(-y))


def build_model(config: dict) -> DepthCompletionUNet:
    """Model from a :meth:`DepthCompletionUNet.config` dictionary."""
    try:
        return DepthCompletionUNet(
            config["input_mode"],
            width=int(config["width"]),
            final_layer=bool(config["final_layer"]),
            output=str(config.get("output", "depth")),
            depth_range=tuple(config.get("depth_range", (0.1, 100.0))),
            initial_depth=config.get("initial_depth"),
            lidar_encoder=str(config.get("lidar_encoder", "none")),
            # before 0.4 every level was fed, and checkpoints did not say so
            lidar_scales=tuple(config.get("lidar_scales", LIDAR_SCALES)),
            url=config.get("url"),
            gate_alpha=float(config.get("gate_alpha", GATE_ALPHA)),
            gate_beta=float(config.get("gate_beta", GATE_BETA)),
        )
    except KeyError as exc:
        raise ParameterError(f"model configuration lacks {exc.args[0]!r}") from None
