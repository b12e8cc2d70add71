"""Rigid registration of LiDAR scans: Open3D point-to-plane ICP and pose chaining.

Used to get poses for :func:`sparsetools.ops.accumulate.accumulate_scans` when a sequence
has none (KITTI raw without oxts, a bag of scans): register consecutive scans pairwise with
:func:`icp_pose`, then :func:`chain_poses` turns the pairwise transforms into every frame's
pose relative to one reference frame.

Open3D is imported inside :func:`icp_pose` (``import sparsetools.ops.registration`` stays
light). Pure computation: arrays in, arrays out.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..errors import DependencyError, ParameterError
from ..validate import (
    check_all_finite,
    check_int_range,
    check_non_negative,
    check_points,
    check_positive,
    check_shape,
)
from .projection import rigid_inverse

__all__ = ["IcpResult", "chain_poses", "icp_pose"]

#: Coarse-to-fine stages (voxel size, correspondence distance) as multiples of the finest
#: ones: a coarse pass pulls in an initial guess that is a metre or more off.
_PYRAMID = ((4.0, 4.0), (2.0, 2.0), (1.0, 1.0))


class IcpResult(NamedTuple):
    """Outcome of :func:`icp_pose` (unpacks as ``T, fitness, rmse = icp_pose(...)``).

    Attributes
    ----------
    T_target_from_source : (4, 4) float64
        Rigid transform taking source-scan coordinates (metres) to target-scan coordinates.
    fitness : float
        Fraction of the (downsampled) source points with a target correspondence within
        ``max_distance`` after the last iteration, 0..1.
    inlier_rmse : float, metres
        Root mean square point-to-point distance of those correspondences.
    """

    T_target_from_source: np.ndarray
    fitness: float
    inlier_rmse: float


def _import_open3d():
    try:
        import open3d as o3d
    except ImportError as exc:
        msg = str(exc)
        hint = (
            "apt-get install -y libusb-1.0-0"
            if "libusb" in msg
            else "pip install 'sparsetools[open3d]' (Open3D is an optional extra)"
        )
        raise DependencyError(
            f"ICP needs Open3D, which cannot be imported ({msg}): {hint}"
        ) from exc
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def _check_cloud(name: str, points, min_range: float) -> np.ndarray:
    p = np.asarray(points)
    check_points(p, name)
    xyz = p[:, :3].astype(np.float64)
    keep = np.all(np.isfinite(xyz), axis=1)
    if min_range > 0:
        keep &= np.hypot(xyz[:, 0], xyz[:, 1]) >= min_range
    xyz = xyz[keep]
    if xyz.shape[0] < 10:
        raise ParameterError(
            f"{name} has {xyz.shape[0]} finite points beyond min_range; ICP needs at least 10"
        )
    return np.ascontiguousarray(xyz)


def _check_transform(name: str, T) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    check_shape(T, "(4, 4)", name)
    check_all_finite(T, name)
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ParameterError(f"{name} is not a rigid transform (rotation not orthonormal)")
    if not np.allclose(T[3], (0, 0, 0, 1)):
        raise ParameterError(f"{name} must have last row 0 0 0 1")
    return T


def icp_pose(
    source_points: np.ndarray,
    target_points: np.ndarray,
    *,
    init: np.ndarray | None = None,
    max_distance: float = 0.5,
    voxel: float = 0.2,
    coarse_to_fine: bool = True,
    normal_radius: float | None = None,
    max_iterations: int = 60,
    min_range: float = 0.0,
    tukey_k: float | None = None,
) -> IcpResult:
    """Rigid transform that aligns a source scan to a target scan (point-to-plane ICP).

    Both clouds are voxel-downsampled; the target's normals are estimated from its
    neighbours within ``normal_radius`` (at most 30); Open3D's ``registration_icp`` with
    ``TransformationEstimationPointToPlane`` then minimises the squared distances of the
    source points to the tangent planes of their nearest target points within
    ``max_distance``.

    Parameters
    ----------
    source_points, target_points : (N, C) float, metres
        x, y, z first (other columns ignored; non-finite rows dropped).
    init : (4, 4) float, optional
        Initial ``T_target_from_source`` (default identity). For consecutive KITTI scans
        (10 Hz, up to ~1.5 m apart) identity is enough with ``coarse_to_fine``.
    max_distance : float, metres
        Correspondence distance of the finest stage (and of the reported fitness / RMSE).
    voxel : float, metres
        Voxel size of the finest stage.
    coarse_to_fine : bool
        Run two coarser stages first (voxel and distance x4 and x2), each starting from the
        result of the previous one.
    normal_radius : float, metres, optional
        Neighbourhood of the normal estimate (default ``3 * voxel`` at each stage).
    max_iterations : int
        ICP iterations per stage.
    min_range : float, metres
        Drop points closer than this horizontal range ``hypot(x, y)`` to their sensor from
        both clouds. In traffic most near points belong to vehicles that move with the ego
        car and pull the estimate towards "no motion" (on the real KITTI sequence here, all
        points give 0.13 m per frame, points beyond 20 m give the 0.24 m that registering
        frames 10 apart confirms); 0 keeps everything.
    tukey_k : float, metres, optional
        Use Open3D's Tukey robust loss with this width instead of least squares.

    Returns
    -------
    IcpResult
        ``T_target_from_source`` (4, 4) float64, ``fitness`` and ``inlier_rmse`` (metres) of
        the finest stage.

    Raises
    ------
    ParameterError
        Bad shapes, fewer than 10 finite points, non-rigid ``init``, non-positive sizes.
    DependencyError
        Open3D cannot be imported.
    """
    min_range = check_non_negative(min_range, "min_range")
    source = _check_cloud("source_points", source_points, min_range)
    target = _check_cloud("target_points", target_points, min_range)
    tukey_k = check_positive(tukey_k, "tukey_k", allow_none=True)
    T = np.eye(4) if init is None else _check_transform("init", init)
    max_distance = check_positive(max_distance, "max_distance")
    voxel = check_positive(voxel, "voxel")
    normal_radius = check_positive(normal_radius, "normal_radius", allow_none=True)
    max_iterations = check_int_range(max_iterations, "max_iterations", low=1)
    o3d = _import_open3d()
    reg = o3d.pipelines.registration
    src_full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    tgt_full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    estimation = (
        reg.TransformationEstimationPointToPlane()
        if tukey_k is None
        else reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=tukey_k))
    )
    stages = _PYRAMID if coarse_to_fine else _PYRAMID[-1:]
    try:
        return _icp_stages(o3d, reg, src_full, tgt_full, T, estimation, stages, voxel=voxel,
                           max_distance=max_distance, normal_radius=normal_radius,
                           max_iterations=max_iterations)  # fmt: skip
    except RuntimeError as exc:  # Open3D's own refusal of these clouds (extents, degeneracy)
        text = re.sub(r"\x1b\[[0-9;]*m", "", str(exc))
        reason = text.rsplit(": ", 1)[-1].strip().rstrip(".") or "Open3D failed"
        raise ParameterError(
            f"ICP cannot register these scans: {reason} (points spread over "
            f"{float(np.ptp(source[:, :3])):.3g} m with --icp-voxel {voxel:g} m)"
        ) from exc


def _icp_stages(o3d, reg, src_full, tgt_full, T, estimation, stages, *, voxel, max_distance,
                normal_radius, max_iterations) -> IcpResult:  # fmt: skip
    result = None
    for voxel_factor, distance_factor in stages:
        size = voxel * voxel_factor
        distance = max_distance * distance_factor
        src = src_full.voxel_down_sample(size)
        tgt = tgt_full.voxel_down_sample(size)
        radius = 3.0 * size if normal_radius is None else normal_radius
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        result = reg.registration_icp(
            src,
            tgt,
            distance,
            T,
            estimation,
            reg.ICPConvergenceCriteria(
                relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=int(max_iterations)
            ),
        )
        T = np.asarray(result.transformation, dtype=np.float64).copy()
    return IcpResult(T, float(result.fitness), float(result.inlier_rmse))


def chain_poses(T_previous_from_next: Sequence[np.ndarray], *, reference: int = 0) -> np.ndarray:
    """Poses of a sequence relative to one of its frames, from consecutive-pair transforms.

    Parameters
    ----------
    T_previous_from_next : sequence of (4, 4) float, length n - 1
        Element k takes frame k+1's coordinates to frame k's, i.e. the
        ``T_target_from_source`` of ``icp_pose(scan[k + 1], scan[k])``.
    reference : int
        Frame whose coordinates become the common "world" (0 <= reference < n).

    Returns
    -------
    T_reference_from_frame : (n, 4, 4) float64
        ``T_reference_from_frame[reference]`` is the identity. Usable directly as the
        ``T_world_from_velo`` poses of :func:`sparsetools.ops.accumulate.accumulate_scans`.
    """
    pairs = [
        _check_transform(f"T_previous_from_next[{k}]", T)
        for k, T in enumerate(T_previous_from_next)
    ]
    n = len(pairs) + 1
    reference = check_int_range(reference, "reference", low=0, high=n - 1)
    # Poses relative to frame 0 first: T_0_from_k = T_0_from_1 @ ... @ T_{k-1}_from_k.
    T_first_from = np.empty((n, 4, 4))
    T_first_from[0] = np.eye(4)
    for k, T in enumerate(pairs):  # one matrix product per frame
        T_first_from[k + 1] = T_first_from[k] @ T
    T_ref_from_first = rigid_inverse(T_first_from[reference])
    out = T_ref_from_first[None] @ T_first_from
    out[reference] = np.eye(4)
    return out
