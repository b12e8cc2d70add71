"""Calibration files: KITTI object, KITTI raw (pair of files), and plain JSON.

All produce a :class:`sparsetools.calibration.Calibration`. The JSON form is::

    {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
     "T_cam_from_sensor": [[...4x4...]], "width": W, "height": H}

optionally with ``"P"`` (3x4). The mmdetection3d-derived nuScenes JSON (``cameras`` ->
``cam2img`` / ``lidar2cam``) is read too, choosing the camera by name.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path

import numpy as np

from ..calibration import Calibration
from ..errors import CalibrationError, FormatError
from .atomic import atomic_write_bytes

__all__ = [
    "PRINCIPAL_POINT_MARGIN",
    "check_principal_point",
    "check_sensor",
    "frame_calibration",
    "load_calibration",
    "read_json_calib",
    "read_key_value_file",
    "read_kitti_object_calib",
    "read_kitti_raw_calib",
    "read_kitti_stereo_rig",
    "write_json_calib",
    "write_kitti_object_calib",
]

KITTI_IMAGE_SIZE = (1242, 375)


#: Largest calibration file read (bytes): real ones are a few KiB.
MAX_CALIB_BYTES = 1 << 20


def read_calibration_text(path: str | os.PathLike) -> str:
    """The text of a calibration file: a regular file of at most :data:`MAX_CALIB_BYTES`.

    A device, a FIFO or a link to one (``/dev/zero``) would be read forever: refused.
    """
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError as exc:
        raise CalibrationError(f"{path}: no such calibration file") from exc
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if path.is_dir():
        raise CalibrationError(f"{path}: not a text calibration file (a folder)")
    if not stat.S_ISREG(st.st_mode):
        raise CalibrationError(f"{path}: not a regular file (a device or a pipe?)")
    if st.st_size > MAX_CALIB_BYTES:
        raise CalibrationError(
            f"{path}: {st.st_size} bytes, too large to be a calibration file (limit 1 MiB)"
        )
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_CALIB_BYTES + 1)
        return data.decode("utf-8", errors="strict")
    except UnicodeDecodeError as exc:
        raise CalibrationError(f"{path}: not a text calibration file") from exc
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read ({exc.strerror or exc})") from exc


def read_key_value_file(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Parse ``key: v1 v2 ...`` lines (KITTI calib format) into float64 arrays.

    Lines whose values are not all numbers (``calib_time: 09-Jan-2012 ...``) are kept only
    if a later lookup asks for them; they are stored as ``None`` so a missing key and a
    non-numeric key are told apart. A key given twice with different values is an error
    (which one a reader would take is arbitrary); the same line twice is fine.
    """
    path = Path(path)
    text = read_calibration_text(path)
    out: dict[str, np.ndarray | None] = {}
    line_of: dict[str, int] = {}
    for number, line in enumerate(text.splitlines(), 1):
        if ":" not in line:
            continue
        key, _, value = line.partition(":")
        key = key.strip()
        try:
            parsed = np.array([float(v) for v in value.split()], dtype=np.float64)
        except ValueError:
            parsed = None
        if key in out:
            old = out[key]
            same = (old is None and parsed is None) or (
                old is not None and parsed is not None and np.array_equal(old, parsed)
            )
            if not same:
                raise CalibrationError(
                    f"{path}: key '{key}' is given twice with different values (lines "
                    f"{line_of[key]} and {number})"
                )
            continue
        out[key] = parsed
        line_of[key] = number
    return out


def _matrix(values: dict, key: str, shape: tuple[int, int], path: Path) -> np.ndarray:
    if key not in values:
        raise CalibrationError(f"{path}: missing key '{key}'")
    v = values[key]
    if v is None or not np.all(np.isfinite(v)):
        raise CalibrationError(f"{path}: key '{key}' holds non-numeric values")
    if v.size != shape[0] * shape[1]:
        raise CalibrationError(
            f"{path}: key '{key}' has {v.size} values, expected {shape[0] * shape[1]}"
        )
    return v.reshape(shape)


def _homogeneous(M: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[: M.shape[0], : M.shape[1]] = M
    return T


def _split_projection(P: np.ndarray, path: Path) -> np.ndarray:
    K = P[:, :3].copy()
    if abs(np.linalg.det(K)) < 1e-9:
        raise CalibrationError(f"{path}: projection matrix is singular")
    return K


def read_kitti_object_calib(
    path: str | os.PathLike, *, camera: int = 2, image_size: tuple[int, int] | None = None
) -> Calibration:
    """Read a KITTI object-benchmark calib file (``P0..P3``, ``R0_rect``, ``Tr_velo_to_cam``).

    The sensor is the Velodyne: ``T_cam_from_sensor = R0_rect @ Tr_velo_to_cam`` (rectified
    reference camera) and ``P = P{camera}`` (3x4, with its translation column), so
    ``P @ T`` is KITTI's and monodepth2's projection. Image size is not in the file; pass
    ``image_size`` (W, H) or set it later with :meth:`Calibration.with_size`.
    """
    path = Path(path)
    values = read_key_value_file(path)
    P = _matrix(values, f"P{camera}", (3, 4), path)
    R0 = _matrix(values, "R0_rect", (3, 3), path)
    Tr = _matrix(values, "Tr_velo_to_cam", (3, 4), path)
    K = _split_projection(P, path)
    T = _homogeneous(R0) @ _homogeneous(Tr)
    w, h = image_size if image_size is not None else (None, None)
    return Calibration(K=K, T_cam_from_sensor=T, P=P, width=w, height=h, source=str(path),
                       extra={"sensor": SENSOR_KITTI})  # fmt: skip


def read_kitti_raw_calib(folder: str | os.PathLike, *, camera: int = 2) -> Calibration:
    """Read a KITTI raw date folder's ``calib_cam_to_cam.txt`` + ``calib_velo_to_cam.txt``.

    ``T = R_rect_00 @ [R | T]`` and ``P = P_rect_0{camera}``; the image size is
    ``S_rect_0{camera}`` (1242x375 for 2011_09_26).
    """
    folder = Path(folder)
    c2c = folder / "calib_cam_to_cam.txt"
    v2c = folder / "calib_velo_to_cam.txt"
    for f in (c2c, v2c):
        if not f.is_file():
            raise CalibrationError(
                f"{folder}: missing {f.name} (a KITTI raw calib folder holds both)"
            )
    cam = read_key_value_file(c2c)
    velo = read_key_value_file(v2c)
    P = _matrix(cam, f"P_rect_0{camera}", (3, 4), c2c)
    R_rect = _matrix(cam, "R_rect_00", (3, 3), c2c)
    S = _matrix(cam, f"S_rect_0{camera}", (1, 2), c2c).ravel()
    R = _matrix(velo, "R", (3, 3), v2c)
    t = _matrix(velo, "T", (3, 1), v2c)
    K = _split_projection(P, c2c)
    T = _homogeneous(R_rect) @ _homogeneous(np.hstack([R, t]))
    return Calibration(
        K=K,
        T_cam_from_sensor=T,
        P=P,
        width=int(round(S[0])),
        height=int(round(S[1])),
        source=str(folder),
        extra={"sensor": SENSOR_KITTI},
    )


def read_kitti_stereo_rig(
    folder: str | os.PathLike, *, left: int = 2, right: int = 3
) -> tuple[float, float]:
    """Focal length and baseline of a KITTI raw rectified stereo pair.

    From ``calib_cam_to_cam.txt``: ``fx = P_rect_0{left}[0, 0]`` and ``baseline =
    (P_rect_0{left}[0, 3] - P_rect_0{right}[0, 3]) / fx`` (the rectified projections differ
    only by ``fx * t_x``); 0.532 m for cameras 2 and 3 of 2011_09_26.

    Returns
    -------
    fx : float, pixels
    baseline : float, metres (> 0: ``right`` is to the right of ``left``)

    Raises
    ------
    CalibrationError
        File or keys missing, different focal lengths, or a baseline that is not positive.
    """
    folder = Path(folder)
    c2c = folder / "calib_cam_to_cam.txt" if folder.is_dir() else folder
    if not c2c.is_file():
        raise CalibrationError(f"{folder}: missing calib_cam_to_cam.txt (the stereo pair's)")
    cam = read_key_value_file(c2c)
    P_left = _matrix(cam, f"P_rect_0{left}", (3, 4), c2c)
    P_right = _matrix(cam, f"P_rect_0{right}", (3, 4), c2c)
    fx = float(P_left[0, 0])
    if fx <= 0 or abs(P_right[0, 0] - fx) > 1e-6 * fx:
        raise CalibrationError(
            f"{c2c}: P_rect_0{left} and P_rect_0{right} are not one rectified pair (fx "
            f"{P_left[0, 0]:g} and {P_right[0, 0]:g})"
        )
    baseline = float(P_left[0, 3] - P_right[0, 3]) / fx
    if not baseline > 0:
        raise CalibrationError(
            f"{c2c}: camera {right} is not to the right of camera {left} (baseline {baseline:g} m)"
        )
    return fx, baseline


def _as_array(d: dict, key: str, shape: tuple[int, int], path: Path) -> np.ndarray:
    if key not in d:
        raise CalibrationError(f"{path}: missing key '{key}'")
    try:
        a = np.array(d[key], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: key '{key}' holds non-numeric values") from exc
    if a.shape != shape:
        raise CalibrationError(f"{path}: key '{key}' must be {shape[0]}x{shape[1]}, got {a.shape}")
    return a


def _size(d: dict, key: str, default, path: Path) -> int | None:
    value = d.get(key, default)
    if value is None:
        return None
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or value != int(value)
        or value <= 0
    ):
        raise CalibrationError(f"{path}: key '{key}' must be a positive integer, got {value!r}")
    return int(value)


def read_json_calib(path: str | os.PathLike, *, camera: str | int | None = None) -> Calibration:
    """Read a JSON calibration (plain form, or the nuScenes ``cameras`` form; see module doc)."""
    path = Path(path)
    try:
        d = json.loads(read_calibration_text(path))
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}: not valid JSON ({exc})") from exc
    except RecursionError as exc:
        raise CalibrationError(f"{path}: not valid JSON (nested too deeply)") from exc
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if not isinstance(d, dict):
        raise CalibrationError(f"{path}: expected a JSON object")
    try:
        return _json_calibration(d, path, camera)
    except CalibrationError:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, OverflowError) as exc:
        # A value of the wrong JSON type somewhere (a list for a number, a number for a table).
        raise CalibrationError(
            f"{path}: malformed calibration ({type(exc).__name__}: {exc})"
        ) from exc


def _json_calibration(d: dict, path: Path, camera) -> Calibration:
    if "cameras" in d:
        cameras = d["cameras"]
        if not isinstance(cameras, dict):
            raise CalibrationError(f"{path}: 'cameras' must be an object of cameras by name")
        name = camera if isinstance(camera, str) else "CAM_FRONT"
        if name not in cameras:
            raise CalibrationError(
                f"{path}: no camera '{name}' (has {', '.join(sorted(map(str, cameras)))})"
            )
        cam = cameras[name]
        if not isinstance(cam, dict):
            raise CalibrationError(f"{path}: camera '{name}' must be an object")
        K = _as_array(cam, "cam2img", (3, 3), path)
        T = _as_array(cam, "lidar2cam", (4, 4), path)
        w, h = _size(cam, "width", 1600, path), _size(cam, "height", 900, path)
        return Calibration(K=K, T_cam_from_sensor=T, width=w, height=h, source=f"{path}:{name}",
                           extra={"sensor": SENSOR_NUSCENES_LIDAR})  # fmt: skip
    K = _as_array(d, "K", (3, 3), path)
    T = _as_array(d, "T_cam_from_sensor", (4, 4), path)
    P = _as_array(d, "P", (3, 4), path) if d.get("P") is not None else None
    extra = {
        k: v for k, v in d.items() if k not in {"K", "T_cam_from_sensor", "P", "width", "height"}
    }
    return Calibration(
        K=K,
        T_cam_from_sensor=T,
        P=P,
        width=_size(d, "width", None, path),
        height=_size(d, "height", None, path),
        source=str(path),
        extra=extra,
    )


def _is_bare_intrinsics(path: Path) -> bool:
    """A text file of numbers only, no ``key:`` lines (KITTI val_selection_cropped intrinsics)."""
    try:
        text = read_calibration_text(path)
    except CalibrationError:
        return False
    return ":" not in text and bool(text.split())


def read_intrinsics_txt(path: str | os.PathLike) -> Calibration:
    """A bare 3x3 intrinsics file (9 numbers; KITTI ``val_selection_cropped/intrinsics``).

    It holds no sensor transform: ``T_cam_from_sensor`` is the identity (the calibration
    describes the image only: fx, fy, cx, cy).
    """
    path = Path(path)
    try:
        values = np.array([float(v) for v in read_calibration_text(path).split()])
    except ValueError as exc:
        raise CalibrationError(f"{path}: intrinsics file holds non-numeric values") from exc
    if values.size not in (9, 12):
        raise CalibrationError(
            f"{path}: an intrinsics file holds 9 numbers (a 3x3 K) or 12 (a 3x4 P), got "
            f"{values.size}"
        )
    M = values.reshape(3, -1)
    return Calibration(
        K=M[:, :3], T_cam_from_sensor=np.eye(4), P=M if M.shape[1] == 4 else None,
        source=str(path),
    )  # fmt: skip


def write_json_calib(
    path: str | os.PathLike, calib: Calibration, *, overwrite: bool = True, **extra
) -> None:
    """Write ``calib`` as plain JSON (atomically); ``extra`` keys are stored alongside."""
    d = calib.to_dict()
    d.update(extra)
    atomic_write_bytes(path, (json.dumps(d, indent=1) + "\n").encode("utf-8"), overwrite=overwrite)


def write_kitti_object_calib(
    path: str | os.PathLike, calib: Calibration, *, overwrite: bool = True
) -> None:
    """Write a KITTI object calib file with ``P2`` = calib's P (or [K|0]), ``R0_rect`` = I.

    ``Tr_velo_to_cam`` holds ``T_cam_from_sensor``; P0, P1, P3 repeat P2 so standard
    readers that expect them find them.
    """
    P = calib.P if calib.P is not None else np.hstack([calib.K, np.zeros((3, 1))])

    def fmt(a: np.ndarray) -> str:
        return " ".join(f"{v:.12e}" for v in np.asarray(a).ravel())

    lines = [f"P{i}: {fmt(P)}" for i in range(4)]
    lines.append(f"R0_rect: {fmt(np.eye(3))}")
    lines.append(f"Tr_velo_to_cam: {fmt(calib.T_cam_from_sensor[:3])}")
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"), overwrite=overwrite)


def load_calibration(
    path_or_dir: str | os.PathLike,
    *,
    camera: int | str = 2,
    image_size: tuple[int, int] | None = None,
) -> Calibration:
    """Load any supported calibration.

    Parameters
    ----------
    path_or_dir : path-like
        A KITTI object calib ``.txt``, a KITTI raw date folder (or one of its two files),
        or a ``.json`` calibration.
    camera : int or str
        KITTI camera index (0-3, default 2 = left colour) or nuScenes camera name.
    image_size : (W, H), optional
        Image size when the file does not hold it (KITTI object calib files do not).

    Returns
    -------
    Calibration
    """
    p = Path(path_or_dir)
    if not p.exists():
        raise CalibrationError(f"{p}: no such calibration file or folder")
    if p.is_dir():
        if (p / "calib_cam_to_cam.txt").exists() or (p / "calib_velo_to_cam.txt").exists():
            calib = read_kitti_raw_calib(
                p, camera=int(camera) if not isinstance(camera, str) else 2
            )
        else:
            raise CalibrationError(
                f"{p}: folder holds no calib_cam_to_cam.txt / calib_velo_to_cam.txt "
                "(for per-frame calib files pass the file, or a folder to a batch command)"
            )
    elif p.name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        calib = read_kitti_raw_calib(
            p.parent, camera=int(camera) if not isinstance(camera, str) else 2
        )
    elif p.suffix.lower() == ".json":
        calib = read_json_calib(p, camera=camera)
    elif p.suffix.lower() == ".txt" and _is_bare_intrinsics(p):
        calib = read_intrinsics_txt(p)
    elif p.suffix.lower() == ".txt":
        cam = int(camera) if not isinstance(camera, str) else 2
        calib = read_kitti_object_calib(p, camera=cam)
    else:
        raise FormatError(f"{p}: unknown calibration format (expected .txt, .json or a folder)")
    if image_size is not None:
        calib = calib.with_size(*image_size)
    return calib


#: The sensor a calibration's ``T_cam_from_sensor`` starts from, where its format says it
#: (``Calibration.extra["sensor"]``): a KITTI calibration is the Velodyne's, an mmdetection3d
#: nuScenes one the LIDAR_TOP's.
SENSOR_KITTI = "KITTI Velodyne HDL-64E"
SENSOR_NUSCENES_LIDAR = "nuScenes LIDAR_TOP"
#: Cloud kinds (:func:`sparsetools.io.pointcloud.cloud_kind`) each sensor writes.
_CLOUDS_OF = {SENSOR_KITTI: ("kitti-bin",), SENSOR_NUSCENES_LIDAR: ("nuscenes-bin",)}
_NAMES_OF_KIND = {"kitti-bin": "a KITTI Velodyne .bin scan", "nuscenes-bin":
                  "a nuScenes LIDAR_TOP .pcd.bin sweep", "radar-pcd": "a nuScenes radar .pcd"}  # fmt: skip


def check_sensor(calib: Calibration, cloud: str | os.PathLike) -> None:
    """Refuse a calibration of one dataset's sensor applied to another dataset's cloud (a
    KITTI scan with a nuScenes calibration gives maps of the wrong camera and size, silently).

    Only formats that say which sensor they are are compared: a KITTI ``.bin`` scan, a
    nuScenes ``.pcd.bin`` or radar ``.pcd``; a KITTI or an mmdetection3d nuScenes calibration.
    """
    from .pointcloud import cloud_kind

    sensor = calib.extra.get("sensor") if isinstance(calib.extra, dict) else None
    if sensor not in _CLOUDS_OF:
        return
    kind = cloud_kind(cloud)
    if kind in _NAMES_OF_KIND and kind not in _CLOUDS_OF[sensor]:
        raise CalibrationError(
            f"calibration {calib.source or ''} is for the {sensor} but {cloud} is "
            f"{_NAMES_OF_KIND[kind]}: give the calibration of the sensor that made the cloud"
        )


#: The principal point of a camera's own (uncropped) images lies within this fraction of the
#: image size from its centre; farther, the calibration belongs to other images.
PRINCIPAL_POINT_MARGIN = 0.4


def check_principal_point(calib: Calibration, *, given_by: str) -> None:
    """Refuse a calibration whose principal point is outside the image or far from its centre
    (more than :data:`PRINCIPAL_POINT_MARGIN` of the size): the intrinsics of other images."""
    w, h = calib.width, calib.height
    off_u, off_v = abs(calib.cx - w / 2) / w, abs(calib.cy - h / 2) / h
    if max(off_u, off_v) > PRINCIPAL_POINT_MARGIN:
        where = "outside the image" if not (0 <= calib.cx < w and 0 <= calib.cy < h) else (
            "far from its centre")  # fmt: skip
        raise CalibrationError(
            f"calibration {calib.source or ''}: principal point ({calib.cx:g}, {calib.cy:g}) is "
            f"{where} of the {w}x{h} image ({given_by}): the calibration is for other images"
        )


def frame_calibration(
    *,
    calib_path: str | os.PathLike | None = None,
    calibration: Calibration | None = None,
    camera: int | str = 2,
    image: str | os.PathLike | None = None,
    image_size: tuple[int, int] | None = None,
    resize: float | None = None,
    crop: tuple[int, int, int, int] | None = None,
    what: str = "depth map",
    resize_to: tuple[int, int] | None = None,
) -> Calibration:
    """The calibration a frame's map uses: loaded, sized, checked, resized, cropped.

    The image size comes from ``image_size`` (``--image-size``), the frame's image header, or
    the calibration's own size (KITTI raw ``S_rect``, a JSON ``width``/``height``, nuScenes);
    every size that is known must agree with the others (a calibration of other images is
    refused, never stretched), and the principal point must lie near the image's centre
    (:func:`check_principal_point`).

    Parameters
    ----------
    calib_path : path-like, optional
        Calibration file or KITTI raw calibration folder (when ``calibration`` is None).
    calibration : Calibration, optional
        Already loaded (shared by a batch) or computed by the source (nuScenes).
    camera : int or str
        KITTI camera index or camera name of a JSON calibration.
    image : path-like, optional
        The frame's camera image (only its header is read).
    image_size : (width, height), optional
    resize : float, optional
        Scale the image and intrinsics first.
    crop : (top, left, height, width), optional
        Then crop (in resized pixels).
    what : str
        What the map is, for the pixel-count message.
    resize_to : (width, height), optional
        Instead of ``resize``: bring the image to exactly this size, each axis scaled by its
        own factor (:meth:`Calibration.resized_to`).

    Raises
    ------
    ParameterError
        No size known, a crop that does not fit, or too many pixels.
    CalibrationError
        Sizes that disagree, or a principal point far from the image's centre.
    """
    from ..errors import ParameterError
    from .image import check_pixel_count, image_size_of

    calib = calibration
    if calib is None:
        if calib_path is None:
            raise ParameterError("no calibration: give --calib")
        calib = load_calibration(calib_path, camera=camera)
    given_by = "its own size"
    if image_size is not None:
        calib = calib.for_size(*image_size, given_by="--image-size")
        given_by = "--image-size"
    if image is not None:
        calib = calib.for_size(*image_size_of(image), given_by=f"image {image}")
        given_by = f"image {image}"
    if calib.width is None or calib.height is None:
        raise ParameterError(
            "image size missing: give --image-size WxH or --image IMG "
            f"(calibration {calib.source or calib_path or '?'} holds no size)"
        )
    check_pixel_count(calib.width, calib.height, "image")
    check_principal_point(calib, given_by=given_by)
    if resize is not None and resize_to is not None:
        raise ParameterError("give a resize factor or an exact size (--resize-to), not both")
    if resize is not None:
        calib = calib.resized(resize)
    if resize_to is not None:
        calib = calib.resized_to(*resize_to)
    if crop is not None:
        top, left, h, w = crop
        calib = calib.cropped(top, left, h, w)
    # A size from an option or a calibration file is not bounded by anything else.
    check_pixel_count(calib.width, calib.height, what)
    return calib
