"""Point clouds of any supported format, chosen by suffix and content.

==========================  ===============================================  =============
suffix                      format                                           columns
==========================  ===============================================  =============
``.bin``                    KITTI Velodyne float32 rows                      x y z r
``.pcd.bin``                nuScenes LIDAR_TOP float32 rows                  x y z i ring
``.pcd`` (nuScenes fields)  nuScenes radar PCD v0.7 (devkit filters on)      18 radar fields
``.pcd`` / ``.ply``         any other PCD (ascii, binary, binary_compressed)  x y z + attrs
                            or PLY (ascii, binary), read natively
``.npy``                    (N, C) array                                     as stored
==========================  ===============================================  =============
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .atomic import atomic_path
from .kitti import drop_non_finite, read_velodyne_bin, write_velodyne_bin
from .nuscenes import RADAR_FIELDS, read_lidar_pcd_bin, read_radar_pcd

__all__ = ["CLOUD_SUFFIXES", "cloud_kind", "read_points", "write_points"]

CLOUD_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")


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


# -- PCD / PLY: native readers, columns named and ordered as Open3D's tensor API names them --
# Before 0.4 these files were read through ``open3d.t.io.read_point_cloud``: x, y, z first,
# then every other attribute in the sorted order of Open3D's names (``colors`` for PCD's packed
# ``rgb``/``rgba`` or PLY's red/green/blue, ``normals`` for normal_x/y/z or nx/ny/nz, the
# field's own name otherwise). The native readers keep that layout, so every cloud Open3D read
# gives the same array; they differ where Open3D loses data: a PCD field of COUNT > 1 gives all
# its values (Open3D kept the first), PLY properties of type char/short/ushort/uint are kept
# (Open3D dropped them), PCL's ``_`` padding fields are skipped (Open3D kept their first byte).

_NORMALS = {"pcd": ("normal_x", "normal_y", "normal_z"), "ply": ("nx", "ny", "nz")}


def _packed_colours(values: np.ndarray) -> list[np.ndarray]:
    """PCL's packed colour (the bits of a float32 or a uint32 ``0x00RRGGBB``) as r, g, b."""
    bits = values.view(np.uint32) if values.dtype.kind == "f" else values.astype(np.uint32)
    return [(bits >> 16) & 255, (bits >> 8) & 255, bits & 255]


def _open3d_columns(rec: np.ndarray, kind: str, path: Path) -> np.ndarray:
    """(N, C) float32: x, y, z, then the attributes in the sorted order of Open3D's names."""
    names = rec.dtype.names
    groups: dict[str, list[np.ndarray]] = {}
    taken = {"x", "y", "z"}
    normals = _NORMALS[kind]
    if set(normals) <= set(names):
        groups["normals"] = [rec[n] for n in normals]
        taken.update(normals)
    if kind == "ply" and {"red", "green", "blue"} <= set(names):
        groups["colors"] = [rec[n] for n in ("red", "green", "blue")]
        taken.update(("red", "green", "blue"))
    if kind == "pcd":
        packed = next(
            (n for n in ("rgb", "rgba") if n in names and rec.dtype[n].itemsize == 4), None
        )
        if packed is not None:
            groups["colors"] = _packed_colours(rec[packed])
            taken.add(packed)
    for name in names:
        if name in taken:
            continue
        if name in groups or name == "positions":
            raise FormatError(f"{path}: field {name!r} collides with the name of other fields")
        values = rec[name]
        groups[name] = [values] if values.ndim == 1 else list(values.T)
    columns = [rec["x"], rec["y"], rec["z"]]
    for key in sorted(groups):
        columns.extend(groups[key])
    # float64 values beyond float32 become Inf (and are dropped by the caller): no warning.
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.empty((rec.shape[0], len(columns)), dtype=np.float32)
        for i, col in enumerate(columns):
            out[:, i] = col
    return out


def _read_pcd_ply(path: Path) -> np.ndarray:
    if not path.is_file():
        raise FormatError(f"{path}: no such point-cloud file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if not data:
        raise FormatError(f"{path}: empty file")
    if path.suffix.lower() == ".ply":
        from .ply import read_ply_vertices

        rec, _ = read_ply_vertices(path, data)
        points = _open3d_columns(rec, "ply", path)
    else:
        from .pcd import read_pcd

        rec, _ = read_pcd(path, data)
        points = _open3d_columns(rec, "pcd", path)
    points, _ = drop_non_finite(points, source=str(path))
    return points


def read_points(path: str | os.PathLike, *, strict: bool = False) -> np.ndarray:
    """Read a point cloud of any supported format (see the module table).

    Parameters
    ----------
    path : path-like
    strict : bool
        Every row must be kept or the file refused (``beams`` writes exact subsets of its
        input): an empty cloud and rows holding NaN/Inf are errors instead of a cloud with
        those rows dropped (PCD/PLY rows with NaN/Inf are still dropped, with a warning, as
        before 0.4).

    Returns
    -------
    (N, C) float32
        x, y, z in metres in the sensor frame first, then the format's other columns, in
        file order. Rows with NaN/Inf are dropped with a warning (refused with ``strict``).

    Raises
    ------
    FormatError
        Missing, unreadable, truncated or corrupt file; with ``strict`` also an empty cloud
        or NaN/Inf values.
    """
    points = _read(Path(path), keep=strict)
    if strict:
        if points.shape[0] == 0:
            raise FormatError(f"{path}: empty file (no points)")
        bad = int(np.count_nonzero(~np.isfinite(points).all(axis=1)))
        if bad:
            raise FormatError(f"{path}: {bad} point(s) hold NaN/Inf values (corrupt file?)")
    return points


def _read(p: Path, *, keep: bool) -> np.ndarray:
    kind = cloud_kind(p)
    if kind == "kitti-bin":
        return read_velodyne_bin(p, drop_non_finite_rows=not keep)
    if kind == "nuscenes-bin":
        return read_lidar_pcd_bin(p, drop_non_finite_rows=not keep)
    if kind == "radar-pcd":
        return read_radar_pcd(p)
    if kind == "npy":
        from .npy import load_npy

        try:
            data = p.read_bytes()
        except FileNotFoundError as exc:
            raise FormatError(f"{p}: no such file") from exc
        except OSError as exc:
            raise FormatError(f"{p}: cannot read ({exc.strerror or exc})") from exc
        a = load_npy(data, source=str(p))
        if a.ndim != 2 or a.shape[1] < 3 or a.dtype.kind not in "fiu":
            raise FormatError(f"{p}: expected a numeric (N, C>=3) array, got {a.dtype} {a.shape}")
        with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: Inf, dropped
            a = a.astype(np.float32)
        return a if keep else drop_non_finite(a, source=str(p))[0]
    return _read_pcd_ply(p)


def write_points(path: str | os.PathLike, points: np.ndarray, *, overwrite: bool = True) -> None:
    """Write an (N, C) cloud by suffix: ``.bin`` (float32 rows), ``.npy``, ``.pcd``/``.ply``.

    PCD (binary) and PLY (binary little-endian) hold float32 fields; columns beyond x, y, z
    are named ``intensity`` (4th), ``ring`` (5th) and ``attr{i}``, in column order.
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
    extra = {3: "intensity", 4: "ring"}
    names = ["x", "y", "z"] + [extra.get(i, f"attr{i}") for i in range(3, points.shape[1])]
    if suffix == ".pcd":
        from .pcd import write_pcd

        write_pcd(p, points, names, overwrite=overwrite)
    else:
        from .ply import write_ply

        write_ply(p, points, names, overwrite=overwrite)
