"""Pose network: two frames -> the 6-DoF motion between them (monodepth2's output format).

Architecture (after SfMLearner's pose CNN, small enough for a CPU): the two normalised frames
concatenated (6 channels) go through seven stride-2 convolutions (kernels 7, 5, 3, 3, 3, 3, 3;
widths ``width * (1, 2, 4, 8, 16, 16, 16)``, ReLU), a 1x1 convolution to 6 channels, and the
mean over the remaining pixels. The 6 numbers times 0.01 are an axis-angle rotation (radians)
and a translation: the scaling keeps the initial motion near zero, as in monodepth2.

For the pair (I_a, I_b) (in time order) the output is the transform ``T_a_to_b`` mapping
points of camera a into camera b (:func:`~sparsetools.train.selfsup.geometry.pose_vector_to_matrix`).
:func:`source_transforms` feeds (I_t, I_t+1) for the next frame, and (I_t-1, I_t) for the
previous one, whose transform is inverted, so both pairs are seen in time order.
"""

from __future__ import annotations

import torch
from torch import nn

from ...errors import ParameterError
from .geometry import pose_vector_to_matrix

__all__ = ["POSE_SCALE", "PoseNet", "build_pose_net", "source_transforms"]

#: Factor on the network's raw output (monodepth2: 0.01).
POSE_SCALE = 0.01
_KERNELS = (7, 5, 3, 3, 3, 3, 3)
_WIDTHS = (1, 2, 4, 8, 16, 16, 16)
_RGB_MEAN = 0.45
_RGB_STD = 0.225


class PoseNet(nn.Module):
    """Two RGB frames -> (axis_angle (B, 3), translation (B, 3)).

    Parameters
    ----------
    width : int
        Width of the first convolution (16 gives SfMLearner's 16-32-64-128-256-256-256).
    """

    def __init__(self, *, width: int = 16):
        super().__init__()
        if int(width) < 1:
            raise ParameterError(f"pose width must be >= 1, got {width}", param="pose_width")
        self.width = int(width)
        layers, c_in = [], 6
        for k, m in zip(_KERNELS, _WIDTHS, strict=True):
            layers += [nn.Conv2d(c_in, self.width * m, k, stride=2, padding=k // 2), nn.ReLU()]
            c_in = self.width * m
        self.encoder = nn.Sequential(*layers)
        self.head = nn.Conv2d(c_in, 6, 1)

    def forward(
        self, frame_a: torch.Tensor, frame_b: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Motion from ``frame_a`` to ``frame_b``.

        Parameters
        ----------
        frame_a, frame_b : (B, 3, H, W) float, 0..1

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
        out = POSE_SCALE * self.head(self.encoder(x)).mean(dim=(2, 3))
        return out[:, :3], out[:, 3:]

    def transform(self, frame_a: torch.Tensor, frame_b: torch.Tensor) -> torch.Tensor:
        """(B, 4, 4) ``T_a_to_b``: points of camera a in camera b."""
        axis_angle, translation = self(frame_a, frame_b)
        return pose_vector_to_matrix(axis_angle, translation)

    def config(self) -> dict:
        """The constructor arguments (saved in checkpoints)."""
        return {"width": self.width}


def build_pose_net(config: dict) -> PoseNet:
    """Pose network from a :meth:`PoseNet.config` dictionary."""
    try:
        return PoseNet(width=int(config["width"]))
    except KeyError as exc:
        raise ParameterError(f"pose-network configuration lacks {exc.args[0]!r}") from None


def source_transforms(
    pose_net: PoseNet, previous: torch.Tensor, target: torch.Tensor, following: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Target-to-source transforms of a triplet.

    Returns
    -------
    T_t_to_prev, T_t_to_next : (B, 4, 4) float
        ``T_t_to_prev`` is the inverse of the network's ``(I_t-1, I_t)`` output.
    """
    axis_angle, translation = pose_net(previous, target)
    t_to_prev = pose_vector_to_matrix(axis_angle, translation, invert=True)
    axis_angle, translation = pose_net(target, following)
    return t_to_prev, pose_vector_to_matrix(axis_angle, translation)
