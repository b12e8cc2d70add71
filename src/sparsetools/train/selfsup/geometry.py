"""Camera geometry for view synthesis (METHODS.md section 8), in torch, batched.

Conventions
-----------
- Camera frame: x right, y down, z forward; depth is camera z in metres.
- Pixels: 0-based, pixel centres at integer coordinates: pixel (row v, column u) is the point
  (u, v) of the image plane, ``K @ [X, Y, Z] / Z = [u, v, 1]``.
- ``T_t_to_s`` (4, 4) maps points in target-camera coordinates to source-camera coordinates:
  ``X_s = T_t_to_s @ X_t`` (homogeneous).
- Sampling: :func:`warp_frame` samples with :func:`torch.nn.functional.grid_sample`,
  ``align_corners=True`` so that the normalised coordinates -1 and +1 are the centres of the
  first and last pixels, i.e. ``x_n = 2 u / (W - 1) - 1``, consistent with pixel centres at
  integers; bilinear interpolation, border padding.
- Axis-angle: a 3-vector whose direction is the rotation axis and whose norm is the angle in
  radians (right-handed), :func:`axis_angle_to_matrix` is Rodrigues' formula.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from ...errors import ParameterError

__all__ = [
    "Warp",
    "axis_angle_to_matrix",
    "backproject",
    "invert_transform",
    "matrix_to_axis_angle",
    "pixel_grid",
    "pose_vector_to_matrix",
    "project",
    "warp_frame",
]

#: Points closer than this to the source camera plane (metres) are "behind" it.
MIN_SOURCE_DEPTH = 1e-3
#: A projection within this many machine epsilons times the image size (pixels) of the
#: border counts as inside: 1e-3 px for float32 at 1242 pixels, 2e-12 px in float64.
BORDER_ULPS = 8


def _skew(v: torch.Tensor) -> torch.Tensor:
    """(B, 3) -> (B, 3, 3) cross-product matrices [v]_x."""
    z = torch.zeros_like(v[:, 0])
    x, y, w = v[:, 0], v[:, 1], v[:, 2]
    return torch.stack([z, -w, y, w, z, -x, -y, x, z], dim=1).reshape(-1, 3, 3)


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of axis-angle vectors (Rodrigues).

    Parameters
    ----------
    axis_angle : (B, 3) float
        Rotation axis times angle (radians).

    Returns
    -------
    (B, 3, 3) float
        ``R = I + (sin t / t) K + ((1 - cos t) / t^2) K^2`` with ``K = [axis_angle]_x``;
        the coefficients use their Taylor series below 1e-4 rad, so the gradient is finite
        at 0.
    """
    if axis_angle.ndim != 2 or axis_angle.shape[1] != 3:
        raise ParameterError(f"axis_angle must be (B, 3), got {tuple(axis_angle.shape)}")
    theta2 = (axis_angle * axis_angle).sum(dim=1)
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / safe2)
    K = _skew(axis_angle)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device).expand_as(K)
    return eye + a[:, None, None] * K + b[:, None, None] * (K @ K)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors of rotation matrices (the inverse of :func:`axis_angle_to_matrix`).

    Parameters
    ----------
    R : (B, 3, 3) float
        Rotations (orthonormal, determinant +1).

    Returns
    -------
    (B, 3) float
        Angle in [0, pi]. Near pi, where sin t vanishes, the axis comes from the symmetric
        part of R, ``(R + R^T) / 2 - cos t I = (1 - cos t) a a^T``.
    """
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ParameterError(f"R must be (B, 3, 3), got {tuple(R.shape)}")
    v = torch.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    sin = 0.5 * torch.linalg.vector_norm(v, dim=1)
    cos = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1)
    theta = torch.atan2(sin, cos)
    # generic case: v = 2 sin(t) axis
    factor = torch.where(sin > 1e-6, theta / (2 * sin.clamp(min=1e-12)), 0.5 + theta * theta / 12)
    generic = v * factor[:, None]
    # near pi: the column of the symmetric part with the largest diagonal gives the axis
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    sym = 0.5 * (R + R.transpose(1, 2)) - cos[:, None, None] * eye
    col = torch.argmax(torch.diagonal(sym, dim1=1, dim2=2), dim=1)
    axis = sym[torch.arange(len(R), device=R.device), :, col]
    axis = axis / torch.linalg.vector_norm(axis, dim=1, keepdim=True).clamp(min=1e-12)
    sign = torch.where((axis * v).sum(dim=1) < 0, -1.0, 1.0).to(R.dtype)
    near_pi = axis * (sign * theta)[:, None]
    use_pi = (sin < 1e-3) & (cos < 0)
    return torch.where(use_pi[:, None], near_pi, generic)


def pose_vector_to_matrix(
    axis_angle: torch.Tensor, translation: torch.Tensor, *, invert: bool = False
) -> torch.Tensor:
    """4x4 transforms from the pose network's output format.

    Parameters
    ----------
    axis_angle : (B, 3) float, radians
    translation : (B, 3) float, metres (up to the unknown scale of camera-only training)
    invert : bool
        Return the inverse transform, ``[R^T, -R^T t]`` (used for the frame before the
        target, whose pair is fed to the pose network in time order).

    Returns
    -------
    (B, 4, 4) float
        ``[[R, t], [0, 1]]`` (rotate, then translate), or its inverse.
    """
    if translation.ndim != 2 or translation.shape[1] != 3 or len(translation) != len(axis_angle):
        raise ParameterError(
            f"translation must be (B, 3) like axis_angle, got {tuple(translation.shape)}"
        )
    R = axis_angle_to_matrix(axis_angle)
    t = translation[:, :, None]
    if invert:
        R = R.transpose(1, 2)
        t = -(R @ t)
    bottom = torch.zeros_like(R[:, :1, :])
    bottom = torch.cat([bottom, torch.ones_like(bottom[:, :, :1])], dim=2)
    return torch.cat([torch.cat([R, t], dim=2), bottom], dim=1)


def invert_transform(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid (B, 4, 4) transforms, ``[R^T, -R^T t]`` (exact, no matrix inverse)."""
    R = T[:, :3, :3].transpose(1, 2)
    t = -(R @ T[:, :3, 3:])
    out = torch.zeros_like(T)
    out[:, :3, :3] = R
    out[:, :3, 3:] = t
    out[:, 3, 3] = 1
    return out


def pixel_grid(height: int, width: int, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """(3, H * W) homogeneous pixel coordinates [u, v, 1], row-major (u = column, v = row)."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    return torch.stack([u.reshape(-1), v.reshape(-1), torch.ones_like(u).reshape(-1)], dim=0)


def backproject(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """3-D points of every pixel: ``X = depth * K^-1 [u, v, 1]^T``.

    Parameters
    ----------
    depth : (B, 1, H, W) float, metres (camera z)
    K : (B, 3, 3) float, pixels

    Returns
    -------
    (B, 3, H * W) float, metres, target-camera coordinates.
    """
    if depth.ndim != 4 or depth.shape[1] != 1:
        raise ParameterError(f"depth must be (B, 1, H, W), got {tuple(depth.shape)}")
    b, _, h, w = depth.shape
    rays = torch.linalg.inv(K) @ pixel_grid(h, w, dtype=depth.dtype, device=depth.device)
    return rays * depth.reshape(b, 1, h * w)


def project(
    points: torch.Tensor, K: torch.Tensor, T: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates of points after the transform ``T``.

    Parameters
    ----------
    points : (B, 3, N) float, metres
    K : (B, 3, 3) float
    T : (B, 4, 4) float
        Applied to the points before the projection (``X_s = T X``).

    Returns
    -------
    uv : (B, 2, N) float, pixels (u = column, v = row)
        Of points behind the camera (z <= 1e-3 m) the values are finite but meaningless.
    z : (B, 1, N) float, metres
        Depth of the points in the new camera.
    """
    X = T[:, :3, :3] @ points + T[:, :3, 3:]
    z = X[:, 2:3]
    uvw = K @ X
    uv = uvw[:, :2] / z.clamp(min=MIN_SOURCE_DEPTH)
    return uv, z


class Warp(NamedTuple):
    """Result of :func:`warp_frame`.

    image : (B, C, H, W) the source sampled at the target pixels' projections
    in_front : (B, 1, H, W) bool, the point projects in front of the source camera
    inside : (B, 1, H, W) bool, and inside the source image (within its pixel centres, to
        rounding: :data:`BORDER_ULPS`)
    """

    image: torch.Tensor
    in_front: torch.Tensor
    inside: torch.Tensor


def warp_frame(
    source: torch.Tensor, depth: torch.Tensor, T_t_to_s: torch.Tensor, K: torch.Tensor
) -> Warp:
    """Synthesise the target view from a source frame: ``p_s ~ K T D_t(p_t) K^-1 p_t``.

    Parameters
    ----------
    source : (B, C, H, W) float
        Source image I_s.
    depth : (B, 1, H, W) float, metres
        Depth of the target frame D_t.
    T_t_to_s : (B, 4, 4) float
        Target-to-source transform.
    K : (B, 3, 3) float
        Intrinsics of both frames.

    Returns
    -------
    Warp
        Bilinear samples with border padding; only pixels with ``in_front`` are meaningful
        (the losses leave the others out).
    """
    b, _, h, w = source.shape
    if h < 2 or w < 2:
        raise ParameterError(f"images need at least 2x2 pixels to be warped, got {w}x{h}")
    if depth.shape != (b, 1, h, w):
        raise ParameterError(
            f"depth {tuple(depth.shape)} does not match the source {tuple(source.shape)}"
        )
    uv, z = project(backproject(depth, K), K, T_t_to_s)
    u, v = uv[:, 0], uv[:, 1]
    in_front = (z[:, 0] > MIN_SOURCE_DEPTH).reshape(b, 1, h, w)
    # a border pixel's projection lands a rounding error outside (v = -1e-16 for the identity
    # in float64): within the round-off of K^-1 then K at this image size it is inside
    tol = BORDER_ULPS * torch.finfo(uv.dtype).eps * max(h, w)
    within = (u >= -tol) & (u <= w - 1 + tol) & (v >= -tol) & (v <= h - 1 + tol)
    inside = in_front & within.reshape(b, 1, h, w)
    grid = torch.stack([2 * u / (w - 1) - 1, 2 * v / (h - 1) - 1], dim=-1).reshape(b, h, w, 2)
    # points behind the camera would sample at arbitrary (possibly huge) coordinates
    grid = torch.where(in_front.reshape(b, h, w, 1), grid, torch.zeros_like(grid))
    image = F.grid_sample(source, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return Warp(image, in_front, inside)
