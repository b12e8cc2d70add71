"""Pose files: KITTI odometry ``poses.txt``, one 4x4 per frame, ``times.txt``, KITTI raw oxts.

Formats
-------
- **KITTI odometry** ``poses.txt``: one line per frame, 12 numbers, the row-major top 3x4 of
  ``T_world_from_cam`` (the world is the first frame's camera, so line 0 is the identity).
- **Per-frame 4x4** ``<frame>.txt``: four lines of four numbers, the full homogeneous matrix
  (the last row must be ``0 0 0 1``).
- **times.txt** (KITTI odometry): one time stamp per line, seconds.
- **KITTI raw oxts** ``oxts/data/<n>.txt``: one line of 30 values (:data:`OXTS_FIELDS`, as in
  the drive's ``oxts/dataformat.txt``): 25 measurements then 5 integer status fields.
- **calib_imu_to_velo.txt** (KITTI raw): ``R`` (9 values, row-major) and ``T`` (3 values) of
  ``T_velo_from_imu``.

Writers use Python's shortest round-trip float format, so a written pose reads back bit for
bit. Readers are strict: a wrong value count, a non-number, a non-finite value, or a matrix
that is not a rigid transform (rotation not orthonormal within ``rigid_tol``, determinant not
+1, last row not ``0 0 0 1``) raises :class:`FormatError` with a one-line message naming the
file and line.

The oxts -> pose conversion is the standard one (KITTI devkit ``convertOxtsToPose``, METHODS.md
section 10): Mercator scale from the FIRST packet's latitude, ``t = (s R_e lon, s R_e
log(tan((90 + lat) / 2)), alt)``, ``R = Rz(yaw) Ry(pitch) Rx(roll)``, poses relative to the first
frame; a sensor's pose is ``T_world_from_imu @ inv(T_sensor_from_imu)``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import astuple, dataclass, fields
from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError
from .atomic import atomic_path

__all__ = [
    "EARTH_RADIUS_M",
    "MAX_POSE_FILE_BYTES",
    "OXTS_FIELDS",
    "OxtsPacket",
    "check_rigid",
    "oxts_poses",
    "read_imu_to_velo",
    "read_kitti_poses",
    "read_oxts_folder",
    "read_oxts_packet",
    "read_pose_matrix",
    "read_times",
    "sensor_poses",
    "write_kitti_poses",
    "write_oxts_packet",
    "write_pose_matrix",
    "write_times",
]

#: Equatorial Earth radius of the Mercator projection used by the KITTI devkit, metres.
EARTH_RADIUS_M = 6378137.0
#: Largest |R^T R - I| entry accepted as a rotation (KITTI's poses carry ~7 digits).
RIGID_TOL = 1e-4


def _fmt(value: float) -> str:
    # repr is the shortest string that reads back to the same double.
    return repr(float(value) + 0.0)  # + 0.0 turns -0.0 into 0.0


#: Largest pose, times or oxts file read (bytes): KITTI odometry's longest ``poses.txt``
#: (4,661 frames) is about 1 MB.
MAX_POSE_FILE_BYTES = 64 << 20


def _read_lines(path: Path, what: str) -> list[str]:
    """The lines of a text file: a regular file (a link to ``/dev/zero`` would be read
    forever) of at most :data:`MAX_POSE_FILE_BYTES`."""
    from .sidecar import read_regular_file

    try:
        data = read_regular_file(path, what=f"{what} file", max_bytes=MAX_POSE_FILE_BYTES)
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such {what} file") from exc
    try:
        text = data.decode("utf-8", errors="strict")
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not a text {what} file") from exc
    return text.splitlines()


def _numbers(path: Path, lineno: int, line: str, count: int, what: str) -> list[float]:
    tokens = line.split()
    if len(tokens) != count:
        raise FormatError(f"{path}:{lineno}: {len(tokens)} values, a {what} line holds {count}")
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise FormatError(f"{path}:{lineno}: {bad[:40]!r} is not a number") from None
    if not all(math.isfinite(v) for v in values):
        raise FormatError(f"{path}:{lineno}: non-finite value (NaN or Inf) in a {what}")
    return values


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _rigid_problem(T: np.ndarray, tol: float) -> str | None:
    """Why ``T`` (4, 4) is not a rigid transform, or None when it is."""
    if not np.all(np.isfinite(T)):
        return "non-finite values"
    if np.any(T[3] != (0.0, 0.0, 0.0, 1.0)):
        return "last row is not 0 0 0 1"
    R = T[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > tol:
        return f"rotation is not orthonormal (|R^T R - I| = {err:.2g} > {tol:g})"
    if np.linalg.det(R) < 0:
        return "rotation is a reflection (determinant -1)"
    return None


def check_rigid(T: np.ndarray, *, name: str = "pose", tol: float = RIGID_TOL) -> np.ndarray:
    """Return ``T`` as (4, 4) float64 after checking it is a finite rigid transform.

    Raises
    ------
    ParameterError
        Naming ``name`` when ``T`` is not (4, 4), not finite, or not rigid within ``tol``.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ParameterError(f"{name} must be a 4x4 matrix, got shape {T.shape}")
    problem = _rigid_problem(T, tol)
    if problem:
        raise ParameterError(f"{name} is not a rigid transform: {problem}")
    return T


def _as_pose_stack(poses, name: str) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ParameterError(f"{name} must be (N, 4, 4), got shape {P.shape}")
    for i, T in enumerate(P):
        problem = _rigid_problem(T, RIGID_TOL)
        if problem:
            raise ParameterError(f"{name}[{i}] is not a rigid transform: {problem}")
    return P


# -- KITTI odometry poses.txt ------------------------------------------------------------------
def read_kitti_poses(path: str | os.PathLike, *, rigid_tol: float = RIGID_TOL) -> np.ndarray:
    """Read a KITTI odometry ``poses.txt``.

    Parameters
    ----------
    path : path-like
        One line per frame of 12 numbers (row-major 3x4 of ``T_world_from_cam``).
    rigid_tol : float
        Largest accepted ``|R^T R - I|`` entry.

    Returns
    -------
    (N, 4, 4) float64
        ``T_world_from_cam`` per frame, translation in metres. Blank lines are not allowed
        (every line is a frame); an empty file gives ``N = 0``.

    Raises
    ------
    FormatError
        Wrong value count, non-number, non-finite or non-rigid pose (names the line).
    """
    path = Path(path)
    lines = _read_lines(path, "poses")
    out = np.zeros((len(lines), 4, 4))
    for i, line in enumerate(lines):
        out[i, :3, :] = np.array(_numbers(path, i + 1, line, 12, "pose")).reshape(3, 4)
        out[i, 3, 3] = 1.0
        problem = _rigid_problem(out[i], rigid_tol)
        if problem:
            raise FormatError(f"{path}:{i + 1}: not a rigid transform: {problem}")
    return out


def write_kitti_poses(path: str | os.PathLike, poses, *, overwrite: bool = True) -> None:
    """Write (N, 4, 4) rigid transforms as a KITTI odometry ``poses.txt`` (atomically).

    Raises
    ------
    ParameterError
        ``poses`` is not (N, 4, 4) or holds a non-rigid or non-finite matrix.
    """
    P = _as_pose_stack(poses, "poses")
    text = "".join(" ".join(_fmt(v) for v in T[:3].ravel()) + "\n" for T in P)
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")


# -- one 4x4 per frame -------------------------------------------------------------------------
def read_pose_matrix(path: str | os.PathLike, *, rigid_tol: float = RIGID_TOL) -> np.ndarray:
    """Read a ``<frame>.txt`` holding one 4x4 rigid transform (4 lines of 4 numbers).

    Returns
    -------
    (4, 4) float64
    """
    path = Path(path)
    lines = [ln for ln in _read_lines(path, "4x4 pose")]
    while lines and not lines[-1].strip():
        lines.pop()  # a trailing blank line is harmless
    if len(lines) != 4:
        raise FormatError(f"{path}: {len(lines)} lines, a 4x4 pose file holds 4")
    T = np.array([_numbers(path, i + 1, ln, 4, "4x4 pose row") for i, ln in enumerate(lines)])
    problem = _rigid_problem(T, rigid_tol)
    if problem:
        line = 4 if "last row" in problem else 1
        raise FormatError(f"{path}:{line}: not a rigid transform: {problem}")
    return T


def write_pose_matrix(path: str | os.PathLike, T, *, overwrite: bool = True) -> None:
    """Write one (4, 4) rigid transform as 4 lines of 4 numbers (atomically)."""
    T = check_rigid(T, name="pose")
    text = "".join(" ".join(_fmt(v) for v in row) + "\n" for row in T)
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")


# -- times.txt ---------------------------------------------------------------------------------
def read_times(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI odometry ``times.txt``: (N,) float64 seconds, non-decreasing."""
    path = Path(path)
    lines = _read_lines(path, "times")
    t = np.array([_numbers(path, i + 1, ln, 1, "time")[0] for i, ln in enumerate(lines)])
    back = np.nonzero(np.diff(t) < 0)[0]
    if back.size:
        raise FormatError(f"{path}:{back[0] + 2}: time goes backwards")
    return t


def write_times(path: str | os.PathLike, times, *, overwrite: bool = True) -> None:
    """Write (N,) seconds as ``times.txt`` (``%e`` as KITTI odometry, atomically)."""
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        raise ParameterError("times must be finite and non-decreasing")
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text("".join(f"{v:e}\n" for v in t), encoding="utf-8")


# -- KITTI raw oxts ----------------------------------------------------------------------------
@dataclass(frozen=True)
class OxtsPacket:
    """One KITTI raw oxts packet (``oxts/dataformat.txt``).

    Attributes
    ----------
    lat, lon : float, degrees
    alt : float, metres
    roll, pitch, yaw : float, radians
        Roll positive = left side up, pitch positive = front down, yaw 0 = east,
        counter-clockwise positive.
    vn, ve, vf, vl, vu : float, m/s
        Velocity north, east, forward, leftward, upward.
    ax, ay, az, af, al, au : float, m/s^2
    wx, wy, wz, wf, wl, wu : float, rad/s
    pos_accuracy : float, metres
    vel_accuracy : float, m/s
    navstat, numsats, posmode, velmode, orimode : int
        Navigation status, satellites, GPS position / velocity / orientation modes.
    """

    lat: float
    lon: float
    alt: float
    roll: float
    pitch: float
    yaw: float
    vn: float
    ve: float
    vf: float
    vl: float
    vu: float
    ax: float
    ay: float
    az: float
    af: float
    al: float
    au: float
    wx: float
    wy: float
    wz: float
    wf: float
    wl: float
    wu: float
    pos_accuracy: float
    vel_accuracy: float
    navstat: int
    numsats: int
    posmode: int
    velmode: int
    orimode: int


#: Field names of an oxts packet, in file order (30).
OXTS_FIELDS = tuple(f.name for f in fields(OxtsPacket))
_N_OXTS_FLOATS = 25


def read_oxts_packet(path: str | os.PathLike) -> OxtsPacket:
    """Read one KITTI raw oxts packet (``oxts/data/<n>.txt``: one line of 30 values).

    Raises
    ------
    FormatError
        Not exactly one line of 30 finite numbers, a status field that is not an integer,
        latitude outside [-90, 90] or longitude outside [-180, 180] degrees.
    """
    path = Path(path)
    lines = _read_lines(path, "oxts packet")
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) != 1:
        raise FormatError(f"{path}: {len(lines)} lines, an oxts packet is one line of 30 values")
    v = _numbers(path, 1, lines[0], len(OXTS_FIELDS), "oxts packet")
    status = v[_N_OXTS_FLOATS:]
    if any(s != int(s) for s in status):
        raise FormatError(f"{path}:1: the last 5 oxts fields (navstat .. orimode) must be integers")
    if not -90.0 <= v[0] <= 90.0 or not -180.0 <= v[1] <= 180.0:
        raise FormatError(f"{path}:1: latitude {v[0]} / longitude {v[1]} out of range")
    return OxtsPacket(*v[:_N_OXTS_FLOATS], *(int(s) for s in status))


def write_oxts_packet(path: str | os.PathLike, packet: OxtsPacket, *, overwrite: bool = True):
    """Write ``packet`` as a one-line oxts file (floats round-trip exactly, status as ints)."""
    values = astuple(packet)
    if not all(math.isfinite(float(x)) for x in values):
        raise ParameterError("oxts packet holds non-finite values")
    text = " ".join(
        [_fmt(x) for x in values[:_N_OXTS_FLOATS]] + [str(int(x)) for x in values[_N_OXTS_FLOATS:]]
    )
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text + "\n", encoding="utf-8")


def read_oxts_folder(folder: str | os.PathLike) -> list[OxtsPacket]:
    """Read every packet of a drive, in file-name order.

    ``folder`` is the drive folder (holding ``oxts/``), its ``oxts/`` or ``oxts/data/``.
    """
    folder = Path(folder)
    for data in (folder / "oxts" / "data", folder / "data", folder):
        files = sorted(data.glob("*.txt")) if data.is_dir() else []
        if files and data.name == "data":
            return [read_oxts_packet(f) for f in files]
    raise FormatError(f"{folder}: no oxts/data/*.txt packets")


def _rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


def oxts_poses(packets: Sequence[OxtsPacket], *, origin: str = "first_pose") -> np.ndarray:
    """IMU poses of a drive from its oxts packets (the standard KITTI conversion).

    Parameters
    ----------
    packets : sequence of OxtsPacket
        In time order.
    origin : {"first_pose", "first_position"}
        ``"first_pose"`` (KITTI devkit ``convertOxtsToPose``): ``inv(T_0) @ T_k``, so pose 0 is
        the identity (exactly) and the world is the first IMU frame. ``"first_position"`` (pykitti): only
        the first position is subtracted; the axes stay east, north, up.

    Returns
    -------
    (N, 4, 4) float64
        ``T_world_from_imu`` per packet, metres.
    """
    if origin not in ("first_pose", "first_position"):
        raise ParameterError(f"origin must be 'first_pose' or 'first_position', got {origin!r}")
    if len(packets) == 0:
        return np.zeros((0, 4, 4))
    scale = math.cos(math.radians(packets[0].lat))
    out = np.zeros((len(packets), 4, 4))
    for i, p in enumerate(packets):
        out[i, :3, :3] = _rotation_rpy(p.roll, p.pitch, p.yaw)
        out[i, 0, 3] = scale * EARTH_RADIUS_M * math.radians(p.lon)
        out[i, 1, 3] = scale * EARTH_RADIUS_M * math.log(math.tan(math.radians(90.0 + p.lat) / 2))
        out[i, 2, 3] = p.alt
        out[i, 3, 3] = 1.0
    if origin == "first_position":
        out[:, :3, 3] -= out[0, :3, 3].copy()
        return out
    rel = _inverse(out[0]) @ out
    rel[0] = np.eye(4)  # exactly, rather than up to the round-off of inv(T_0) @ T_0
    return rel


def _inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform (exact transpose of the rotation)."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -(T[:3, :3].T @ T[:3, 3])
    return out


def read_imu_to_velo(path: str | os.PathLike, *, rigid_tol: float = RIGID_TOL) -> np.ndarray:
    """Read KITTI raw ``calib_imu_to_velo.txt`` (``R``: 9 values, ``T``: 3 values).

    Returns
    -------
    (4, 4) float64
        ``T_velo_from_imu`` (maps IMU coordinates to Velodyne coordinates), metres.
    """
    path = Path(path)
    found: dict[str, tuple[int, list[float]]] = {}
    for i, line in enumerate(_read_lines(path, "IMU-to-Velodyne calibration")):
        key, sep, rest = line.partition(":")
        key = key.strip()
        if sep and key in ("R", "T"):
            if key in found:
                raise FormatError(f"{path}:{i + 1}: key '{key}' given twice")
            found[key] = (i + 1, _numbers(path, i + 1, rest, 9 if key == "R" else 3, key))
    for key in ("R", "T"):
        if key not in found:
            raise FormatError(f"{path}: missing key '{key}' (calib_imu_to_velo.txt holds R and T)")
    T = np.eye(4)
    T[:3, :3] = np.array(found["R"][1]).reshape(3, 3)
    T[:3, 3] = found["T"][1]
    problem = _rigid_problem(T, rigid_tol)
    if problem:
        raise FormatError(f"{path}:{found['R'][0]}: R is not a rotation: {problem}")
    return T


def sensor_poses(
    T_world_from_imu, T_sensor_from_imu, *, relative_to_first: bool = False
) -> np.ndarray:
    """Poses of a sensor rigidly mounted with the IMU: ``T_world_from_imu @ inv(T_sensor_from_imu)``.

    Parameters
    ----------
    T_world_from_imu : (N, 4, 4) float64
        From :func:`oxts_poses`.
    T_sensor_from_imu : (4, 4) float64
        E.g. ``T_velo_from_imu`` of :func:`read_imu_to_velo`.
    relative_to_first : bool
        Re-base so that the first sensor pose is the identity (``inv(P_0) @ P_k``, the world
        becomes the first frame's sensor).

    Returns
    -------
    (N, 4, 4) float64
        ``T_world_from_sensor``.
    """
    P = _as_pose_stack(T_world_from_imu, "T_world_from_imu")
    T = check_rigid(T_sensor_from_imu, name="T_sensor_from_imu")
    out = P @ _inverse(T)
    if relative_to_first and len(out):
        out = _inverse(out[0]) @ out
    return out
