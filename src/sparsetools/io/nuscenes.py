"""nuScenes files read without the devkit: LIDAR_TOP ``.pcd.bin``, radar ``.pcd`` and v1.0 tables.

The devkit pulls in ``opencv-python``, which conflicts with the headless build, so the few
formats needed are read here directly.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .atomic import atomic_path
from .kitti import read_velodyne_bin
from .pcd import parse_pcd_header, pcd_dtype
from .sidecar import check_field, read_json_document, read_regular_file

__all__ = [
    "MAX_RADAR_PCD_BYTES",
    "MAX_TABLE_BYTES",
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


RADAR_DTYPE = pcd_dtype(RADAR_FIELDS, RADAR_SIZES, RADAR_TYPES)


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


#: Largest radar ``.pcd`` read (bytes): a real one holds at most a few hundred points (~10 KiB).
MAX_RADAR_PCD_BYTES = 64 << 20


def _read_radar_bytes(path: Path) -> bytes:
    """The bytes of a radar file: a regular file (a link to ``/dev/zero`` would be read
    forever) of at most :data:`MAX_RADAR_PCD_BYTES`."""
    try:
        return read_regular_file(path, what="radar .pcd", max_bytes=MAX_RADAR_PCD_BYTES)
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such radar file") from exc


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
    data = _read_radar_bytes(path)
    header, offset = parse_pcd_header(data, path)
    try:
        fields = header["FIELDS"]
        dtype = pcd_dtype(fields, [int(s) for s in header["SIZE"]], header["TYPE"])
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        n = int(header["POINTS"][0]) if "POINTS" in header else width * height
    except (KeyError, ValueError, IndexError) as exc:
        raise FormatError(
            f"{path}: PCD header misses or garbles FIELDS/SIZE/TYPE/WIDTH/HEIGHT/POINTS"
        ) from exc
    if header["DATA"] != ["binary"]:
        raise FormatError(
            f"{path}: PCD DATA '{' '.join(header['DATA'])}' unsupported (need binary)"
        )
    if fields != RADAR_FIELDS:
        raise FormatError(f"{path}: not a nuScenes radar PCD (fields {' '.join(fields)})")
    if "COUNT" in header and header["COUNT"] != ["1"] * len(fields):
        raise FormatError(
            f"{path}: PCD COUNT '{' '.join(header['COUNT'])}' unsupported (a radar PCD holds one "
            "value per field)"
        )
    if n < 0 or width < 0 or height < 0 or n != width * height:
        raise FormatError(
            f"{path}: PCD header declares POINTS {n} but WIDTH {width} x HEIGHT {height} = "
            f"{width * height}: the point count is unknown (refused rather than read short)"
        )
    need = n * dtype.itemsize
    if len(data) - offset < need:
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


def _pose_matrix(record: dict, where: str) -> np.ndarray:
    """The 4x4 of a record's ``rotation`` (quaternion [w, x, y, z]) and ``translation``."""
    q = np.asarray(check_field(record.get("rotation"), "vector", where, "rotation", length=4),
                   dtype=np.float64)  # fmt: skip
    t = np.asarray(
        check_field(record.get("translation"), "vector", where, "translation", length=3),
        dtype=np.float64,
    )
    norm = float(np.linalg.norm(q))
    if not (np.isfinite(norm) and norm > 0):
        raise FormatError(f"{where}: 'rotation' must be a non-zero quaternion [w, x, y, z]")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(q)
    T[:3, 3] = t
    return T


#: Largest nuScenes table read (bytes): v1.0-trainval's largest tables (sample_data, ego_pose)
#: are well below it; a larger file (or a device, a link to ``/dev/zero``) is not a table.
MAX_TABLE_BYTES = 4 << 30

#: Fields every record of a table must hold, and their kinds (:func:`.sidecar.check_field`).
_REQUIRED_FIELDS = {
    "sample": {"token": "str", "timestamp": "number"},
    "sample_data": {
        "token": "str",
        "sample_token": "str",
        "calibrated_sensor_token": "str",
        "ego_pose_token": "str",
        "filename": "str",
    },
    "calibrated_sensor": {"token": "str", "sensor_token": "str"},
    "ego_pose": {"token": "str"},
    "sensor": {"token": "str", "channel": "str"},
}
#: Optional fields, checked when present and not null. Poses (``rotation``, ``translation``)
#: and ``camera_intrinsic`` are checked where they are used (ego_pose holds millions).
_OPTIONAL_FIELDS = {
    "sample": {"scene_token": "str", "prev": "str", "next": "str"},
    "sample_data": {
        "prev": "str",
        "next": "str",
        "is_key_frame": "bool",
        "width": "count",
        "height": "count",
        "timestamp": "number",
    },
    "ego_pose": {"timestamp": "number"},
    "scene": {"name": "str", "description": "str"},
}


def _record_where(path: Path, i: int, r: dict) -> str:
    tok = r.get("token")
    return f"{path}: record {i}" + (f" (token {tok})" if isinstance(tok, str) and tok else "")


def _index_records(rows: list, name: str, path: Path) -> dict[str, dict]:
    """token -> record, after checking every record's fields (kinds, unique tokens)."""
    required = _REQUIRED_FIELDS.get(name, {"token": "str"})
    optional = _OPTIONAL_FIELDS.get(name, {})
    out: dict[str, dict] = {}
    for i, r in enumerate(rows):
        if not isinstance(r, dict):
            raise FormatError(f"{path}: record {i} is not a JSON object")
        where = _record_where(path, i, r)
        for key, kind in required.items():
            if key not in r or r[key] is None:
                raise FormatError(f"{where} lacks '{key}'")
            check_field(r[key], kind, where, key)
        for key, kind in optional.items():
            if r.get(key) is not None:
                check_field(r[key], kind, where, key)
        token = r["token"]
        if not token:
            raise FormatError(f"{where}: 'token' is empty")
        if token in out:
            raise FormatError(f"{path}: token {token} is given twice (records are unique)")
        if name == "sample_data":
            _check_filename(r["filename"], where)
        out[token] = r
    return out


def _check_filename(name: str, where: str) -> None:
    """A sample_data file name is relative to the root (``samples/...``, ``sweeps/...``)."""
    parts = name.replace("\\", "/").split("/")
    if not name or name.startswith("/") or ".." in parts or "\x00" in name:
        raise FormatError(
            f"{where}: 'filename' {name[:60]!r} is not a path relative to the nuScenes root"
        )


def _read_table(path: Path, *, required: bool) -> list | None:
    """The records of one table file (None when an optional table is absent)."""
    try:
        rows = read_json_document(path, what="nuScenes table", max_bytes=MAX_TABLE_BYTES,
                                  max_depth=None)  # fmt: skip
    except FileNotFoundError as exc:
        if not required:
            return None
        raise FormatError(f"{path}: missing nuScenes table") from exc
    if not isinstance(rows, list):
        raise FormatError(f"{path}: expected a JSON list of records")
    return rows


class NuScenesTables:
    """The v1.0 JSON tables needed for projection: sample, sample_data, calibrated_sensor,
    ego_pose, sensor. ``root/version/*.json`` is read directly; file names in ``sample_data``
    are relative to ``root``.

    Every table is a regular file of at most :data:`MAX_TABLE_BYTES`; every field used is
    checked for its kind when the tables are loaded (poses and intrinsics when used), with a
    one-line :class:`FormatError` naming the file, the record and the field.
    """

    TABLES = ("sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor")
    #: Read when present: scene names (frame sequences) and descriptions (day / night).
    OPTIONAL_TABLES = ("scene", "log")

    def __init__(self, root: str | os.PathLike, version: str = "v1.0-mini"):
        self.root = Path(root)
        folder = self.root / version
        if not folder.is_dir():
            raise FormatError(f"{folder}: no such nuScenes table folder (check --nuscenes-version)")
        self._tables: dict[str, dict[str, dict]] = {}
        self._files: dict[str, Path] = {}
        for name in (*self.TABLES, *self.OPTIONAL_TABLES):
            f = folder / f"{name}.json"
            rows = _read_table(f, required=name in self.TABLES)
            self._tables[name] = {} if rows is None else _index_records(rows, name, f)
            if rows is not None:
                self._files[name] = f
        self.table_files = tuple(self._files.values())
        sensors = self._tables["sensor"]
        self._channel_of_cs = {}
        for tok, cs in self._tables["calibrated_sensor"].items():
            sensor = sensors.get(cs["sensor_token"])
            if sensor is None:
                raise FormatError(
                    f"{self._files['calibrated_sensor']}: calibrated_sensor {tok} refers to "
                    f"sensor {cs['sensor_token']}, which {self._files['sensor'].name} lacks"
                )
            self._channel_of_cs[tok] = sensor["channel"]
        self._keyframe: dict[tuple[str, str], dict] = {}
        for sd in self._tables["sample_data"].values():
            if sd.get("is_key_frame", True):
                key = (sd["sample_token"], self.channel(sd))
                other = self._keyframe.get(key)
                if other is not None:
                    raise FormatError(
                        f"{self._files['sample_data']}: sample {key[0]} has two {key[1]} key "
                        f"frames ({other['token']} and {sd['token']}): which one is meant is "
                        "unknown"
                    )
                self._keyframe[key] = sd

    def _where(self, table: str, record: dict) -> str:
        return f"{self._files.get(table, table)}: record token {record.get('token')}"

    def get(self, table: str, token: str) -> dict:
        try:
            return self._tables[table][token]
        except (KeyError, TypeError) as exc:
            where = self._files.get(table, f"nuScenes table '{table}'")
            raise FormatError(f"{where}: no record with token {token}") from exc

    def sensors(self) -> list[dict]:
        """The records of sensor.json (channel, modality)."""
        return list(self._tables["sensor"].values())

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
                f"{self._files.get('sample_data', 'sample_data')}: sample_data "
                f"{sample_data.get('token')} refers to calibrated_sensor "
                f"{sample_data.get('calibrated_sensor_token')}, which calibrated_sensor.json lacks"
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
        """``sample_data`` and up to ``n - 1`` previous sweeps of the same sensor (newest first).

        The chain follows ``prev``; it must stay on the sensor's channel, go back in time and
        never return to a sweep already taken (a cycle would merge the same sweeps again).
        """
        out = [sample_data]
        seen = {sample_data["token"]}
        channel = self.channel(sample_data)
        table = self._files.get("sample_data", "sample_data.json")
        while len(out) < n and out[-1].get("prev"):
            cur, prev = out[-1], out[-1]["prev"]
            if prev in seen:
                raise FormatError(
                    f"{table}: the 'prev' chain of {channel} sample_data {sample_data['token']} "
                    f"comes back to {prev} (a cycle): the same sweeps would be merged again"
                )
            sd = self.get("sample_data", prev)
            other = self.channel(sd)
            if other != channel:
                raise FormatError(
                    f"{table}: 'prev' of {channel} sample_data {cur['token']} is {prev}, a "
                    f"sweep of {other}: a chain of sweeps stays on one sensor"
                )
            t_cur, t_prev = cur.get("timestamp"), sd.get("timestamp")
            if t_cur is not None and t_prev is not None and not t_prev < t_cur:
                raise FormatError(
                    f"{table}: 'prev' of {channel} sample_data {cur['token']} is {prev}, which "
                    f"is not earlier (timestamp {t_prev} vs {t_cur})"
                )
            seen.add(prev)
            out.append(sd)
        return out

    def T_ego_from_sensor(self, sample_data: dict) -> np.ndarray:
        cs = self.get("calibrated_sensor", sample_data["calibrated_sensor_token"])
        return _pose_matrix(cs, self._where("calibrated_sensor", cs))

    def T_global_from_ego(self, sample_data: dict) -> np.ndarray:
        pose = self.get("ego_pose", sample_data["ego_pose_token"])
        return _pose_matrix(pose, self._where("ego_pose", pose))

    def intrinsics(self, sample_data: dict) -> np.ndarray:
        cs = self.get("calibrated_sensor", sample_data["calibrated_sensor_token"])
        K = cs.get("camera_intrinsic")
        ok = isinstance(K, list) and len(K) == 3 and all(isinstance(row, list) for row in K)
        if ok:
            try:
                flat = [check_field(row, "vector", "", "", length=3) for row in K]
            except FormatError:
                ok = False
        if not ok:
            raise FormatError(
                f"{self._where('calibrated_sensor', cs)}: 'camera_intrinsic' must be a 3x3 "
                "matrix of finite numbers (the sensor is not a camera?)"
            )
        return np.asarray(flat, dtype=np.float64)

    def path(self, sample_data: dict) -> Path:
        return self.root / sample_data["filename"]
