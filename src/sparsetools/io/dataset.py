"""The sparsetools training dataset on disk: Parquet manifest, PNG files, Parquet sparse points.

Layout (METHODS.md section 6; docs/dataset.md has the full schema table)::

    DATASET/
      manifest.parquet          one row per sample (schema: MANIFEST_SCHEMA)
      rgb/<id>.png|.jpg         camera images, copied byte for byte (or reflinked); with
                                --store reference not here: the manifest names each by a
                                root, a path in it and its identity (schema version 3)
      sparse/<id>.png           sparse depth, KITTI uint16 PNG (--sparse-format png|both)
      sparse/part-00000.parquet sparse depth as points, one row per frame (parquet|both)
      gt/<id>.png|.npy          ground-truth depth (optional)
      confidence/<id>.png|.npy  confidence map, e.g. jbf-expand's (optional)
      points/part-00000.parquet sensor points in the camera frame (--store-points; POINTS_SCHEMA)

The columns of :data:`OPTIONAL_SCHEMA` (camera of a rig, geometry, points) follow
:data:`MANIFEST_SCHEMA`'s, each written only when some row has a value.

Every path stored in the manifest is relative to ``DATASET``, uses ``/`` and may not be
absolute or contain ``..``: :func:`check_relative_path` rejects such a path when the manifest
is written and when it is read, and :func:`resolve_in_dataset` also refuses a path that a
symbolic link takes outside the dataset.

The schema version is stored in the Parquet key-value metadata under
``sparsetools.schema_version``; readers refuse a newer major version.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..errors import FormatError
from .dataset_refs import check_root_name, reference_unchanged, resolve_reference

__all__ = [
    "FULL_SCHEMA",
    "MANIFEST_NAME",
    "MANIFEST_ROW_GROUP",
    "MANIFEST_SCHEMA",
    "METADATA_INFO_KEY",
    "METADATA_VERSION_KEY",
    "OPTIONAL_SCHEMA",
    "PART_SCHEMA",
    "POINTS_DIR",
    "POINTS_SCHEMA",
    "REFERENCE_COLUMNS",
    "SCHEMA_VERSION",
    "SPARSE_DIR",
    "ManifestRow",
    "brief_error",
    "bytes_sha256",
    "check_relative_path",
    "check_root_name",
    "depth_to_points",
    "file_sha256",
    "points_sha256",
    "points_to_depth",
    "read_manifest",
    "reference_unchanged",
    "resolve_in_dataset",
    "resolve_reference",
]

#: Version of the manifest / part layout. Bump on any incompatible change.
SCHEMA_VERSION = 3
#: Columns added in schema version 2 (null when a version-1 manifest is read).
V2_COLUMNS = ("frame_index", "timestamp", "T_world_cam")
#: Columns added in schema version 3: the camera image referenced in place (``--store
#: reference``) by a named root, a path relative to it (``rgb_path``) and its identity.
#: Written only when a row references its image: a dataset that references nothing is
#: written as a version-2 manifest, exactly as before (older readers read it); read, a
#: manifest without them has them null.
REFERENCE_COLUMNS = ("rgb_root", "rgb_size", "rgb_mtime_ns")
#: Schema version of a manifest without :data:`REFERENCE_COLUMNS`.
BASE_SCHEMA_VERSION = 2
MANIFEST_NAME = "manifest.parquet"
#: Rows per row group of a written manifest: :class:`~.manifest_stream.ManifestBatches`
#: decodes one row group at a time. A manifest of fewer rows is one row group, byte for
#: byte as before.
MANIFEST_ROW_GROUP = 4096
SPARSE_DIR = "sparse"
METADATA_VERSION_KEY = b"sparsetools.schema_version"
METADATA_INFO_KEY = b"sparsetools.dataset"
#: uint16 pixel coordinates bound the image size of the Parquet sparse format.
#: Largest image side whose pixel coordinates fit uint16 (0..65535).
MAX_SIDE = 65536

MANIFEST_SCHEMA = pa.schema(
    [
        pa.field("id", pa.string(), nullable=False),
        pa.field("sequence", pa.string(), nullable=False),
        pa.field("frame", pa.string(), nullable=False),
        pa.field("split", pa.string()),
        pa.field("width", pa.int32(), nullable=False),
        pa.field("height", pa.int32(), nullable=False),
        pa.field("fx", pa.float64()),
        pa.field("fy", pa.float64()),
        pa.field("cx", pa.float64()),
        pa.field("cy", pa.float64()),
        pa.field("rgb_path", pa.string(), nullable=False),
        # version 3: the image referenced in place (REFERENCE_COLUMNS)
        pa.field("rgb_root", pa.string()),
        pa.field("rgb_size", pa.int64()),
        pa.field("rgb_mtime_ns", pa.int64()),
        pa.field("sparse_path", pa.string()),
        pa.field("sparse_parquet", pa.string()),
        pa.field("sparse_row", pa.int32()),
        pa.field("gt_path", pa.string()),
        pa.field("confidence_path", pa.string()),
        pa.field("n_sparse", pa.int64(), nullable=False),
        pa.field("density", pa.float64(), nullable=False),
        pa.field("n_gt", pa.int64()),
        pa.field("source", pa.string()),
        pa.field("rgb_sha256", pa.string(), nullable=False),
        pa.field("sparse_sha256", pa.string()),
        pa.field("sparse_points_sha256", pa.string()),
        pa.field("gt_sha256", pa.string()),
        pa.field("confidence_sha256", pa.string()),
        pa.field("generation_params", pa.string()),
        # version 2: order within the sequence (neighbours for video training), time, pose
        pa.field("frame_index", pa.int32()),
        pa.field("timestamp", pa.float64()),
        pa.field("T_world_cam", pa.list_(pa.float64())),
    ]
)

#: Optional columns (sparsetools 0.4, same schema version): a manifest holds one of them only
#: when some row has a value (so a dataset built without them is byte for byte as before),
#: and a manifest without them reads with them null. Cameras of a rig and each sample's
#: geometry (docs/dataset.md, "Geometry"); 4x4 transforms are row-major.
OPTIONAL_SCHEMA = pa.schema(
    [
        pa.field("camera", pa.string()),
        pa.field("K", pa.list_(pa.float64(), 9)),
        pa.field("T_cam_lidar", pa.list_(pa.float64(), 16)),
        pa.field("T_ego_cam", pa.list_(pa.float64(), 16)),
        pa.field("T_world_ego", pa.list_(pa.float64(), 16)),
        pa.field("baseline_m", pa.float64()),
        pa.field("points_parquet", pa.string()),
        pa.field("points_row", pa.int32()),
    ]
)
#: Every column a manifest may hold: :data:`MANIFEST_SCHEMA`, then :data:`OPTIONAL_SCHEMA`.
FULL_SCHEMA = pa.schema([*MANIFEST_SCHEMA, *OPTIONAL_SCHEMA])
#: The columns holding a tuple of floats (a matrix) in :class:`ManifestRow`.
MATRIX_COLUMNS = ("T_world_cam", "K", "T_cam_lidar", "T_ego_cam", "T_world_ego")


@dataclass(frozen=True, slots=True)
class ManifestRow:
    """One sample of the manifest: the fields of :data:`MANIFEST_SCHEMA`, in its order.

    Paths are relative to the dataset folder (``/``-separated); ``None`` is an empty
    (null) value. A row is immutable: a changed row is ``dataclasses.replace(row, ...)``.

    Attributes
    ----------
    id, sequence, frame : str
        Sample id (``<sequence>/<frame>`` of the input tree), its sequence and frame name.
    split : str, optional
    width, height : int
        Image size, pixels.
    fx, fy, cx, cy : float, optional
        Intrinsics, pixels.
    rgb_path : str
        Relative to the dataset; or, with ``rgb_root``, to that root.
    rgb_root : str, optional
        The image is referenced in place (``--store reference``, schema version 3): the name
        of its root (``rgb``, ``kitti``), whose path the manifest's build information
        records (``roots``) and :class:`~sparsetools.io.dataset_reader.DatasetReader` can be
        given again. None: the image is in the dataset.
    rgb_size, rgb_mtime_ns : int, optional
        The referenced image's identity when it was built: bytes and modification time (ns);
        with ``rgb_sha256`` for files up to :data:`sparsetools.io.provenance.HASH_LIMIT`
        bytes (:func:`reference_unchanged`).
    sparse_path : str, optional
        Sparse depth as a KITTI uint16 PNG.
    sparse_parquet : str, optional
        The ``sparse/part-*.parquet`` holding the frame's points, at row ``sparse_row``.
    sparse_row : int, optional
    gt_path, confidence_path : str, optional
    n_sparse : int
        Valid sparse depth pixels.
    density : float
        ``n_sparse / (width * height)``.
    n_gt : int, optional
        Valid ground-truth pixels.
    source : str, optional
        Sensor of the sparse depth (``lidar``, ``lidar-4beam``, ``radar``...).
    rgb_sha256, sparse_sha256, gt_sha256, confidence_sha256 : str, optional
        SHA-256 of the stored files (``rgb_sha256`` always).
    sparse_points_sha256 : str, optional
        :func:`points_sha256` of the Parquet points.
    generation_params : str, optional
        JSON: how the sample was made.
    frame_index : int, optional
        Rank in the sequence, frames in natural order (schema version 2).
    timestamp : float, optional
        Seconds (schema version 2).
    T_world_cam : tuple of 16 float, optional
        Row-major camera pose (schema version 2).
    camera : str, optional
        The camera of the rig (``image_03``, ``CAM_BACK``) in a dataset of several cameras.
    K : tuple of 9 float, optional
        Row-major 3x3 intrinsics of the stored image, pixels (rectified for KITTI).
    T_cam_lidar : tuple of 16 float, optional
        Row-major 4x4 rigid transform from the depth sensor's frame (LiDAR, radar) to this
        camera's frame, metres: ``x_cam = T_cam_lidar @ x_sensor``; with ``K`` it projects
        the sensor's points to this image.
    T_ego_cam, T_world_ego : tuple of 16 float, optional
        nuScenes: camera -> ego vehicle frame, and ego -> world (global) frame at the
        camera's timestamp, metres.
    baseline_m : float, optional
        KITTI stereo: distance from this camera to its stereo partner, metres.
    points_parquet : str, optional
        The ``points/part-*.parquet`` holding the sample's points in the camera frame
        (``--store-points``), at row ``points_row``.
    points_row : int, optional
    """

    id: str
    sequence: str
    frame: str
    split: str | None
    width: int
    height: int
    fx: float | None
    fy: float | None
    cx: float | None
    cy: float | None
    rgb_path: str
    rgb_root: str | None
    rgb_size: int | None
    rgb_mtime_ns: int | None
    sparse_path: str | None
    sparse_parquet: str | None
    sparse_row: int | None
    gt_path: str | None
    confidence_path: str | None
    n_sparse: int
    density: float
    n_gt: int | None
    source: str | None
    rgb_sha256: str
    sparse_sha256: str | None
    sparse_points_sha256: str | None
    gt_sha256: str | None
    confidence_sha256: str | None
    generation_params: str | None
    frame_index: int | None
    timestamp: float | None
    T_world_cam: tuple[float, ...] | None
    # -- optional columns (OPTIONAL_SCHEMA): one block, keep it last
    camera: str | None = None
    K: tuple[float, ...] | None = None
    T_cam_lidar: tuple[float, ...] | None = None
    T_ego_cam: tuple[float, ...] | None = None
    T_world_ego: tuple[float, ...] | None = None
    baseline_m: float | None = None
    points_parquet: str | None = None
    points_row: int | None = None

    def __getitem__(self, name: str):
        """``row["n_sparse"]``: a column by name, as the dict rows of sparsetools 0.2 read."""
        try:
            return getattr(self, name)
        except AttributeError:
            raise KeyError(name) from None

    def to_dict(self) -> dict:
        """The row as a dict in schema order (``T_world_cam`` as a list): JSON-ready."""
        out = {name: getattr(self, name) for name in _ROW_FIELDS}
        for name in MATRIX_COLUMNS:
            if out[name] is not None:
                out[name] = list(out[name])
        return out

    @classmethod
    def from_dict(cls, row: Mapping) -> ManifestRow:
        """A row from a mapping of column -> value (missing columns are empty, others ignored)."""
        values = {name: row.get(name) for name in _ROW_FIELDS}
        for name in MATRIX_COLUMNS:
            if values[name] is not None:
                values[name] = tuple(values[name])
        return cls(**values)

    @staticmethod
    def to_table(rows: Iterable[ManifestRow], *, every_column: bool = False) -> pa.Table:
        """The rows as an Arrow table of :data:`MANIFEST_SCHEMA` (columns, order, types), then
        the columns of :data:`OPTIONAL_SCHEMA` that some row fills (``every_column``: all of
        them, the table of :data:`FULL_SCHEMA` whatever the rows)."""
        rows = list(rows)
        fields = [*MANIFEST_SCHEMA]
        fields += [f for f in OPTIONAL_SCHEMA
                   if every_column or any(getattr(r, f.name) is not None for r in rows)]  # fmt: skip
        columns = [pa.array([getattr(r, f.name) for r in rows], type=f.type) for f in fields]
        return pa.Table.from_arrays(columns, schema=pa.schema(fields))

    @classmethod
    def from_table(cls, table: pa.Table) -> list[ManifestRow]:
        """The rows of a manifest table (optional columns it lacks are None; columns beyond
        :data:`FULL_SCHEMA` are ignored)."""
        n = table.num_rows
        names = [name for name in _ROW_FIELDS if name in table.column_names]
        columns = {name: table.column(name).to_pylist() for name in names}
        for name in MATRIX_COLUMNS:
            if name in columns:
                columns[name] = [None if m is None else tuple(m) for m in columns[name]]
        return [cls(**{name: columns[name][i] for name in names}) for i in range(n)]


#: ManifestRow's fields: MANIFEST_SCHEMA's names, in its order (a test holds them equal).
_ROW_FIELDS = tuple(f.name for f in dataclasses.fields(ManifestRow))

PART_SCHEMA = pa.schema(
    [
        pa.field("id", pa.string(), nullable=False),
        pa.field("u", pa.list_(pa.uint16()), nullable=False),
        pa.field("v", pa.list_(pa.uint16()), nullable=False),
        pa.field("depth", pa.list_(pa.float32()), nullable=False),
        pa.field("height", pa.int32(), nullable=False),
        pa.field("width", pa.int32(), nullable=False),
    ]
)

#: Folder of the points parts (``--store-points``).
POINTS_DIR = "points"
#: One row per sample: its sensor points in the camera frame (``T_cam_lidar @ x``), float64
#: metres, the points that land in the image; ``ring``: each point's laser (0 = highest),
#: null when the sensor has none (radar) or it is unknown.
POINTS_SCHEMA = pa.schema(
    [
        pa.field("id", pa.string(), nullable=False),
        pa.field("x", pa.list_(pa.float64()), nullable=False),
        pa.field("y", pa.list_(pa.float64()), nullable=False),
        pa.field("z", pa.list_(pa.float64()), nullable=False),
        pa.field("ring", pa.list_(pa.int16())),
        pa.field("height", pa.int32(), nullable=False),
        pa.field("width", pa.int32(), nullable=False),
    ]
)

PATH_COLUMNS = ("rgb_path", "sparse_path", "sparse_parquet", "gt_path", "confidence_path")
#: Path columns of :data:`OPTIONAL_SCHEMA`, checked like :data:`PATH_COLUMNS` when present.
OPTIONAL_PATH_COLUMNS = ("points_parquet",)


def brief_error(exc: BaseException) -> str:
    """An exception's text on one line (Arrow's messages span several)."""
    return " ".join(str(exc).split()) or type(exc).__name__


# -- paths -------------------------------------------------------------------------------------
def check_relative_path(rel: str, *, what: str = "path") -> str:
    """Validate a dataset-relative path and return it.

    A valid path is a non-empty ``/``-separated relative path whose components are neither
    empty, ``.`` nor ``..``, without backslashes, NUL bytes or a drive letter.

    Raises
    ------
    FormatError
        For anything that could point outside the dataset.
    """
    if not isinstance(rel, str) or not rel:
        raise FormatError(f"{what}: empty or non-string path in the dataset")
    bad = (
        rel.startswith("/")
        or "\\" in rel
        or "\x00" in rel
        or (len(rel) >= 2 and rel[1] == ":")
        or any(part in ("", ".", "..") for part in rel.split("/"))
    )
    if bad:
        raise FormatError(
            f"{what}: path {rel!r} is not a plain relative path inside the dataset "
            "(absolute paths and '..' are refused)"
        )
    return rel


def resolve_in_dataset(root: str | os.PathLike, rel: str, *, what: str = "path") -> Path:
    """``root / rel`` after :func:`check_relative_path`, refusing symlinks that leave ``root``."""
    check_relative_path(rel, what=what)
    root = Path(root)
    path = root.joinpath(*PurePosixPath(rel).parts)
    real_root = os.path.realpath(root)
    real = os.path.realpath(path)
    if real != real_root and not real.startswith(real_root.rstrip(os.sep) + os.sep):
        raise FormatError(f"{what}: {rel!r} resolves outside the dataset (symbolic link?)")
    return path


# -- hashing -----------------------------------------------------------------------------------
def bytes_sha256(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def file_sha256(path: str | os.PathLike, *, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes, read in chunks."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while block := f.read(chunk):
                h.update(block)
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    return h.hexdigest()


def points_sha256(u: np.ndarray, v: np.ndarray, depth: np.ndarray) -> str:
    """SHA-256 identifying a frame's sparse points.

    The digest is over the little-endian bytes of ``u`` (uint16), then ``v`` (uint16), then
    ``depth`` (float32), in stored order; it is what ``sparse_points_sha256`` holds.
    """
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(u, dtype="<u2").tobytes())
    h.update(np.ascontiguousarray(v, dtype="<u2").tobytes())
    h.update(np.ascontiguousarray(depth, dtype="<f4").tobytes())
    return h.hexdigest()


# -- depth maps <-> points -----------------------------------------------------------------------
def depth_to_points(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The valid pixels of a depth map as (u, v, depth) arrays.

    Parameters
    ----------
    depth : (H, W) float32, metres
        0 = no measurement. Must already be cleaned (no negative or non-finite values).

    Returns
    -------
    u, v : (N,) uint16
        Column and row of each valid pixel, row-major order.
    depth : (N,) float32
        The stored values, bit for bit.
    """
    from ..ops.projection import sparse_from_depth

    return sparse_from_depth(depth)


def points_to_depth(
    u: np.ndarray, v: np.ndarray, depth: np.ndarray, height: int, width: int
) -> np.ndarray:
    """Rebuild the (H, W) float32 depth map from (u, v, depth); 0 elsewhere.

    Raises :class:`FormatError` for mismatched lengths or pixels outside the image.
    """
    u = np.asarray(u)
    v = np.asarray(v)
    depth = np.asarray(depth, dtype=np.float32)
    if not (u.shape == v.shape == depth.shape) or u.ndim != 1:
        raise FormatError(
            f"sparse points: u, v, depth lengths differ ({u.size}, {v.size}, {depth.size})"
        )
    out = np.zeros((int(height), int(width)), dtype=np.float32)
    if u.size:
        if int(u.max()) >= width or int(v.max()) >= height:
            raise FormatError(f"sparse points outside the {width}x{height} image")
        out[v.astype(np.intp), u.astype(np.intp)] = depth
    return out


# -- manifest and parts --------------------------------------------------------------------------
def read_manifest(path: str | os.PathLike) -> tuple[pa.Table, dict]:
    """Read and validate ``manifest.parquet``.

    Returns
    -------
    table : pyarrow.Table
        With :data:`MANIFEST_SCHEMA` (extra columns of later minor versions are kept).
    info : dict
        ``schema_version`` plus the build information stored in the metadata.

    Raises
    ------
    FormatError
        Missing or unreadable file, no sparsetools metadata, a newer schema version,
        missing columns, duplicate ids, or a path that could leave the dataset.

    See Also
    --------
    sparsetools.io.manifest_stream.ManifestBatches : the same rows and checks, a batch at a
        time (memory flat in the rows).
    """
    path = _manifest_file(path)
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        raise _unreadable(path, exc) from exc
    version, info, meta = _manifest_header(table.schema, path)
    table = _conform_manifest(table, path, version=version, meta=meta)
    dup = _duplicate_ids(table.column("id").to_pylist())
    if dup:
        raise FormatError(_duplicates_message(path, dup))
    _check_manifest_values(table, path)
    _check_roots(info, path)
    return table, info


# -- the checks of a manifest, shared with manifest_stream.ManifestBatches ---------------------
def _manifest_file(path: str | os.PathLike) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such manifest (is this a sparsetools dataset folder?)")
    return path


def _unreadable(path: Path, exc: BaseException) -> FormatError:
    return FormatError(f"{path}: cannot read the manifest ({brief_error(exc)})")


def _added_columns(version: int) -> tuple[str, ...]:
    """Columns a manifest of ``version`` may lack, read as null."""
    return (*(V2_COLUMNS if version < 2 else ()), *REFERENCE_COLUMNS)


def _manifest_header(schema: pa.Schema, path: Path) -> tuple[int, dict, dict]:
    """(schema version, build information, key-value metadata) of a manifest's schema.

    Raises
    ------
    FormatError
        No or a newer schema version, missing columns, corrupt build information.
    """
    meta = schema.metadata or {}
    raw = meta.get(METADATA_VERSION_KEY)
    if raw is None:
        raise FormatError(f"{path}: no sparsetools schema version in the metadata")
    try:
        version = int(raw.decode())
    except ValueError as exc:
        raise FormatError(f"{path}: bad schema version {raw!r}") from exc
    if version > SCHEMA_VERSION:
        raise FormatError(
            f"{path}: schema version {version} was written by a newer sparsetools "
            f"(this one reads up to {SCHEMA_VERSION})"
        )
    present = {*schema.names, *_added_columns(version), *OPTIONAL_SCHEMA.names}
    missing = [f.name for f in MANIFEST_SCHEMA if f.name not in present]
    if missing:
        raise FormatError(f"{path}: manifest lacks column(s) {', '.join(missing)}")
    try:
        info = json.loads(meta.get(METADATA_INFO_KEY, b"{}").decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"{path}: corrupt dataset metadata ({brief_error(exc)})") from exc
    if not isinstance(info, dict):
        raise FormatError(f"{path}: corrupt dataset metadata (not a JSON object)")
    info["schema_version"] = version
    return version, info, meta


def _conform_manifest(table: pa.Table, path: Path, *, version: int, meta: dict) -> pa.Table:
    """A manifest table (or a batch of its rows) as :data:`FULL_SCHEMA`, then its extra
    columns: the columns its version or the writer left out added as nulls, the types cast,
    the values validated (Parquet does not check that strings are UTF-8)."""
    for name in _added_columns(version):
        if name not in table.column_names:
            typ = MANIFEST_SCHEMA.field(name).type
            table = table.append_column(name, pa.nulls(table.num_rows, type=typ))
    for f in OPTIONAL_SCHEMA:  # optional columns: absent when no row has a value
        if f.name not in table.column_names:
            table = table.append_column(f, pa.nulls(table.num_rows, type=f.type))
    for f in MANIFEST_SCHEMA:  # before the cast, which refuses them with a ValueError
        if not f.nullable and table.column(f.name).null_count:
            raise FormatError(f"{path}: column {f.name} holds empty (null) values")
    try:
        extra = [c for c in table.column_names if c not in FULL_SCHEMA.names]
        table = table.select([*FULL_SCHEMA.names, *extra])
        table = table.cast(
            pa.schema([*FULL_SCHEMA, *(table.schema.field(c) for c in extra)], metadata=meta),
        )
        table.validate(full=True)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
        raise FormatError(
            f"{path}: manifest columns have unexpected types ({brief_error(exc)})"
        ) from exc
    return table


def _duplicate_ids(ids: Iterable[str | None]) -> list[str]:
    """The ids that occur more than once, sorted (nulls are :func:`_check_manifest_values`'s)."""
    return sorted(i for i, n in Counter(ids).items() if n > 1 and i is not None)


def _duplicates_message(path: Path, dup: list[str]) -> str:
    return f"{path}: duplicate sample id(s) {', '.join(dup[:5])}"


def _check_roots(info: dict, path: Path) -> None:
    """Refuse build information whose ``roots`` is not a map of name -> path."""
    roots = info.get("roots", {})
    if not isinstance(roots, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in roots.items()
    ):
        raise FormatError(f"{path}: corrupt dataset metadata (roots is not a name -> path map)")


def _check_manifest_values(table: pa.Table, path: Path) -> None:
    """Refuse values a reader would trip on: impossible sizes, a Parquet reference without
    its row, a path that could leave the dataset, a bad root name (nulls in required columns:
    :func:`_conform_manifest`). Row by row: a batch of a manifest's rows is checked as the
    whole manifest is."""
    from .image import max_image_pixels

    w = table.column("width").to_numpy().astype(np.int64)
    h = table.column("height").to_numpy().astype(np.int64)
    if w.size and ((w <= 0).any() or (h <= 0).any() or (w * h > max_image_pixels()).any()):
        raise FormatError(f"{path}: a sample has an impossible image size (width, height)")
    part = table.column("sparse_parquet").is_valid().to_numpy(zero_copy_only=False)
    if (part & (np.maximum(w, h) > MAX_SIDE)).any():
        raise FormatError(f"{path}: a sample with Parquet points is over {MAX_SIDE} px on a side")
    row = table.column("sparse_row")
    row_ok = row.is_valid().to_numpy(zero_copy_only=False)
    rows = row.fill_null(0).to_numpy().astype(np.int64)
    if (part & (~row_ok | (rows < 0))).any():
        raise FormatError(f"{path}: a sample refers to a sparse part without a valid sparse_row")
    if (table.column("n_sparse").to_numpy() < 0).any():
        raise FormatError(f"{path}: a sample has a negative n_sparse")
    ref = table.column("rgb_root").is_valid().to_numpy(zero_copy_only=False)
    for col in ("rgb_size", "rgb_mtime_ns"):
        c = table.column(col)
        if (ref & ~c.is_valid().to_numpy(zero_copy_only=False)).any():
            raise FormatError(f"{path}: a referenced image (rgb_root) has no {col}")
    if (table.column("rgb_size").fill_null(0).to_numpy() < 0).any():
        raise FormatError(f"{path}: a sample has a negative rgb_size")
    for col in (*PATH_COLUMNS, *OPTIONAL_PATH_COLUMNS):
        for rel in table.column(col).to_pylist():
            if rel is not None:
                check_relative_path(rel, what=f"{path.name} column {col}")
    for name in table.column("rgb_root").to_pylist():
        if name is not None:
            check_root_name(name, what=f"{path.name} column rgb_root")
