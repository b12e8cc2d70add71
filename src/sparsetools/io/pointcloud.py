"""Point clouds of any supported format, chosen by suffix and content.

==========================  ===============================================  =============
suffix                      format                                           columns
==========================  ===============================================  =============
``.bin``                    KITTI Velodyne float32 rows                      x y z r
``.pcd.bin``                nuScenes LIDAR_TOP float32 rows                  x y z i ring
``.pcd`` (nuScenes fields)  nuScenes radar PCD v0.7 (devkit filters on)      18 radar fields
``.pcd`` / ``.ply``         any other PCD/PLY through Open3D's tensor API    x y z + attrs
``.npy``                    (N, C) array                                     as stored
==========================  ===============================================  =============
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import DependencyError, FormatError
from .atomic import atomic_path
from .kitti import drop_non_finite, read_velodyne_bin, write_velodyne_bin
from .nuscenes import RADAR_FIELDS, read_lidar_pcd_bin, read_radar_pcd

__all__ = ["CLOUD_SUFFIXES", "cloud_kind", "import_open3d", "read_points", "write_points"]

CLOUD_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")


def import_open3d():
    """Import Open3D, turning a missing wheel or system library into a clear error."""
    try:
        import open3d as o3d
    except ImportError as exc:
        msg = str(exc)
        if "libusb" in msg:
            raise DependencyError(
                "Open3D needs the system library libusb-1.0: apt-get install -y libusb-1.0-0"
            ) from exc
        raise DependencyError(
            f"Open3D is needed for PCD/PLY files but cannot be imported ({msg}): pip install open3d"
        ) from exc
    return o3d


def cloud_kind(path: str | os.PathLike) -> str:
    """'kitti-bin', 'nuscenes-bin', 'radar-pcd', 'pcd', 'ply' or 'npy' for a cloud file."""
    p = Path(path)
    name = p.name.lower()
    if name.endswith(".pcd.bin"):
        return "nuscenes-bin"
    suffix = p.suffix.lower()
    if suffix == ".bin":
        return "kitti-bin"
    if suffix == ".pcd":
        try:
            with open(p, "rb") as fh:
                head = fh.read(1024)
        except OSError as exc:
            raise FormatError(f"{p}: cannot read ({exc.strerror or exc})") from exc
        for line in head.split(b"\n"):
            if line.upper().startswith(b"FIELDS"):
                if line.decode("ascii", "replace").split()[1:] == RADAR_FIELDS:
                    return "radar-pcd"
                break
        return "pcd"
    if suffix in (".ply", ".npy"):
        return suffix[1:]
    raise FormatError(f"{p}: unknown point-cloud format (expected {', '.join(CLOUD_SUFFIXES)})")


def _read_open3d(path: Path) -> np.ndarray:
    if not path.is_file():
        raise FormatError(f"{path}: no such point-cloud file")
    if path.stat().st_size == 0:
        raise FormatError(f"{path}: empty file")
    o3d = import_open3d()
    try:
        pcd = o3d.t.io.read_point_cloud(str(path))
    except Exception as exc:  # Open3D raises plain RuntimeError with its own text
        raise FormatError(f"{path}: Open3D cannot read it ({exc})") from exc
    if "positions" not in pcd.point:
        raise FormatError(f"{path}: no points (corrupt or unsupported {path.suffix} file)")
    cols = [pcd.point["positions"].numpy().astype(np.float32).reshape(-1, 3)]
    for key in sorted(k for k in pcd.point if k != "positions"):
        a = pcd.point[key].numpy().astype(np.float32)
        cols.append(a.reshape(a.shape[0], -1))
    points = np.hstack(cols)
    points, _ = drop_non_finite(points, source=str(path))
    return points


def read_points(path: str | os.PathLike) -> np.ndarray:
    """Read a point cloud of any supported format (see the module table).

    Returns
    -------
    (N, C) float32
        x, y, z in metres in the sensor frame first, then the format's other columns, in
        file order. Rows with NaN/Inf are dropped with a warning.
    """
    p = Path(path)
    kind = cloud_kind(p)
    if kind == "kitti-bin":
        return read_velodyne_bin(p)
    if kind == "nuscenes-bin":
        return read_lidar_pcd_bin(p)
    if kind == "radar-pcd":
        return read_radar_pcd(p)
    if kind == "npy":
        try:
            a = np.load(p, allow_pickle=False)
        except FileNotFoundError as exc:
            raise FormatError(f"{p}: no such file") from exc
        except (ValueError, OSError, EOFError) as exc:
            raise FormatError(f"{p}: not a valid .npy array ({exc})") from exc
        if a.ndim != 2 or a.shape[1] < 3 or a.dtype.kind not in "fiu":
            raise FormatError(f"{p}: expected a numeric (N, C>=3) array, got {a.dtype} {a.shape}")
        return drop_non_finite(a.astype(np.float32), source=str(p))[0]
    return _read_open3d(p)


def write_points(path: str | os.PathLike, points: np.ndarray, *, overwrite: bool = True) -> None:
    """Write an (N, C) cloud by suffix: ``.bin`` (float32 rows), ``.npy``, ``.pcd``/``.ply``.

    PCD/PLY go through Open3D's tensor API: columns beyond x, y, z are stored as
    ``intensity`` (4th) and ``ring`` (5th) or ``attr{i}``.
    """
    p = Path(path)
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] < 3:
        raise FormatError(f"points must be (N, C>=3), got shape {points.shape}")
    suffix = p.suffix.lower()
    if suffix == ".bin":
        write_velodyne_bin(p, points, overwrite=overwrite)
        return
    if suffix == ".npy":
        with atomic_path(p, overwrite=overwrite) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, points)
        return
    if suffix not in (".pcd", ".ply"):
        raise FormatError(f"{p}: cannot write '{suffix}' (use .bin, .npy, .pcd or .ply)")
    o3d = import_open3d()
    pcd = o3d.t.geometry.PointCloud()
    pcd.point["positions"] = o3d.core.Tensor(np.ascontiguousarray(points[:, :3]))
    names = {3: "intensity", 4: "ring"}
    for i in range(3, points.shape[1]):
        pcd.point[names.get(i, f"attr{i}")] = o3d.core.Tensor(
            np.ascontiguousarray(points[:, i : i + 1])
        )
    with atomic_path(p, overwrite=overwrite) as tmp:
        if not o3d.t.io.write_point_cloud(str(tmp), pcd, write_ascii=False):
            raise FormatError(f"{p}: Open3D failed to write the point cloud")
