"""nuScenes files read without the devkit: LIDAR_TOP ``.pcd.bin``, radar ``.pcd`` and v1.0 tables.

The devkit pulls in ``opencv-python``, which conflicts with the headless build, so the few
formats needed are read here directly.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .atomic import atomic_path
from .kitti import read_velodyne_bin

__all__ = [
    "RADAR_FIELDS",
    "NuScenesTables",
    "RadarFilter",
    "quaternion_to_matrix",
    "read_lidar_pcd_bin",
    "read_radar_pcd",
    "write_radar_pcd",
]

#: nuScenes radar PCD v0.7 fields, their byte sizes and types (F float, I signed integer).
RADAR_FIELDS = (
    "x y z dyn_prop id rcs vx vy vx_comp vy_comp is_quality_valid ambig_state "
    "x_rms y_rms invalid_state pdh0 vx_rms vy_rms"
).split()
RADAR_SIZES = (4, 4, 4, 1, 2, 4, 4, 4, 4, 4, 1, 1, 1, 1, 1, 1, 1, 1)
RADAR_TYPES = tuple("F F F I I F F F F F I I I I I I I I".split())


def _pcd_dtype(fields, sizes, types) -> np.dtype:
    codes = {
        ("F", 4): "<f4",
        ("F", 8): "<f8",
        ("I", 1): "i1",
        ("I", 2): "<i2",
        ("I", 4): "<i4",
        ("U", 1): "u1",
        ("U", 2): "<u2",
        ("U", 4): "<u4",
    }
    try:
        return np.dtype([(f, codes[(t, s)]) for f, s, t in zip(fields, sizes, types, strict=True)])
    except KeyError as exc:
        raise FormatError(f"unsupported PCD field type/size {exc.args[0]}") from exc


RADAR_DTYPE = _pcd_dtype(RADAR_FIELDS, RADAR_SIZES, RADAR_TYPES)


def read_lidar_pcd_bin(path: str | os.PathLike, *, drop_non_finite_rows: bool = True) -> np.ndarray:
    """Read a nuScenes LIDAR_TOP ``.pcd.bin``: (N, 5) float32 x, y, z, intensity, ring (0..31)."""
    return read_velodyne_bin(path, n_columns=5, drop_non_finite_rows=drop_non_finite_rows)


@dataclass(frozen=True)
class RadarFilter:
    """The devkit's default radar point filters (``RadarPointCloud`` class defaults).

    Set a field to None to disable that filter; :meth:`none` disables all of them.
    """

    invalid_states: tuple[int, ...] | None = (0,)
    dynprop_states: tuple[int, ...] | None = tuple(range(7))
    ambig_states: tuple[int, ...] | None = (3,)

    @classmethod
    def none(cls) -> RadarFilter:
        return cls(None, None, None)

    def mask(self, rec: np.ndarray) -> np.ndarray:
        keep = np.ones(rec.shape[0], dtype=bool)
        for field, allowed in (
            ("invalid_state", self.invalid_states),
            ("dyn_prop", self.dynprop_states),
            ("ambig_state", self.ambig_states),
        ):
            if allowed is not None:
                keep &= np.isin(rec[field], np.asarray(allowed))
        return keep


def _parse_pcd_header(data: bytes, path: Path) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise FormatError(f"{path}: PCD header has no DATA line (truncated or not a PCD)")
        try:
            line = data[pos:end].decode("ascii").strip()
        except UnicodeDecodeError as exc:
            raise FormatError(f"{path}: not a PCD file (binary data in the header)") from exc
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, pos
        if len(header) > 32:
            raise FormatError(f"{path}: not a PCD file (no DATA line in the header)")


def read_radar_pcd(
    path: str | os.PathLike, *, filters: RadarFilter | None = RadarFilter()
) -> np.ndarray:
    """Read a nuScenes radar ``.pcd`` (PCD v0.7, binary, 18 fields).

    Parameters
    ----------
    path : path-like
    filters : RadarFilter or None
        The devkit's default filters (invalid_state == 0, dyn_prop 0..6, ambig_state == 3);
        None keeps every point.

    Returns
    -------
    (N, 18) float32
        Columns in :data:`RADAR_FIELDS` order (x, y, z in metres in the radar frame,
        velocities in m/s); rows with non-finite x, y or z are dropped.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such radar file") from exc
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    header, offset = _parse_pcd_header(data, path)
    try:
        fields = header["FIELDS"]
        dtype = _pcd_dtype(fields, [int(s) for s in header["SIZE"]], header["TYPE"])
        n = int(header["POINTS"][0]) if "POINTS" in header else int(header["WIDTH"][0])
    except (KeyError, ValueError, IndexError) as exc:
        raise FormatError(f"{path}: PCD header misses or garbles FIELDS/SIZE/TYPE/POINTS") from exc
    if header["DATA"] != ["binary"]:
        raise FormatError(
            f"{path}: PCD DATA '{' '.join(header['DATA'])}' unsupported (need binary)"
        )
    if fields != RADAR_FIELDS:
        raise FormatError(f"{path}: not a nuScenes radar PCD (fields {' '.join(fields)})")
    need = n * dtype.itemsize
    if n < 0 or len(data) - offset < need:
        raise FormatError(
            f"{path}: truncated: header declares {n} points ({need} bytes), "
            f"file holds {len(data) - offset}"
        )
    rec = np.frombuffer(data, dtype=dtype, count=n, offset=offset)
    if filters is not None:
        rec = rec[filters.mask(rec)]
    out = np.empty((rec.shape[0], len(RADAR_FIELDS)), dtype=np.float32)
    for i, f in enumerate(RADAR_FIELDS):
        out[:, i] = rec[f]
    return out[np.isfinite(out[:, :3]).all(axis=1)]


def write_radar_pcd(path: str | os.PathLike, points: np.ndarray, *, overwrite: bool = True) -> None:
    """Write (N, 18) radar points (:data:`RADAR_FIELDS` order) as a binary PCD v0.7, atomically.

    Integer fields are rounded; this is the writer the tests and the synthetic scenes use to
    make nuScenes-format radar files.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != len(RADAR_FIELDS):
        raise FormatError(f"radar points must be (N, {len(RADAR_FIELDS)}), got {points.shape}")
    rec = np.zeros(points.shape[0], dtype=RADAR_DTYPE)
    for i, f in enumerate(RADAR_FIELDS):
        col = points[:, i]
        if RADAR_DTYPE[f].kind == "i":
            col = np.rint(col)
            info = np.iinfo(RADAR_DTYPE[f])
            if col.size and (
                not np.isfinite(col).all() or col.min() < info.min or col.max() > info.max
            ):
                raise FormatError(
                    f"radar field '{f}' holds values outside {RADAR_DTYPE[f]} [{info.min}, {info.max}]"
                )
        rec[f] = col
    n = points.shape[0]
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(RADAR_FIELDS)}\nSIZE {' '.join(map(str, RADAR_SIZES))}\n"
        f"TYPE {' '.join(RADAR_TYPES)}\nCOUNT {' '.join('1' for _ in RADAR_FIELDS)}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(header.encode("ascii") + rec.tobytes())


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion given as nuScenes does: [w, x, y, z]."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _pose_matrix(record: dict) -> np.ndarray:
    try:
        q = np.asarray(record["rotation"], dtype=np.float64)
        t = np.asarray(record["translation"], dtype=np.float64)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise FormatError(f"nuScenes record {record.get('token')}: bad pose ({exc})") from exc
    norm = float(np.linalg.norm(q)) if q.shape == (4,) else 0.0
    if q.shape != (4,) or t.shape != (3,) or not (np.isfinite(norm) and norm > 0):
        raise FormatError(
            f"nuScenes record {record.get('token')}: rotation must be a non-zero quaternion "
            "[w, x, y, z] and translation [x, y, z]"
        )
    if not np.isfinite(t).all():
        raise FormatError(f"nuScenes record {record.get('token')}: non-finite translation")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(q)
    T[:3, 3] = t
    return T


#: Fields every record of a table must hold (with their JSON types), checked when loading.
_REQUIRED_FIELDS = {
    "sample": {"token": str, "timestamp": (int, float)},
    "sample_data": {
        "token": str,
        "sample_token": str,
        "calibrated_sensor_token": str,
        "ego_pose_token": str,
        "filename": str,
    },
    "calibrated_sensor": {"token": str, "sensor_token": str},
    "ego_pose": {"token": str},
    "sensor": {"token": str, "channel": str},
}
#: Optional fields, checked when present and not null.
_OPTIONAL_FIELDS = {
    "sample_data": {"prev": str, "is_key_frame": bool, "width": int, "height": int},
}


def _index_records(rows: list, name: str, path: Path) -> dict[str, dict]:
    """token -> record, after checking every record holds its table's fields."""
    required = _REQUIRED_FIELDS.get(name, {"token": str})
    optional = _OPTIONAL_FIELDS.get(name, {})
    out: dict[str, dict] = {}
    for i, r in enumerate(rows):
        if not isinstance(r, dict):
            raise FormatError(f"{path}: record {i} is not a JSON object")
        for key, typ in required.items():
            value = r.get(key)
            if not isinstance(value, typ) or isinstance(value, bool):
                raise FormatError(f"{path}: record {i} lacks '{key}' or it has the wrong type")
        for key, typ in optional.items():
            value = r.get(key)
            if value not in (None, "") and not isinstance(value, typ):
                raise FormatError(f"{path}: record {i}: '{key}' has the wrong type")
        out[r["token"]] = r
    return out


class NuScenesTables:
    """The v1.0 JSON tables needed for projection: sample, sample_data, calibrated_sensor,
    ego_pose, sensor. ``root/version/*.json`` is read directly; file names in ``sample_data``
    are relative to ``root``.
    """

    TABLES = ("sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor")
    #: Read when present: scene names (frame sequences) and descriptions (day / night).
    OPTIONAL_TABLES = ("scene", "log")

    def __init__(self, root: str | os.PathLike, version: str = "v1.0-mini"):
        self.root = Path(root)
        folder = self.root / version
        if not folder.is_dir():
            raise FormatError(f"{folder}: no such nuScenes table folder (check --version)")
        self._tables: dict[str, dict[str, dict]] = {}
        for name in self.TABLES:
            f = folder / f"{name}.json"
            try:
                rows = json.loads(f.read_text(encoding="utf-8"))
            except FileNotFoundError as exc:
                raise FormatError(f"{f}: missing nuScenes table") from exc
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise FormatError(f"{f}: not valid JSON ({exc})") from exc
            if not isinstance(rows, list):
                raise FormatError(f"{f}: expected a JSON list of records")
            self._tables[name] = _index_records(rows, name, f)
        for name in self.OPTIONAL_TABLES:
            f = folder / f"{name}.json"
            if not f.is_file():
                self._tables[name] = {}
                continue
            try:
                rows = json.loads(f.read_text(encoding="utf-8"))
            except (json.JSONDecodeError, UnicodeDecodeError, OSError) as exc:
                raise FormatError(f"{f}: not valid JSON ({exc})") from exc
            if not isinstance(rows, list):
                raise FormatError(f"{f}: expected a JSON list of records")
            self._tables[name] = _index_records(rows, name, f)
        self.table_files = tuple(
            folder / f"{n}.json"
            for n in (*self.TABLES, *self.OPTIONAL_TABLES)
            if (folder / f"{n}.json").is_file()
        )
        try:
            self._channel_of_cs = {
                tok: self._tables["sensor"][cs["sensor_token"]]["channel"]
                for tok, cs in self._tables["calibrated_sensor"].items()
            }
        except (KeyError, TypeError) as exc:
            raise FormatError(
                f"{folder}: calibrated_sensor refers to a sensor token missing from sensor.json "
                f"({exc})"
            ) from exc
        self._keyframe: dict[tuple[str, str], dict] = {}
        for sd in self._tables["sample_data"].values():
            if sd.get("is_key_frame", True):
                self._keyframe[(sd["sample_token"], self.channel(sd))] = sd

    def get(self, table: str, token: str) -> dict:
        try:
            return self._tables[table][token]
        except (KeyError, TypeError) as exc:
            raise FormatError(f"nuScenes table '{table}' has no token {token}") from exc

    def samples(self) -> list[dict]:
        """All samples, sorted by timestamp."""
        return sorted(self._tables["sample"].values(), key=lambda s: s["timestamp"])

    def scene(self, sample: dict) -> dict | None:
        """The scene record of a sample (None when scene.json is absent or lacks it)."""
        return self._tables["scene"].get(sample.get("scene_token"))

    def scene_name(self, sample: dict) -> str:
        """The sample's scene name (``scene-0061``); its scene token without scene.json."""
        scene = self.scene(sample)
        if scene is not None and scene.get("name"):
            return str(scene["name"])
        return str(sample.get("scene_token") or "")

    def channel(self, sample_data: dict) -> str:
        try:
            return self._channel_of_cs[sample_data["calibrated_sensor_token"]]
        except (KeyError, TypeError) as exc:
            raise FormatError(
                f"sample_data {sample_data.get('token')}: unknown calibrated_sensor_token"
            ) from exc

    def sample_data(self, sample_token: str, channel: str) -> dict:
        """The key-frame sample_data record of ``channel`` in a sample."""
        try:
            return self._keyframe[(sample_token, channel)]
        except KeyError as exc:
            raise FormatError(
                f"sample {sample_token} has no key frame for channel {channel}"
            ) from exc

    def sweeps(self, sample_data: dict, n: int) -> list[dict]:
        """``sample_data`` and up to ``n - 1`` previous sweeps of the same sensor (newest first)."""
        out = [sample_data]
        while len(out) < n and out[-1].get("prev"):
            out.append(self.get("sample_data", out[-1]["prev"]))
        return out

    def T_ego_from_sensor(self, sample_data: dict) -> np.ndarray:
        return _pose_matrix(self.get("calibrated_sensor", sample_data["calibrated_sensor_token"]))

    def T_global_from_ego(self, sample_data: dict) -> np.ndarray:
        return _pose_matrix(self.get("ego_pose", sample_data["ego_pose_token"]))

    def intrinsics(self, sample_data: dict) -> np.ndarray:
        cs = self.get("calibrated_sensor", sample_data["calibrated_sensor_token"])
        try:
            K = np.asarray(cs.get("camera_intrinsic") or [], dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            K = np.empty(0)
        if K.shape != (3, 3):
            raise FormatError(f"calibrated_sensor {cs['token']} has no 3x3 camera_intrinsic")
        return K

    def path(self, sample_data: dict) -> Path:
        return self.root / sample_data["filename"]
