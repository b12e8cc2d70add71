"""Pose network: two frames -> the 6-DoF motion between them (monodepth2's output format).

Architecture (after SfMLearner's pose CNN, small enough for a CPU): the two normalised frames
concatenated (6 channels) go through seven stride-2 convolutions (kernels 7, 5, 3, 3, 3, 3, 3;
widths ``width * (1, 2, 4, 8, 16, 16, 16)``, ReLU), a 1x1 convolution to 6 channels, and the
mean over the remaining pixels. The first 3 numbers times 0.01 are an axis-angle rotation
(radians), the last 3 times ``translation_scale`` a translation: the scaling keeps the initial
motion small, as in monodepth2.

Translation scale (METHODS.md section 8). monodepth2's 0.01 fits its depth range: a
camera-only depth network starts with every sigmoid near 0.5, i.e. a depth of about 0.2 m for
the range 0.1-100 m (:func:`camera_only_initial_depth`), and a translation of ~0.01 then gives
an initial flow t / z of the order of the true one. A run with the sparse loss is metric and
starts every pixel at ``initial_depth`` = 10 m (:mod:`sparsetools.train.selfsup.task`): with
0.01 its initial t / z is 50x smaller, the warp hardly moves, the photometric term gives the
pose network no useful gradient and it never finds the motion (measured on the synthetic
street videos: ATE 0.97 m with 4 beams against 0.065 m with the scale below).
:func:`metric_translation_scale` gives metric runs the camera-only initial t / z:
``0.01 * initial_depth / camera_only_initial_depth`` (0.5 for 10 m and 0.1-100 m). The
rotation keeps 0.01: a rotation moves pixels by the same angle at every depth.

For the pair (I_a, I_b) (in time order) the output is the transform ``T_a_to_b`` mapping
points of camera a into camera b (:func:`~sparsetools.train.selfsup.geometry.pose_vector_to_matrix`).
:func:`source_transforms` feeds (I_t, I_t+1) for the next frame, and (I_t-1, I_t) for the
previous one, whose transform is inverted, so both pairs are seen in time order.

LiDAR branch (``lidar_encoder='sfe'`` or ``'dense'``; EffisDepth's "SFE in depth and pose"):
the two frames' sparse depth maps, stacked as a ``(B, 2, H, W)`` input (a site is active where
either frame has depth; :class:`~sparsetools.train.sfe.SparseFeatureExtractor` with
``depth_channels=2``), go through an SFE (or its dense twin) with outputs at the scales and
widths of the first five convolutions (1/2 .. 1/32, as EffisDepth's ResNet levels); each is
added to that convolution's output after its ReLU, the way the depth network fuses
(:mod:`sparsetools.train.model`). The two deepest levels (1/64, 1/128: a few pixels) get none.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ...errors import ParameterError
from ..model import LIDAR_ENCODERS, build_lidar_encoder
from .geometry import pose_vector_to_matrix

__all__ = [
    "POSE_SCALE",
    "PoseNet",
    "build_pose_net",
    "camera_only_initial_depth",
    "metric_translation_scale",
    "source_transforms",
]

#: Factor on the network's raw rotation output, and the default on its translation
#: (monodepth2: 0.01 on both).
POSE_SCALE = 0.01
_KERNELS = (7, 5, 3, 3, 3, 3, 3)
_WIDTHS = (1, 2, 4, 8, 16, 16, 16)
#: Encoder levels (from the first) that a LiDAR branch feeds: scales 1/2 .. 1/32.
LIDAR_LEVELS = 5
_RGB_MEAN = 0.45
_RGB_STD = 0.225


def camera_only_initial_depth(depth_range: tuple[float, float]) -> float:
    """Depth (m) of a sigmoid output of 0.5: where a camera-only depth network starts.

    ``1 / (1/max + (1/min - 1/max) / 2)``: 0.1998 m for monodepth2's range 0.1-100 m.
    """
    lo, hi = (float(v) for v in depth_range)
    return 1.0 / (1.0 / hi + 0.5 * (1.0 / lo - 1.0 / hi))


def metric_translation_scale(initial_depth: float, depth_range: tuple[float, float]) -> float:
    """Translation scale that gives a run starting at ``initial_depth`` (m) the initial flow
    t / z of a camera-only run: ``POSE_SCALE * initial_depth / camera_only_initial_depth``.

    Examples
    --------
    >>> round(metric_translation_scale(10.0, (0.1, 100.0)), 4)
    0.5005
    """
    if not (float(initial_depth) > 0 and math.isfinite(initial_depth)):
        raise ParameterError(f"initial depth must be a positive number, got {initial_depth}")
    return POSE_SCALE * float(initial_depth) / camera_only_initial_depth(depth_range)


class PoseNet(nn.Module):
    """Two RGB frames -> (axis_angle (B, 3), translation (B, 3)).

    Parameters
    ----------
    width : int
        Width of the first convolution (16 gives SfMLearner's 16-32-64-128-256-256-256).
    lidar_encoder : {'none', 'sfe', 'dense'}
        LiDAR branch of the frame pair (module docstring); ``forward`` then needs ``lidar``.
    translation_scale : float
        Factor on the raw translation output (module docstring; metric runs:
        :func:`metric_translation_scale`).
    """

    def __init__(
        self,
        *,
        width: int = 16,
        lidar_encoder: str = "none",
        translation_scale: float = POSE_SCALE,
    ):
        super().__init__()
        if int(width) < 1:
            raise ParameterError(f"pose width must be >= 1, got {width}", param="pose_width")
        if not (float(translation_scale) > 0 and math.isfinite(translation_scale)):
            raise ParameterError(
                f"pose translation scale must be a positive number, got {translation_scale}",
                param="pose_translation_scale",
            )
        if lidar_encoder not in LIDAR_ENCODERS:
            raise ParameterError(
                f"unknown pose LiDAR encoder {lidar_encoder!r}; choose one of "
                f"{', '.join(LIDAR_ENCODERS)}",
                param="pose_lidar_encoder",
            )
        self.width = int(width)
        self.lidar_encoder = lidar_encoder
        self.translation_scale = float(translation_scale)
        layers, c_in = [], 6
        for k, m in zip(_KERNELS, _WIDTHS, strict=True):
            layers += [nn.Conv2d(c_in, self.width * m, k, stride=2, padding=k // 2), nn.ReLU()]
            c_in = self.width * m
        self.encoder = nn.Sequential(*layers)
        self.head = nn.Conv2d(c_in, 6, 1)
        self.lidar_branch = build_lidar_encoder(
            lidar_encoder,
            widths=tuple(self.width * m for m in _WIDTHS[:LIDAR_LEVELS]),
            scales=tuple(2 ** (i + 1) for i in range(LIDAR_LEVELS)),
            depth_channels=2,
            network="pose",
        )

    @property
    def uses_lidar(self) -> bool:
        """Whether ``forward`` needs the frames' sparse depth."""
        return self.lidar_branch is not None

    def forward(
        self, frame_a: torch.Tensor, frame_b: torch.Tensor, lidar: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Motion from ``frame_a`` to ``frame_b``.

        Parameters
        ----------
        frame_a, frame_b : (B, 3, H, W) float, 0..1
        lidar : (B, 2, H, W) float, metres, 0 = empty
            Sparse depth of frame a and frame b (with a LiDAR branch; ignored without).

        Returns
        -------
        axis_angle : (B, 3) float, radians
        translation : (B, 3) float
        """
        if frame_a.shape != frame_b.shape or frame_a.ndim != 4 or frame_a.shape[1] != 3:
            raise ParameterError(
                f"pose network needs two (B, 3, H, W) frames of one shape, got "
                f"{tuple(frame_a.shape)} and {tuple(frame_b.shape)}"
            )
        x = (torch.cat([frame_a, frame_b], dim=1) - _RGB_MEAN) / _RGB_STD
        if self.lidar_branch is None:
            y = self.encoder(x)
        else:
            expected = (frame_a.shape[0], 2, *frame_a.shape[-2:])
            if lidar is None or tuple(lidar.shape) != expected:
                got = None if lidar is None else tuple(lidar.shape)
                raise ParameterError(
                    f"a pose network with the {self.lidar_encoder} LiDAR encoder needs "
                    f"lidar={expected} (both frames' sparse depth), got {got}",
                    param="lidar",
                )
            lidar_feats = self.lidar_branch(lidar.to(x.dtype))
            y = x
            for i in range(len(_KERNELS)):
                y = self.encoder[2 * i + 1](self.encoder[2 * i](y))  # conv, ReLU
                if i < LIDAR_LEVELS:
                    y = y + lidar_feats[i]
        out = self.head(y).mean(dim=(2, 3))
        return POSE_SCALE * out[:, :3], self.translation_scale * out[:, 3:]

    def transform(
        self, frame_a: torch.Tensor, frame_b: torch.Tensor, lidar: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, 4, 4) ``T_a_to_b``: points of camera a in camera b."""
        axis_angle, translation = self(frame_a, frame_b, lidar)
        return pose_vector_to_matrix(axis_angle, translation)

    def config(self) -> dict:
        """The constructor arguments (saved in checkpoints)."""
        cfg: dict = {"width": self.width}
        if self.lidar_encoder != "none":  # older checkpoints have no such key: 'none'
            cfg["lidar_encoder"] = self.lidar_encoder
        if self.translation_scale != POSE_SCALE:  # older checkpoints: 0.01
            cfg["translation_scale"] = self.translation_scale
        return cfg


def build_pose_net(config: dict) -> PoseNet:
    """Pose network from a :meth:`PoseNet.config` dictionary."""
    try:
        return PoseNet(
            width=int(config["width"]),
            lidar_encoder=str(config.get("lidar_encoder", "none")),
            translation_scale=float(config.get("translation_scale", POSE_SCALE)),
        )
    except KeyError as exc:
        raise ParameterError(f"pose-network configuration lacks {exc.args[0]!r}") from None


def source_transforms(
    pose_net: PoseNet,
    previous: torch.Tensor,
    target: torch.Tensor,
    following: torch.Tensor,
    *,
    lidar: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Target-to-source transforms of a triplet.

    Parameters
    ----------
    previous, target, following : (B, 3, H, W) float, 0..1
    lidar : (B, 3, H, W) float, metres, optional
        Sparse depth of [previous, target, following] (a pose network with a LiDAR branch).

    Returns
    -------
    T_t_to_prev, T_t_to_next : (B, 4, 4) float
        ``T_t_to_prev`` is the inverse of the network's ``(I_t-1, I_t)`` output.
    """
    pairs = (None, None) if lidar is None else (lidar[:, 0:2], lidar[:, 1:3])
    axis_angle, translation = pose_net(previous, target, pairs[0])
    t_to_prev = pose_vector_to_matrix(axis_angle, translation, invert=True)
    axis_angle, translation = pose_net(target, following, pairs[1])
    return t_to_prev, pose_vector_to_matrix(axis_angle, translation)
