"""KITTI Velodyne ``.bin`` point clouds: little-endian float32 (x, y, z, reflectance) rows."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .atomic import atomic_path

__all__ = ["drop_non_finite", "read_velodyne_bin", "write_velodyne_bin"]

log = logging.getLogger(__name__)


def drop_non_finite(points: np.ndarray, *, source: str = "") -> tuple[np.ndarray, int]:
    """Remove rows holding NaN or Inf; return the kept rows and how many were dropped.

    ``points`` itself is returned (no copy) when every value is finite.
    """
    # One pairwise sum is a fast test that every value is finite: NaN and Inf propagate into
    # it. A sum that overflows only sends a finite cloud down the exact per-row path below.
    with np.errstate(over="ignore", invalid="ignore"):
        total = points.sum() if points.size else 0.0
    if np.isfinite(total):
        return points, 0
    finite = np.isfinite(points).all(axis=1)
    dropped = int(points.shape[0] - np.count_nonzero(finite))
    if dropped:
        log.warning("%s: dropped %d point(s) with NaN/Inf coordinates", source or "cloud", dropped)
        points = points[finite]
    return points, dropped


def read_velodyne_bin(
    path: str | os.PathLike, *, n_columns: int = 4, drop_non_finite_rows: bool = True
) -> np.ndarray:
    """Read a KITTI Velodyne scan.

    Parameters
    ----------
    path : path-like
        ``.bin`` file of float32 rows.
    n_columns : int
        Floats per point: 4 for KITTI (x, y, z, reflectance), 5 for nuScenes LIDAR_TOP
        (x, y, z, intensity, ring).
    drop_non_finite_rows : bool
        Drop rows holding NaN/Inf (with a warning); False keeps every row as stored.

    Returns
    -------
    (N, n_columns) float32
        Points in the sensor frame, metres, in file (scan) order; a writable array of its
        own. Rows with NaN/Inf are dropped (a warning gives the count).

    Raises
    ------
    FormatError
        Missing file, or a size that is not a multiple of ``4 * n_columns`` bytes (truncated).
    """
    path = Path(path)
    row_bytes = 4 * n_columns
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size % row_bytes:
                raise FormatError(
                    f"{path}: size {size} bytes is not a multiple of {row_bytes} "
                    f"({n_columns} float32 per point): truncated or not a point cloud"
                )
            # Read straight into the array: no bytes object, no copy, no dtype conversion.
            points = np.empty((size // row_bytes, n_columns), dtype="<f4")
            got = fh.readinto(memoryview(points).cast("B")) if size else 0
            if got != size:
                raise FormatError(f"{path}: file changed size while it was read")
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such file") from exc
    except IsADirectoryError as exc:
        raise FormatError(f"{path}: is a folder, expected a .bin point cloud") from exc
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    # A no-op on little-endian machines; a byte swap on others.
    points = points.astype(np.float32, copy=False)
    if drop_non_finite_rows:
        points, _ = drop_non_finite(points, source=str(path))
    return points


def write_velodyne_bin(
    path: str | os.PathLike, points: np.ndarray, *, overwrite: bool = True
) -> None:
    """Write ``points`` ((N, C) array) as little-endian float32 rows, atomically."""
    points = np.asarray(points)
    if points.ndim != 2:
        raise FormatError(f"points must be (N, C), got shape {points.shape}")
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(np.ascontiguousarray(points, dtype="<f4").tobytes())
