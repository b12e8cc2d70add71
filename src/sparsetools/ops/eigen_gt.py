"""The KITTI Eigen-split ground truth as monodepth2 makes it (``generate_depth_map``).

monodepth2's ``export_gt_depth.py --split eigen`` projects each frame's Velodyne scan into
camera 2 and stores, per pixel, a depth map of the scan (METHODS.md section 12). To be a
drop-in ``gt_depths.npz`` this follows its convention, not sparsetools' own projection:

- points with Velodyne ``x < 0`` (behind the LiDAR) are dropped; nothing else is (no minimum
  or maximum depth, no test on the camera z);
- pixel = ``round(u) - 1``, ``round(v) - 1`` (numpy's round half to even, then the -1 offset
  mimicking KITTI's 1-based MATLAB code), kept when inside the image;
- the value stored is the point's **Velodyne x** (forward distance from the LiDAR:
  ``generate_depth_map(..., vel_depth=True)``), not its camera z; where several points land
  in one pixel the smallest value wins; negative values become 0 (0 = no value).

``value="camera-z"`` stores the camera z instead (what sparsetools' ``project`` stores, with
monodepth2's points, offset and smallest-value rule): the two differ by the LiDAR-camera
offset (~0.28 m on KITTI) and the small rotation between the sensors.
"""

from __future__ import annotations

import numpy as np

from ..validate import check_choice, check_int_range, check_points, check_shape

__all__ = ["VALUES", "eigen_depth_map"]

#: What a pixel of the map holds.
VALUES = ("velodyne-x", "camera-z")


def eigen_depth_map(
    points: np.ndarray,
    projection: np.ndarray,
    shape: tuple[int, int],
    *,
    value: str = "velodyne-x",
    pixel_offset: int = -1,
) -> np.ndarray:
    """A Velodyne scan as monodepth2's Eigen ground-truth depth map.

    Parameters
    ----------
    points : (N, C) float, metres
        Velodyne points, x (forward), y (left), z (up) first; further columns are ignored.
    projection : (3, 4) float
        Velodyne to camera-2 pixels: ``P_rect_02 @ R_rect_00 @ [R | T]`` (``calib.projection``
        of :func:`~sparsetools.io.calib.read_kitti_raw_calib`).
    shape : (height, width)
        The image size (``S_rect_02``, as monodepth2 takes it).
    value : {'velodyne-x', 'camera-z'}
        What a pixel holds (module docstring); monodepth2's Eigen GT is ``velodyne-x``.
    pixel_offset : int
        Added to the rounded pixel coordinates (monodepth2: -1).

    Returns
    -------
    (height, width) float32, metres
        0 where no point landed.
    """
    check_choice(value, "value", VALUES)
    check_points(points)
    M = np.asarray(projection, dtype=np.float64)
    check_shape(M, "(3, 4)", "projection")
    height = check_int_range(shape[0], "height", low=1)
    width = check_int_range(shape[1], "width", low=1)
    offset = check_int_range(pixel_offset, "pixel_offset")
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    xyz = xyz[xyz[:, 0] >= 0]  # NaN fails the test too
    uvw = xyz @ M[:, :3].T + M[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.round(uvw[:, 0] / uvw[:, 2]) + offset
        v = np.round(uvw[:, 1] / uvw[:, 2]) + offset
    inside = (u >= 0) & (v >= 0) & (u < width) & (v < height)  # NaN / Inf fail
    stored = (xyz[:, 0] if value == "velodyne-x" else uvw[:, 2])[inside]
    flat = v[inside].astype(np.int64) * width + u[inside].astype(np.int64)
    best = np.full(height * width, np.inf)
    np.minimum.at(best, flat, stored)
    best[~np.isfinite(best) | (best < 0)] = 0.0
    return best.reshape(height, width).astype(np.float32)
