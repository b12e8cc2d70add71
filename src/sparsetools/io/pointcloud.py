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
import struct
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
    # Open3D prints its warnings ("Read PCD failed ...") on stdout, which holds results and
    # --json summaries; the library reports failures through its own exceptions instead.
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
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


# -- header checks before Open3D ----------------------------------------------------------------
# Open3D trusts headers: a PCD header without POINTS/WIDTH yields a cloud of an uninitialised
# (billions of) points, and a PLY header cut short crashes the process (segmentation fault).
# Both formats are checked here first, and every declared count is bounded by the file size.

_PLY_TYPE_SIZES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
    "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "double": 8, "float64": 8,
}  # fmt: skip


def _check_pcd_header(data: bytes, path: Path) -> int:
    """Validate a PCD header against the file; return the number of points it declares."""
    from .nuscenes import parse_pcd_header

    header, offset = parse_pcd_header(data, path)
    try:
        fields = header["FIELDS"]
        sizes = [int(v) for v in header["SIZE"]]
        types = [t.upper() for t in header["TYPE"]]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(fields))]
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        points = int(header["POINTS"][0]) if "POINTS" in header else width * height
        kind = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as exc:
        raise FormatError(
            f"{path}: PCD header misses or garbles FIELDS/SIZE/TYPE/WIDTH/HEIGHT/DATA"
        ) from exc
    if (
        not fields
        or not len(fields) == len(sizes) == len(types) == len(counts)
        or any(v not in (1, 2, 4, 8) for v in sizes)
        or any(t not in ("F", "I", "U") for t in types)
        or any(not 1 <= c <= 4096 for c in counts)
    ):
        raise FormatError(f"{path}: PCD header has inconsistent FIELDS/SIZE/TYPE/COUNT")
    if len(set(fields)) != len(fields):  # Open3D 0.19 corrupts its heap on a repeated field
        raise FormatError(
            f"{path}: PCD header repeats a field name (PCL's '_' padding fields included): "
            "Open3D cannot read such files safely"
        )
    if not {"x", "y", "z"} <= set(fields):
        raise FormatError(f"{path}: PCD has no x, y, z fields")
    if min(width, height, points) < 0 or points != width * height:
        raise FormatError(f"{path}: PCD header: POINTS {points} != WIDTH {width} x HEIGHT {height}")
    row = sum(v * c for v, c in zip(sizes, counts, strict=True))
    body = len(data) - offset
    if kind == "binary":
        if points * row > body:
            raise FormatError(
                f"{path}: truncated: {points} points of {row} bytes declared, {body} bytes held"
            )
    elif kind == "binary_compressed":
        if body < 8:
            raise FormatError(f"{path}: truncated compressed PCD data")
        packed, unpacked = struct.unpack("<II", data[offset : offset + 8])
        if unpacked != points * row or packed > body - 8:
            raise FormatError(f"{path}: compressed PCD sizes do not match the header")
    elif kind == "ascii":
        if points > data.count(b"\n", offset) + 1:
            raise FormatError(f"{path}: truncated: {points} points declared, fewer lines held")
    else:
        raise FormatError(f"{path}: PCD DATA '{kind}' unsupported")
    return points


def _check_ply_header(data: bytes, path: Path) -> int:
    """Validate a PLY header against the file; return the number of vertices it declares."""
    end = data.find(b"end_header")
    nl = data.find(b"\n", end) if end >= 0 else -1
    if not data.startswith(b"ply") or nl < 0:
        raise FormatError(f"{path}: not a PLY file (no complete 'ply' ... 'end_header' header)")
    try:
        lines = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not a PLY file (binary data in the header)") from exc
    fmt = None
    elements: list[list] = []  # name, count, bytes per row (lists: their count only), properties
    try:
        for line in lines:
            parts = line.split()
            if not parts or parts[0] in ("comment", "obj_info"):
                continue
            if parts[0] == "format" and len(parts) == 3 and parts[2] == "1.0":
                fmt = parts[1]
            elif parts[0] == "element" and len(parts) == 3 and int(parts[2]) >= 0:
                elements.append([parts[1], int(parts[2]), 0, []])
            elif parts[0] == "property" and elements and len(parts) == 5 and parts[1] == "list":
                _PLY_TYPE_SIZES[parts[3]]  # the item type must be known too
                elements[-1][2] += _PLY_TYPE_SIZES[parts[2]]  # at least the count per row
                elements[-1][3].append(parts[4])
            elif parts[0] == "property" and elements and len(parts) == 3:
                elements[-1][2] += _PLY_TYPE_SIZES[parts[1]]
                elements[-1][3].append(parts[2])
            else:
                raise ValueError(line)
    except (ValueError, KeyError) as exc:
        raise FormatError(f"{path}: PLY header line not understood: {str(exc)[:60]!r}") from exc
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise FormatError(f"{path}: PLY header has no valid 'format' line")
    if any(len(set(e[3])) != len(e[3]) for e in elements) or len({e[0] for e in elements}) != len(
        elements
    ):
        raise FormatError(f"{path}: PLY header repeats an element or property name")
    vertex = next((e for e in elements if e[0] == "vertex"), None)
    if vertex is None or not {"x", "y", "z"} <= set(vertex[3]):
        raise FormatError(f"{path}: PLY has no vertex element with x, y, z")
    body = len(data) - nl - 1
    if fmt == "ascii":
        if sum(e[1] for e in elements) > data.count(b"\n", nl + 1) + 1:
            raise FormatError(f"{path}: truncated: the header declares more rows than held")
    elif sum(e[1] * max(e[2], 1) for e in elements) > body:
        raise FormatError(f"{path}: truncated: the header declares more data than held")
    return vertex[1]


def _read_open3d(path: Path) -> np.ndarray:
    if not path.is_file():
        raise FormatError(f"{path}: no such point-cloud file")
    if path.stat().st_size == 0:
        raise FormatError(f"{path}: empty file")
    o3d = import_open3d()  # a missing dependency is named first, whatever the file holds
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    check = _check_ply_header if path.suffix.lower() == ".ply" else _check_pcd_header
    declared = check(data, path)
    from ._native import native_stderr_captured

    with native_stderr_captured() as native:
        try:
            pcd = o3d.t.io.read_point_cloud(str(path))
        except Exception as exc:  # Open3D raises plain RuntimeError with its own text
            pcd, error = None, exc
    detail = " ".join(native[0].split()) if native and native[0] else ""
    if pcd is None:
        raise FormatError(f"{path}: Open3D cannot read it ({error})") from error
    if "positions" not in pcd.point:
        why = f": {detail}" if detail else ""
        raise FormatError(f"{path}: no points (corrupt or unsupported {path.suffix} file){why}")
    if pcd.point["positions"].shape[0] != declared:
        raise FormatError(
            f"{path}: Open3D read {pcd.point['positions'].shape[0]} points, the header declares "
            f"{declared} (corrupt file)"
        )
    try:
        # float64 values beyond float32 become Inf (and are dropped below): no warning for it.
        with np.errstate(over="ignore", invalid="ignore"):
            cols = [pcd.point["positions"].numpy().astype(np.float32).reshape(-1, 3)]
            for key in sorted(k for k in pcd.point if k != "positions"):
                a = pcd.point[key].numpy().astype(np.float32)
                cols.append(a.reshape(a.shape[0], -1))
            points = np.hstack(cols)
    except (UnicodeDecodeError, ValueError, TypeError, RuntimeError) as exc:
        # Field names that are not UTF-8, attributes whose length differs from the points'.
        raise FormatError(f"{path}: corrupt {path.suffix} file ({type(exc).__name__})") from exc
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
        those rows dropped (PCD/PLY rows Open3D drops are still dropped, with a warning).

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
