"""Point clouds to sparse depth maps: pinhole projection with an exact, order-free z-buffer.

Conventions (METHODS.md sections 0-1):

- ``calib.projection`` (3x4, ``P @ T_cam_from_sensor``) takes homogeneous sensor points to
  homogeneous pixels ``(u w, v w, w)``; ``w`` is the depth (camera z in metres; with a KITTI
  ``P2`` it is z in camera 2's frame, as KITTI and monodepth2 use).
- Pixel centres sit at integer coordinates: a point at (u, v) lands in pixel
  ``(rint(u) + pixel_offset, rint(v) + pixel_offset)``. ``rint`` rounds half to even, as
  ``numpy.round`` (and so monodepth2) does; it differs from round-half-up only for points
  exactly on a pixel border.
- A point is kept when ``min_depth < w <= max_depth`` and its pixel is inside the image.
  Points with NaN or Inf coordinates never land anywhere.
- Z-buffer: the smallest depth wins. The depth map is therefore independent of point order.
  For the index map, equal depths are decided by the points' coordinates (smallest x, then
  y, then z) and only exact duplicates by the smallest index, so it is independent of point
  order up to exact duplicates.

The z-buffer is one pass over the points (a scatter with a min), so its cost is O(N) with no
sort. It runs in numpy until a process has projected enough points to pay for loading the
compiled numba loop (:data:`COMPILED_AFTER_POINTS`); both give the same maps bit for bit. The
index map (:func:`project_points_with_index`) always uses the compiled loop.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence

import numpy as np

from ..calibration import Calibration
from ..errors import ParameterError
from ..validate import (
    check_all_finite,
    check_choice,
    check_instance,
    check_int_range,
    check_non_negative,
    check_nonempty,
    check_ordered,
    check_points,
    check_shape,
)

__all__ = [
    "BACKENDS",
    "COMPILED_AFTER_POINTS",
    "accumulate_sweeps",
    "nuscenes_T_cam_from_sensor",
    "project_points",
    "project_points_with_index",
    "project_uvz",
    "rigid_inverse",
    "sparse_from_depth",
    "transform_points",
]

# -- the z-buffer ---------------------------------------------------------------------------------
# Two exact implementations of one pass "project, filter, keep the smallest depth per pixel":
# numpy (below) and a compiled numba loop (:mod:`._projection_kernels`). Both compute in
# float64 in the order ``M[r, 0] x + M[r, 1] y + M[r, 2] z + M[r, 3]``, without fused
# multiply-adds, so they give the same maps bit for bit (tests/test_speed_equivalence.py).
# numba's load costs 0.5-1 s per process, the numpy pass (a float32 pre-selection of the
# points that can land, then the exact float64 pass on those) about 1 ms more than the compiled
# one per 120k-point KITTI frame: a process starts with numpy and switches once the points it
# has projected would have paid for the load (a ski-rental rule: never more than twice the
# cost of the better choice made in hindsight).

#: Points a process projects with numpy before it loads the compiled kernel.
COMPILED_AFTER_POINTS = 80_000_000
_points_projected = 0


#: The choices of ``backend``: ``auto`` (the rule above, and the compiled kernel at once
#: when numba is loaded in the process already), ``numpy`` or ``compiled`` (always).
BACKENDS = ("auto", "numpy", "compiled")


def _use_compiled(n_points: int, backend: str = "auto") -> bool:
    global _points_projected
    if backend != "auto":
        return backend == "compiled"
    if "numba" in sys.modules:  # loaded already (by this or any other module): free to use
        return True
    _points_projected += n_points
    return _points_projected > COMPILED_AFTER_POINTS


def _affine_row(M: np.ndarray, r: int, x, y, z) -> np.ndarray:
    """``M[r, 0] x + M[r, 1] y + M[r, 2] z + M[r, 3]`` in float64, left to right."""
    out = np.multiply(x, M[r, 0], dtype=np.float64)
    tmp = np.multiply(y, M[r, 1], dtype=np.float64)
    out += tmp
    np.multiply(z, M[r, 2], out=tmp, dtype=np.float64)
    out += tmp
    out += M[r, 3]
    return out


#: Clouds smaller than this skip the float32 pre-selection (the exact pass is cheap already).
_PRESELECT_MIN_POINTS = 4096
_EPS32 = float(np.finfo(np.float32).eps)


def _candidates(points, M, min_depth, max_depth, offset, shape) -> np.ndarray | None:
    """Rows that may land in the image: a superset of those the exact test keeps (None: all).

    A point lands when ``min_depth < w <= max_depth`` and ``rint(U / w) + offset`` lies in
    ``0 .. width - 1`` (likewise for V), which for ``w > 0`` implies the five linear
    conditions ``w > min_depth``, ``w <= max_depth``, ``U >= c_lo w``, ``U <= c_hi w`` (and
    V's) with ``c_lo = -offset - 0.5``, ``c_hi = width - 1 - offset + 0.5``. They are
    evaluated for all points at once in float32 (one small matrix product) and each is
    relaxed by 16 float32 epsilons of its largest possible term sum ``S`` (every coordinate
    bounded by the cloud's largest magnitude): more than any float32 rounding of the product
    and of the coefficients, and of the float64 rounding of the exact test. So no point that
    lands is dropped, and the exact float64 pass then runs on the few candidates only.
    """
    if points.shape[0] < _PRESELECT_MIN_POINTS:
        return None
    bound = max(abs(float(points.min())), abs(float(points.max())))  # NaN/Inf: not finite
    if not math.isfinite(bound):
        return None
    height, width = shape
    c_lo = -offset - 0.5
    cu_hi = width - 1 - offset + 0.5
    cv_hi = height - 1 - offset + 0.5
    rows = np.stack([M[2], M[0] - c_lo * M[2], cu_hi * M[2] - M[0],
                     M[1] - c_lo * M[2], cv_hi * M[2] - M[1]])  # fmt: skip
    weight = np.abs(np.stack([M[2], M[0], M[0], M[1], M[1]]))
    weight += np.abs([0.0, c_lo, cu_hi, c_lo, cv_hi])[:, None] * np.abs(M[2])[None, :]
    term_sum = weight[:, :3].sum(axis=1) * bound + weight[:, 3]
    if not np.all(term_sum < 1e30):  # float32 could overflow: no pre-selection
        return None
    slack = 16.0 * _EPS32 * term_sum
    linear = rows[:, :3].astype(np.float32) @ points[:, :3].T  # (5, N)
    # float32 thresholds rounded outwards, so that the comparisons stay in float32 and still
    # keep every point the float64 thresholds would.
    keep = linear[0] > _float32_below(min_depth - rows[0, 3] - slack[0])
    keep &= linear[0] <= _float32_above(max_depth - rows[0, 3] + slack[0])
    for k in range(1, 5):
        keep &= linear[k] >= _float32_below(-rows[k, 3] - slack[k])
    return np.flatnonzero(keep)


def _float32_below(value: float) -> np.float32:
    """The largest float32 <= ``value``."""
    f = np.float32(value)
    return f if f <= value else np.nextafter(f, np.float32(-np.inf))


def _float32_above(value: float) -> np.float32:
    """The smallest float32 >= ``value``."""
    f = np.float32(value)
    return f if f >= value else np.nextafter(f, np.float32(np.inf))


def _zbuffer_depth_numpy(points, M, min_depth, max_depth, offset, depth) -> int:
    """numpy twin of :func:`._projection_kernels.zbuffer_depth` (same arguments and result)."""
    height, width = depth.shape
    rows = _candidates(points, M, min_depth, max_depth, offset, depth.shape)
    if rows is not None:
        points = np.take(points, rows, axis=0)  # 7x faster than points[rows] for (N, 4) rows
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    w = _affine_row(M, 2, x, y, z)
    front = np.flatnonzero((w > min_depth) & (w <= max_depth))  # NaN fails both
    if front.size < w.size:  # after the pre-selection, usually all of them
        x, y, z, w = x[front], y[front], z[front], w[front]
    fu = _affine_row(M, 0, x, y, z)
    fu /= w
    np.rint(fu, out=fu)
    fu += offset
    fv = _affine_row(M, 1, x, y, z)
    fv /= w
    np.rint(fv, out=fv)
    fv += offset
    d = w.astype(np.float32)
    inside = (fu >= 0.0) & (fu < width) & (fv >= 0.0) & (fv < height) & (d > 0.0)
    hit = np.flatnonzero(inside)
    pixel = fv[hit].astype(np.intp)
    pixel *= width
    pixel += fu[hit].astype(np.intp)
    flat = depth.reshape(-1)
    # Only the pixels hit are reset for the minimum: no pass over the whole image, and a pixel
    # reached by an Inf depth alone holds Inf, as in the compiled loop.
    flat[pixel] = np.inf
    np.minimum.at(flat, pixel, d[hit])
    return int(hit.size)


def _zbuffer_depth(points, M, min_depth, max_depth, offset, depth, backend="auto") -> int:
    if _use_compiled(points.shape[0], backend):
        from ._projection_kernels import zbuffer_depth

        return int(zbuffer_depth(points, M, min_depth, max_depth, offset, depth))
    # Inf and NaN coordinates are dropped by the tests, silently, as in the compiled loop.
    with np.errstate(all="ignore"):
        return _zbuffer_depth_numpy(points, M, min_depth, max_depth, offset, depth)


def _check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    points = np.asarray(points)
    check_points(points, name)
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    return np.ascontiguousarray(points)


def _check_options(
    calib: Calibration, min_depth: float, max_depth: float | None, pixel_offset: int
) -> tuple[np.ndarray, int, int, float, float, int]:
    check_instance(calib, "calib", Calibration)
    width, height = calib.size
    min_depth = check_non_negative(min_depth, "min_depth")
    if max_depth is None:
        max_depth = np.inf
    else:
        max_depth = float(max_depth)  # inf: no limit
        check_ordered(min_depth, max_depth, "min_depth", "max_depth")
    pixel_offset = check_int_range(pixel_offset, "pixel_offset")
    M = np.ascontiguousarray(calib.projection, dtype=np.float64)
    return M, width, height, min_depth, max_depth, pixel_offset


def project_uvz(points: np.ndarray, projection: np.ndarray) -> tuple[np.ndarray, ...]:
    """Continuous image coordinates and depth of every point (no rounding, no filtering).

    Parameters
    ----------
    points : (N, C) float, metres
        Sensor-frame points, x, y, z in the first three columns.
    projection : (3, 4) float
        ``calib.projection``.

    Returns
    -------
    u, v, depth : (N,) float64
        Pixel coordinates (centres at integers) and depth in metres. Points at depth 0
        give non-finite u, v; points behind the camera give a negative depth.
    """
    points = _check_points(points)
    M = np.asarray(projection, dtype=np.float64)
    check_shape(M, "(3, 4)", "projection")
    xyz = points[:, :3].astype(np.float64)
    uvw = xyz @ M[:, :3].T + M[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = uvw[:, 0] / uvw[:, 2]
        v = uvw[:, 1] / uvw[:, 2]
    return u, v, uvw[:, 2]


def project_points(
    points: np.ndarray,
    calib: Calibration,
    *,
    min_depth: float = 0.1,
    max_depth: float | None = None,
    pixel_offset: int = 0,
    return_count: bool = False,
    backend: str = "auto",
) -> np.ndarray | tuple[np.ndarray, int]:
    """Project a point cloud to a sparse depth map (nearest point wins).

    Parameters
    ----------
    points : (N, C) float32 or float64, metres
        Sensor-frame points, x, y, z first (further columns are ignored).
    calib : Calibration
        Sensor-to-camera calibration with a known image size (``calib.size``).
    min_depth : float, metres
        Points with depth <= ``min_depth`` are dropped (>= 0; default 0.1).
    max_depth : float, metres, optional
        Points with depth > ``max_depth`` are dropped (default: no limit).
    pixel_offset : int
        Added to the rounded pixel coordinates: 0 (default, pixel centres at integers) or
        -1 (monodepth2's shift mimicking KITTI's 1-based MATLAB code).
    return_count : bool
        Also return how many points landed inside the image (before the z-buffer).
    backend : {"auto", "numpy", "compiled"}
        Which of the two bit-identical z-buffers runs. ``compiled`` (numba) is the fastest
        per frame (about 4x the numpy pass on a KITTI scan) but its first call in a process
        loads numba (0.3-1 s); ``numpy`` never loads it; ``auto`` (default) uses the compiled
        kernel when numba is loaded in the process already, and otherwise switches to it once
        the process has projected :data:`COMPILED_AFTER_POINTS` points. Pass ``compiled`` in a
        long loop of your own.

    Returns
    -------
    depth : (H, W) float32, metres
        0 where no point landed.
    n_in_image : int
        Only with ``return_count``.

    Examples
    --------
    >>> calib = Calibration(K=np.diag([100.0, 100.0, 1.0]) + [[0, 0, 2], [0, 0, 1], [0, 0, 0]],
    ...                     T_cam_from_sensor=np.eye(4), width=4, height=3)
    >>> float(project_points(np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 4.0]]), calib)[1, 2])
    4.0
    """
    points = _check_points(points)
    M, width, height, lo, hi, offset = _check_options(calib, min_depth, max_depth, pixel_offset)
    check_choice(backend, "backend", BACKENDS)
    depth = np.zeros((height, width), dtype=np.float32)
    n_in = int(_zbuffer_depth(points, M, lo, hi, offset, depth, backend)) if points.shape[0] else 0
    return (depth, n_in) if return_count else depth


def project_points_with_index(
    points: np.ndarray,
    calib: Calibration,
    *,
    min_depth: float = 0.1,
    max_depth: float | None = None,
    pixel_offset: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`project_points`, also returning which point won each pixel.

    The index map carries any per-point field into the image:
    ``np.where(index >= 0, intensity[index], 0)`` (intensity, ring, radar velocity, RCS).

    Returns
    -------
    depth : (H, W) float32, metres
        0 where no point landed.
    index : (H, W) int64
        Row of ``points`` that won the pixel (smallest depth; on equal depth the smallest
        (x, y, z), then the smallest index); -1 where no point landed.
    """
    points = _check_points(points)
    M, width, height, lo, hi, offset = _check_options(calib, min_depth, max_depth, pixel_offset)
    depth = np.zeros((height, width), dtype=np.float32)
    index = np.full((height, width), -1, dtype=np.int64)
    if points.shape[0]:
        from ._projection_kernels import zbuffer_index

        zbuffer_index(points, M, lo, hi, offset, depth, index)
    return depth, index


def transform_points(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Points moved by a rigid transform, in float64 and in the z-buffer's operation order.

    Parameters
    ----------
    points : (N, C) float, metres
        x, y, z in the first three columns.
    T : (4, 4) float
        Row-major transform (e.g. ``T_cam_lidar``).

    Returns
    -------
    (N, 3) float64
        ``T[r, 0] x + T[r, 1] y + T[r, 2] z + T[r, 3]`` per row ``r``, left to right, as
        :func:`project_points` computes its rows: with ``T``'s third row equal to a
        projection's, the depth is bit for bit the one that projection gives.
    """
    points = _check_points(points)
    T = np.asarray(T, dtype=np.float64)
    check_shape(T, "(4, 4)", "T")
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return np.stack([_affine_row(T, r, x, y, z) for r in range(3)], axis=1)


def sparse_from_depth(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Valid pixels of a sparse depth map as coordinate lists, in row-major order.

    Parameters
    ----------
    depth : (H, W) float, metres; 0 or non-finite = empty. H and W must be <= 65536.

    Returns
    -------
    u, v : (M,) uint16
        Column and row of each valid pixel.
    depth : (M,) float32, metres
        Exact values of the map (no quantisation).
    """
    depth = np.asarray(depth)
    check_shape(depth, "(H, W)", "depth")
    if max(depth.shape) > 65536:  # coordinates 0..65535 fit uint16
        raise ParameterError(
            f"map {depth.shape} too large for uint16 pixel coordinates", param="depth"
        )
    valid = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(valid)
    return u.astype(np.uint16), v.astype(np.uint16), depth[v, u].astype(np.float32)


# -- rigid transforms (nuScenes chains, multi-sweep accumulation) --------------------------------


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform ``[R | t]``: ``[R^T | -R^T t]``."""
    T = np.asarray(T, dtype=np.float64)
    check_shape(T, "(4, 4)", "T")
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def nuscenes_T_cam_from_sensor(
    T_ego_from_sensor: np.ndarray,
    T_global_from_ego_at_sensor: np.ndarray,
    T_global_from_ego_at_camera: np.ndarray,
    T_ego_from_camera: np.ndarray,
) -> np.ndarray:
    """nuScenes chain sensor -> ego (sensor time) -> global -> ego (camera time) -> camera.

    Parameters
    ----------
    T_ego_from_sensor : (4, 4)
        The sensor's ``calibrated_sensor`` record.
    T_global_from_ego_at_sensor : (4, 4)
        ``ego_pose`` of the sensor's sample_data (its timestamp).
    T_global_from_ego_at_camera : (4, 4)
        ``ego_pose`` of the camera's sample_data.
    T_ego_from_camera : (4, 4)
        The camera's ``calibrated_sensor`` record.

    Returns
    -------
    T_cam_from_sensor : (4, 4) float64
    """
    for name, T in (
        ("T_ego_from_sensor", T_ego_from_sensor),
        ("T_global_from_ego_at_sensor", T_global_from_ego_at_sensor),
        ("T_global_from_ego_at_camera", T_global_from_ego_at_camera),
        ("T_ego_from_camera", T_ego_from_camera),
    ):
        check_shape(np.asarray(T), "(4, 4)", name)
    return (
        rigid_inverse(T_ego_from_camera)
        @ rigid_inverse(T_global_from_ego_at_camera)
        @ np.asarray(T_global_from_ego_at_sensor, dtype=np.float64)
        @ np.asarray(T_ego_from_sensor, dtype=np.float64)
    )


def accumulate_sweeps(
    sweeps: Sequence[tuple[np.ndarray, np.ndarray]], *, return_sweep_index: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Merge several sweeps into one frame (multi-sweep radar or LiDAR accumulation).

    Parameters
    ----------
    sweeps : sequence of (points, T_target_from_sweep)
        ``points`` (N_k, C) with x, y, z (metres) in the sweep's sensor frame and the same C
        for every sweep; ``T_target_from_sweep`` (4, 4) takes that sweep's sensor frame (at
        its own time) to the target frame, e.g. the key sweep's sensor frame:
        ``inv(T_global_from_ego_key @ T_ego_from_sensor_key) @ T_global_from_ego_k @
        T_ego_from_sensor_k``.
    return_sweep_index : bool
        Also return, per point, the position of its sweep in ``sweeps``.

    Returns
    -------
    points : (sum N_k, C), dtype of the first sweep
        x, y, z transformed (computed in float64); the other columns are copied unchanged.
        Radar velocities (vx, vy, vx_comp, vy_comp) are not rotated, as in the nuScenes devkit.
    sweep_index : (sum N_k,) int16
        Only with ``return_sweep_index``.
    """
    check_nonempty(sweeps, "sweeps")
    chunks, owners = [], []
    n_cols = None
    dtype = None
    for k, (pts, T) in enumerate(sweeps):
        pts = _check_points(pts, f"sweeps[{k}]")
        T = np.asarray(T, dtype=np.float64)
        check_shape(T, "(4, 4)", f"sweeps[{k}]")  # T_target_from_sweep
        check_all_finite(T, f"sweeps[{k}]")
        if n_cols is None:
            n_cols, dtype = pts.shape[1], pts.dtype
        elif pts.shape[1] != n_cols:
            raise ParameterError(f"sweep {k} has {pts.shape[1]} columns, sweep 0 has {n_cols}")
        out = pts.astype(dtype, copy=True)
        out[:, :3] = pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        chunks.append(out)
        owners.append(np.full(pts.shape[0], k, dtype=np.int16))
    merged = np.concatenate(chunks, axis=0)
    return (merged, np.concatenate(owners)) if return_sweep_index else merged
