"""The per-frame work of ``dataset build``.

Each frame is copied (or reflinked) into the dataset, decoded to check sizes, hashed, and its
manifest row (:class:`~sparsetools.io.dataset.ManifestRow`) and sparse points staged: its
staging record appended to a pack in ``DATASET/.staging/`` (:mod:`.staged`), last (an entry
means a complete frame).
:class:`sparsetools.pipeline.dataset.build.DatasetJob` runs :func:`stage_frame` per frame,
then :mod:`.merge` merges the staged records into the manifest.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import FormatError
from ...io.atomic import atomic_path, atomic_write_bytes
from ...io.dataset import (
    MAX_SIDE,
    SPARSE_DIR,
    ManifestRow,
    bytes_sha256,
    depth_to_points,
    points_sha256,
)
from ...io.depth_files import decode_confidence_bytes, decode_depth_bytes
from ..core import FrameStats
from .settings import BuildSettings
from .staged import append_staged, encode_record

__all__ = [
    "STAGES",
    "STAGING",
    "DatasetFrameInput",
    "DatasetFrameStats",
    "InputFolders",
    "camera_points",
    "sample_files",
    "stage_frame",
    "staging_folder",
]

STAGING = ".staging"
#: A frame's staged points (``--store-points``): an .npy of (N, 4) float64, x y z ring.
POINTS_SUFFIX = ".pts.npy"
#: Points nearer than this (camera z, metres) are not stored: ``project``'s min_depth.
POINTS_MIN_DEPTH = 0.1


# -- per-frame job -----------------------------------------------------------------------------------
def _read_bytes(path: str, what: str) -> bytes:
    """A frame's input file (:func:`sparsetools.io.npy.read_map_bytes`: a regular file of
    bounded size; a ``.npy`` header checked, against the pixel limit too, before the read)."""
    from ...io.npy import read_map_bytes

    data = read_map_bytes(path, what=what)
    if not data:
        raise FormatError(f"{path}: empty {what} file")
    return data


def _decode_rgb_size(data: bytes, source: str) -> tuple[int, int]:
    """Decode an 8-bit colour image (to prove it is readable); return (width, height)."""
    from ...io.image import decode_image_bytes

    img = decode_image_bytes(data, source=source)
    if img.dtype != np.uint8:
        raise FormatError(f"{source}: {img.dtype} image, expected 8-bit RGB (is this a depth map?)")
    if img.ndim == 3 and img.shape[2] not in (3, 4):
        raise FormatError(f"{source}: {img.shape[2]}-channel image, expected RGB")
    return int(img.shape[1]), int(img.shape[0])


#: Linux ioctl that makes ``dst`` a copy-on-write clone of ``src`` (btrfs, XFS, ...).
_FICLONE = 0x40049409


def _clone(src: str, dst: Path) -> bool:
    """Make ``dst`` a reflink (copy-on-write clone) of ``src``; False where not supported."""
    import fcntl

    try:
        with open(src, "rb") as fs, open(dst, "wb") as fd:
            fcntl.ioctl(fd.fileno(), _FICLONE, fs.fileno())
        return True
    except OSError:
        return False


def _store(data: bytes, sha256: str, src: str | None, dst: Path, link: bool) -> bool:
    """Write ``data`` (hex SHA-256 ``sha256``) to ``dst`` atomically; with ``link``, as a
    reflink of ``src`` where the file system can (returns True), else as a copy.

    A reflink shares the data blocks copy-on-write but is a file of its own (own inode,
    permissions, times): nothing done to the dataset can change the user's file, unlike a
    hard link, and nothing points outside the dataset, unlike a symbolic link.
    """
    if link and src is not None:
        with atomic_path(dst) as tmp:
            if _clone(os.path.realpath(src), tmp):
                return True
            tmp.write_bytes(data)
        return False
    atomic_write_bytes(dst, data, sha256=sha256)
    return False


def _clean_points(u, v, d, h: int, w: int, source: str) -> np.ndarray:
    u = np.asarray(u)
    v = np.asarray(v)
    d = np.asarray(d, dtype=np.float32)
    if not (u.shape == v.shape == d.shape):
        raise FormatError(f"{source}: u, v, depth lengths differ")
    keep = np.isfinite(d) & (d > 0)
    u, v, d = u[keep], v[keep], d[keep]
    if u.size and (u.min() < 0 or v.min() < 0 or u.max() >= w or v.max() >= h):
        raise FormatError(f"{source}: sparse points outside the {w}x{h} image")
    flat = v.astype(np.int64) * w + u.astype(np.int64)
    if np.unique(flat).size != flat.size:
        raise FormatError(f"{source}: two sparse points in the same pixel")
    depth = np.zeros((h, w), dtype=np.float32)
    depth[v.astype(np.intp), u.astype(np.intp)] = d
    return depth


def _image_calibration(calib_path: str, image: str, w: int, h: int, camera: int = 2):
    """The frame's calibration, checked against its ``w`` x ``h`` image as every command checks
    it (:func:`sparsetools.io.calib.frame_calibration`): a calibration that holds its image
    size must hold this one; one without a size must have its principal point near the
    image's centre. Either way a calibration of other images is refused, never used."""
    from ...errors import CalibrationError
    from ...io.calib import check_principal_point, load_calibration

    calib = load_calibration(calib_path, camera=camera)
    if calib.width is not None and calib.height is not None:
        if (calib.width, calib.height) != (w, h):
            raise CalibrationError(
                f"{calib_path}: calibration is for {calib.width}x{calib.height}, "
                f"the image {image} is {w}x{h}"
            )
        # A calibration of this size may be of a crop (the routes write them so): its
        # principal point need not be near the centre.
        return calib
    calib = calib.with_size(w, h)
    check_principal_point(calib, given_by=f"image {image}")
    return calib


def _flat(M: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(M, dtype=np.float64).reshape(-1))


def camera_frame_transform(calib) -> tuple[np.ndarray, np.ndarray]:
    """``K`` and ``T_cam_lidar`` of a calibration: ``K @ (T_cam_lidar @ x)[:3]`` is its
    projection ``calib.projection @ x``.

    A KITTI rectified ``P = [K | p]`` carries the camera's offset from the reference camera in
    its last column; it goes into the transform, ``T_cam_lidar = [I | K^-1 p] @
    T_cam_from_sensor`` (the frame of the rectified camera itself, monodepth2's), so that a
    plain pinhole ``K`` projects the points.

    Returns
    -------
    K : (3, 3) float64, pixels
    T_cam_lidar : (4, 4) float64, metres
    """
    T = np.asarray(calib.T_cam_from_sensor, dtype=np.float64)
    if calib.P is None:
        return np.asarray(calib.K, dtype=np.float64), T
    K = np.asarray(calib.P[:, :3], dtype=np.float64)
    shift = np.eye(4)
    shift[:3, 3] = np.linalg.solve(K, calib.P[:, 3])
    return K, shift @ T


def calibration_geometry(calib, calib_path: str, camera: int) -> dict:
    """The geometry columns a calibration gives (``K``, ``T_cam_lidar``; ``baseline_m`` for
    a KITTI raw date folder holding both colour cameras' ``P_rect``)."""
    from ...errors import CalibrationError
    from ...io.calib import read_kitti_stereo_rig

    K, T = camera_frame_transform(calib)
    out = {"K": _flat(K), "T_cam_lidar": _flat(T)}
    folder = Path(calib_path)
    if calib.P is not None and (folder / "calib_cam_to_cam.txt").is_file() and camera in (2, 3):
        try:
            out["baseline_m"] = float(read_kitti_stereo_rig(folder)[1])
        except CalibrationError:  # no P_rect_03 (or not a pair): no stereo partner
            pass
    return out


def camera_points(cloud_path: str, calib, *, sweeps=()) -> np.ndarray:
    """A scan's points that land in the calibration's image, in the camera frame, with rings.

    Parameters
    ----------
    cloud_path : str
        The key sweep (KITTI ``.bin``, nuScenes ``.pcd.bin`` or radar ``.pcd``).
    calib : Calibration
        The stored image's calibration (sensor -> camera, sized).
    sweeps : tuple of Sweep
        Earlier sweeps merged as ``project`` merges them
        (:func:`sparsetools.pipeline.project.load_frame_points`).

    Returns
    -------
    (N, 4) float64
        x, y, z in the frame of :func:`camera_frame_transform` (``T_cam_lidar @ x``, metres,
        computed as :func:`sparsetools.ops.projection.transform_points`), then the ring:
        KITTI ``.bin``: :func:`sparsetools.ops.rings.recover_rings`, 64 lasers, scan order
        (elevation, with a warning, for a scan that is not in scan order); nuScenes
        ``.pcd.bin``: its ring column (32 lasers); -1 where there is none (radar) or it
        cannot be recovered (an empty scan). A point lands when ``z > 0.1`` m and ``K``
        puts it inside the image (``project``'s rule).
    """
    from ...errors import ParameterError
    from ...io.pointcloud import cloud_kind
    from ...ops.projection import transform_points
    from ...ops.rings import recover_rings
    from ..project import load_frame_points

    pts = load_frame_points(cloud_path, sweeps)
    K, T = camera_frame_transform(calib)
    xyz = transform_points(pts, T)
    kind = cloud_kind(cloud_path)
    ring = np.full(len(pts), -1.0)
    try:
        if kind == "kitti-bin":
            ring = recover_rings(pts, n_lasers=64, method="scan-order").astype(np.float64)
        elif kind == "nuscenes-bin":
            ring = recover_rings(pts, n_lasers=32, method="column", column=4).astype(np.float64)
    except ParameterError:
        pass
    w, h = calib.size
    with np.errstate(all="ignore"):
        z = xyz[:, 2]
        u = np.rint((K[0, 0] * xyz[:, 0] + K[0, 1] * xyz[:, 1] + K[0, 2] * z) / z)
        v = np.rint((K[1, 1] * xyz[:, 1] + K[1, 2] * z) / z)
        keep = (z > POINTS_MIN_DEPTH) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return np.column_stack([xyz[keep], ring[keep]])


def _npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


@dataclass(frozen=True, slots=True)
class InputFolders:
    """The folders (or files) a build's inputs were given as, which each frame's
    ``generation_params["inputs"]`` names its files relative to; one object shared by the
    frames of a build (a frame holds a reference, not its own strings).

    Attributes
    ----------
    rgb, sparse, gt, confidence, calib : str, optional
        As given (``--rgb`` ...).
    dirs : frozenset of str
        The kinds given as a folder (looked at once, when the inputs are found).
    """

    rgb: str | None = None
    sparse: str | None = None
    gt: str | None = None
    confidence: str | None = None
    calib: str | None = None
    dirs: frozenset[str] = frozenset()

    @classmethod
    def of(cls, **given) -> InputFolders:
        paths = {k: None if v is None else os.fspath(v) for k, v in given.items()}
        dirs = frozenset(k for k, v in paths.items() if v is not None and os.path.isdir(v))
        return cls(**paths, dirs=dirs)

    def relative(self, path: str, kind: str) -> str:
        """``path`` relative to the folder of ``kind`` (POSIX); the name of what was given
        when it is a file, the file's own name when it is not inside."""
        folder = getattr(self, kind)
        if kind not in self.dirs:
            return Path(folder).name
        try:
            return Path(path).relative_to(folder).as_posix()
        except ValueError:
            return Path(path).name

    def describe(self, x: DatasetFrameInput) -> tuple[tuple[str, str], ...]:
        """Where each input of frame ``x`` came from: (kind, relative path), sorted."""
        desc = {"rgb": self.relative(x.rgb, "rgb")}
        if x.sparse_table is not None:
            desc["sparse"] = Path(x.sparse_table).name
        elif x.sparse is not None:
            desc["sparse"] = self.relative(x.sparse, "sparse")
        for kind in ("gt", "confidence"):
            if getattr(x, kind) is not None:
                desc[kind] = self.relative(getattr(x, kind), kind)
        if x.calib is not None:
            desc["calib"] = self.relative(x.calib, "calib") if self.calib else Path(x.calib).name
        return tuple(sorted(desc.items()))


@dataclass(frozen=True, slots=True)
class DatasetFrameInput:
    """One frame of a build: where its files are and what the manifest row will say.

    Attributes
    ----------
    id, sequence, frame : str
        Sample id (``<sequence>/<frame>`` of the input tree), its sequence and frame name.
    rgb : str
    sparse : str, optional
        Sparse depth map file (PNG / .npy), or ``sparse_points`` (u, v, depth, h, w) read
        from the points table ``sparse_table``.
    gt, confidence, calib : str, optional
    timestamp : float, optional
    pose : tuple of 16 floats, optional
        Row-major ``T_world_cam``.
    split : str, optional
        The split the inputs give the frame (a split file listing it, or the tree it is in);
        None: assigned by sequence when the frames are merged.
    folders : InputFolders, optional
        What the inputs were given as: ``inputs_desc``, where each input came from (for
        ``generation_params``), is made from it when the frame is staged.
    sample_params : tuple of (name, value)
        What this frame's generation did that differs per frame (a nuScenes sample's radar
        sweeps actually merged), stored in ``generation_params`` under ``"sample"``; the
        run's own ``params`` are the same for every frame.
    camera : str, optional
        The rig's camera (``image_03``, ``CAM_BACK``) in a dataset of several cameras.
    calib_camera : int
        KITTI camera index the calibration is read for (a raw date folder holds all four).
    T_ego_cam, T_world_ego : tuple of 16 floats, optional
        Row-major camera -> ego and ego -> world transforms (nuScenes), stored with
        ``--store-geometry``.
    cloud : str, optional
        The sensor's point cloud (KITTI ``velodyne_points/data/<frame>.bin``, a nuScenes key
        sweep), stored in the camera frame with ``--store-points``.
    sweeps : tuple of Sweep
        The earlier sweeps merged into ``cloud`` (nuScenes), as ``project`` merges them.
    """

    id: str
    sequence: str
    frame: str
    rgb: str
    sparse: str | None = None
    sparse_points: tuple | None = None
    sparse_table: str | None = None
    gt: str | None = None
    confidence: str | None = None
    calib: str | None = None
    timestamp: float | None = None
    pose: tuple[float, ...] | None = None
    split: str | None = None
    folders: InputFolders | None = None
    sample_params: tuple[tuple[str, object], ...] = ()
    # -- cameras of a rig and geometry (one block, keep it last)
    camera: str | None = None
    calib_camera: int = 2
    T_ego_cam: tuple[float, ...] | None = None
    T_world_ego: tuple[float, ...] | None = None
    cloud: str | None = None
    sweeps: tuple = ()

    @property
    def inputs_desc(self) -> tuple[tuple[str, str], ...]:
        """Where each input came from: (kind, path relative to what was given), sorted."""
        return () if self.folders is None else self.folders.describe(self)

    @property
    def sources(self) -> tuple[Path, ...]:
        """The input files whose identity decides whether the frame is up to date."""
        files = (self.rgb, self.sparse_table or self.sparse, self.gt, self.confidence, self.calib,
                 self.cloud, *(sw.path for sw in self.sweeps))  # fmt: skip
        return tuple(Path(f) for f in files if f is not None)


@dataclass(frozen=True)
class DatasetFrameStats(FrameStats):
    """What staging one frame did: its sparse points, files linked (reflinked) instead of
    copied, and the seconds spent per stage (timings: never recorded)."""

    n_sparse: int
    linked: int = 0
    t_read: float = 0.0
    t_decode: float = 0.0
    t_encode: float = 0.0
    t_hash: float = 0.0
    t_write: float = 0.0
    t_stage: float = 0.0


#: The per-frame stages of :class:`DatasetFrameStats`, in the order a frame runs them.
STAGES = ("t_read", "t_decode", "t_encode", "t_hash", "t_write", "t_stage")


def sample_files(
    x: DatasetFrameInput, sparse_format: str, store: str = "copy", *, store_points: bool = False
) -> dict[str, str]:
    """Dataset-relative path of every file a frame writes, by role; with ``store_points``
    its points (``points``, staged: merged into a part); at the end ``staged``, the staging
    record's name as earlier versions wrote it (a file per frame; the record now goes into
    a pack of that folder, :mod:`.staged`: the role stays, so that their folders resume). With ``store`` ``reference`` the
    camera image is not written (it is referenced in place)."""
    files = {} if store == "reference" else {"rgb": f"rgb/{x.id}{Path(x.rgb).suffix.lower()}"}
    if sparse_format in ("png", "both"):
        files["sparse"] = f"{SPARSE_DIR}/{x.id}.png"
    for kind in ("gt", "confidence"):
        src = getattr(x, kind)
        if src is not None:
            files[kind] = f"{kind}/{x.id}{Path(src).suffix.lower()}"
    if store_points and x.cloud is not None:
        files["points"] = f"{STAGING}/{x.id}{POINTS_SUFFIX}"
    files["staged"] = f"{STAGING}/{x.id}.rec"
    return files


def _reference(path: str, rgb_root: tuple[str, str] | None) -> tuple[str, str, os.stat_result]:
    """(root name, path relative to the root, stat) of an image referenced in place; refused
    when it is not inside the root (a link leaving it included)."""
    from ...io.dataset import resolve_reference

    if rgb_root is None:
        raise FormatError("--store reference: the build names no root of the camera images")
    name, root = rgb_root
    rel = os.path.relpath(os.path.abspath(path), os.path.abspath(root))
    rel = Path(rel).as_posix()
    try:
        full = resolve_reference(root, rel, name=name)
    except FormatError as exc:
        raise FormatError(
            f"{path}: cannot be referenced in place ({exc}); use --store copy"
        ) from None
    try:
        st = os.stat(full)
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    return name, rel, st


def stage_frame(
    x: DatasetFrameInput,
    outputs: Mapping[str, Path],
    settings: BuildSettings,
    rgb_root: tuple[str, str] | None = None,
) -> DatasetFrameStats:
    """Copy (or reflink) one frame's files to ``outputs`` (from :func:`sample_files`) after
    decoding every input to check it, and stage its manifest row and points.

    With ``settings.store == "reference"`` the camera image stays where it is: the row
    records ``rgb_root`` (the name of ``rgb_root = (name, path)``), ``rgb_path`` relative to
    it and the file's identity (``rgb_size``, ``rgb_mtime_ns``, ``rgb_sha256``)."""
    fid = x.id
    t = dict.fromkeys(STAGES, 0.0)
    clock = time.perf_counter

    def timed(stage, fn, *args, **kwargs):
        t0 = clock()
        out = fn(*args, **kwargs)
        t[stage] += clock() - t0
        return out

    rel = sample_files(
        x, settings.sparse_format, settings.store, store_points=settings.store_points
    )
    desc = dict(x.inputs_desc)

    # RGB: stored byte for byte with its own suffix, or referenced where it is.
    ref = _reference(x.rgb, rgb_root) if settings.store == "reference" else None
    data = timed("t_read", _read_bytes, x.rgb, "image")
    if ref is not None and len(data) != ref[2].st_size:
        raise FormatError(f"{x.rgb}: the file changed while it was read")
    w, h = timed("t_decode", _decode_rgb_size, data, x.rgb)
    rgb_sha256 = timed("t_hash", bytes_sha256, data)
    # Files are written only once every input of the frame has been decoded and checked, so
    # a bad frame leaves nothing behind in the dataset.
    writes = [] if ref is not None else [(data, rgb_sha256, x.rgb, outputs["rgb"])]

    # Sparse depth: the float32 map as decoded, then PNG and/or points.
    fmt = settings.sparse_format
    params = {"sparse_format": fmt, "inputs": desc}
    sparse_png = None
    if x.sparse is not None:
        src = x.sparse
        sdata = timed("t_read", _read_bytes, src, "sparse depth")
        depth = timed("t_decode", decode_depth_bytes, sdata, Path(src).suffix, source=src)
        if Path(src).suffix.lower() == ".png":
            sparse_png = sdata
    else:
        u, v, d, ph, pw = x.sparse_points
        if (ph is not None and ph != h) or (pw is not None and pw != w):
            raise FormatError(f"frame {fid}: sparse points are for {pw}x{ph}, the image is {w}x{h}")
        src = "sparse points table"
        depth = timed("t_decode", _clean_points, u, v, d, h, w, f"frame {fid}")
    if depth.shape != (h, w):
        raise FormatError(
            f"{src}: sparse depth is {depth.shape[1]}x{depth.shape[0]}, the image {x.rgb} is {w}x{h}"
        )
    n_sparse = int(np.count_nonzero(depth))
    sparse_sha256 = None
    if "sparse" in rel:
        if sparse_png is None:
            from ...io.image import encode_depth_png

            sparse_png, clipped = timed("t_encode", encode_depth_png, depth)
            params["png_clipped"] = int(clipped)
            png_src = None
        else:
            png_src = src
        sparse_sha256 = timed("t_hash", bytes_sha256, sparse_png)
        writes.append((sparse_png, sparse_sha256, png_src, outputs["sparse"]))
    points = points_sha = None
    if fmt in ("parquet", "both"):
        if max(w, h) > MAX_SIDE:
            raise FormatError(f"frame {fid}: {w}x{h} is too large for uint16 pixel coordinates")
        points = timed("t_encode", depth_to_points, depth)
        points_sha = timed("t_hash", points_sha256, *points)

    # Ground truth and confidence: stored byte for byte (PNG or .npy), decoded to check.
    stored: dict[str, tuple[str | None, str | None]] = {}
    n_gt = None
    for kind, decode in (("gt", decode_depth_bytes), ("confidence", decode_confidence_bytes)):
        src_k = getattr(x, kind)
        if src_k is None:
            stored[kind] = (None, None)
            continue
        kdata = timed("t_read", _read_bytes, src_k, kind)
        arr = timed("t_decode", decode, kdata, Path(src_k).suffix, source=src_k)
        if arr.shape != (h, w):
            raise FormatError(
                f"{src_k}: {kind} is {arr.shape[1]}x{arr.shape[0]}, the image {x.rgb} is {w}x{h}"
            )
        if kind == "gt":
            n_gt = int(np.count_nonzero(arr))
        stored[kind] = (rel[kind], timed("t_hash", bytes_sha256, kdata))
        writes.append((kdata, stored[kind][1], src_k, outputs[kind]))

    fx = fy = cx = cy = None
    geometry = {}
    if x.calib is not None:
        calib = _image_calibration(x.calib, x.rgb, w, h, x.calib_camera)
        fx, fy, cx, cy = calib.fx, calib.fy, calib.cx, calib.cy
        params["calib"] = desc.get("calib")
        if settings.geometry:
            geometry = calibration_geometry(calib, x.calib, x.calib_camera)
    if settings.geometry:
        geometry.update(T_ego_cam=x.T_ego_cam, T_world_ego=x.T_world_ego)
    if "points" in rel:
        if x.calib is None:
            raise FormatError(f"frame {fid}: --store-points needs the frame's calibration")
        cloud = timed("t_encode", camera_points, x.cloud, calib, sweeps=x.sweeps)
        cloud_npy = _npy_bytes(cloud)
        writes.append((cloud_npy, bytes_sha256(cloud_npy), None, outputs["points"]))
    if settings.params:
        params["params"] = settings.params
    if x.sample_params:
        params["sample"] = dict(x.sample_params)

    row = ManifestRow(
        id=fid,
        sequence=x.sequence,
        frame=x.frame,
        split=None,  # assigned when the frames are merged
        width=w,
        height=h,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        rgb_path=rel["rgb"] if ref is None else ref[1],
        rgb_root=None if ref is None else ref[0],
        rgb_size=None if ref is None else int(ref[2].st_size),
        rgb_mtime_ns=None if ref is None else int(ref[2].st_mtime_ns),
        sparse_path=rel.get("sparse"),
        sparse_parquet=None,  # the part is written when the frames are merged
        sparse_row=None,
        gt_path=stored["gt"][0],
        confidence_path=stored["confidence"][0],
        n_sparse=n_sparse,
        density=n_sparse / float(w * h),
        n_gt=n_gt,
        source=settings.source,
        rgb_sha256=rgb_sha256,
        sparse_sha256=sparse_sha256,
        sparse_points_sha256=points_sha,
        gt_sha256=stored["gt"][1],
        confidence_sha256=stored["confidence"][1],
        generation_params=json.dumps(params, sort_keys=True),
        frame_index=None,  # the rank in the sequence, known when the frames are merged
        timestamp=x.timestamp,
        T_world_cam=x.pose,
        camera=x.camera,
        **geometry,
    )
    linked = 0
    for wdata, wsha, wsrc, wdst in writes:
        linked += timed("t_write", _store, wdata, wsha, wsrc, wdst, settings.store == "link")
    t0 = clock()
    append_staged(staging_folder(outputs["staged"], fid), fid, encode_record(row.to_dict(), points))
    t["t_stage"] += clock() - t0
    return DatasetFrameStats(n_sparse=n_sparse, linked=linked, **t)


def staging_folder(staged: Path, fid: str) -> Path:
    """The staging folder of a frame, from its ``staged`` output (``<folder>/<id>.rec``)."""
    return Path(staged).parents[fid.count("/")]
