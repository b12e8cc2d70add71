"""Poses of point-cloud frames, for commands that merge several scans (``accumulate``).

:func:`attach_poses` sets every frame's :attr:`Frame.pose` (row-major 4x4
``T_world_from_sensor``: the pose of the sensor that measured the frame's cloud, metres) and
adds the files the pose was read from to its :attr:`Frame.extra_inputs` (so they decide
resume). Where the pose comes from, first found:

1. **A pose file given** (``path``): KITTI odometry ``poses.txt`` (12 numbers per line, the
   row-major 3x4 top of a 4x4 pose; line ``i`` is frame number ``i``, the frame's name read
   as an integer). One file for a single sequence, or a folder holding per sequence
   ``<sequence>.txt``, ``<sequence>/poses_velodyne.txt`` or ``<sequence>/poses.txt`` (the
   synthetic video layout). ``poses_frame``: the file holds ``camera`` poses
   (``T_world_from_cam``, KITTI odometry; converted with the frame's calibration,
   ``T_world_from_sensor = T_world_from_cam @ T_cam_from_sensor``) or ``sensor`` poses;
   ``auto``: ``sensor`` when the file name contains ``velodyne`` or ``lidar``, else
   ``camera``.
2. **The input's own layout**: a synthetic video's ``<sequence>/poses_velodyne.txt``
   beside ``<sequence>/velodyne/<frame>.bin``; a KITTI raw drive's oxts packets
   (``<drive>/oxts/data/<frame>.txt`` with ``calib_imu_to_velo.txt`` in the calibration
   folder; the standard conversion of :func:`sparsetools.io.poses.oxts_poses`, Mercator
   scale and origin from the drive's FIRST packet, which every frame therefore depends on);
   nuScenes frames, whose source already set :attr:`Frame.pose` (ego pose x sensor mounting).

Frames without a pose are reported with the reason (:attr:`PoseAttachment.missing`).

:func:`accumulation_frames` enumerates the inputs of such commands: synthetic video folders
(:func:`video_frames`: one sequence per ``seq_NNNN`` folder), nuScenes roots (LIDAR_TOP key
frames with their ego poses) and everything :func:`~sparsetools.io.sources.cloud_frames` reads.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ...errors import FormatError, ParameterError
from .frame import Frame, FrameKey

__all__ = [
    "POSES_FRAMES",
    "AccumulationInputs",
    "FrameNumbers",
    "PoseAttachment",
    "accumulation_frames",
    "accumulation_inputs",
    "attach_poses",
    "frame_number",
    "is_synthetic_video",
    "moving_masks",
    "video_frames",
    "video_masks",
]

POSES_FRAMES = ("auto", "camera", "sensor")
VIDEO_POSES = "poses_velodyne.txt"
IMU_TO_VELO = "calib_imu_to_velo.txt"


@dataclass(frozen=True)
class PoseAttachment:
    """Frames with their poses, and what could not be found.

    Attributes
    ----------
    frames : tuple of Frame
        The frames given, in order; ``pose`` set where one was found.
    kinds : tuple of str
        Per frame: ``poses-file``, ``synthetic-video``, ``kitti-oxts``, ``nuscenes`` or ``""``.
    missing : mapping of FrameKey -> str
        Why a frame has no pose.
    """

    frames: tuple[Frame, ...]
    kinds: tuple[str, ...]
    missing: Mapping[FrameKey, str] = field(default_factory=dict)

    @property
    def source(self) -> str:
        """Kinds used, ``+``-joined (``kitti-oxts``, ``poses-file+synthetic-video``)."""
        return "+".join(sorted({k for k in self.kinds if k}))


# -- synthetic video layout ----------------------------------------------------------------------


def _is_video_sequence(path: Path) -> bool:
    return (path / "velodyne").is_dir() and (path / VIDEO_POSES).is_file()


def is_synthetic_video(path: str | os.PathLike) -> bool:
    """A ``synth-scene --video`` folder (``video.json``) or one of its sequence folders."""
    p = Path(path)
    return p.is_dir() and ((p / "video.json").is_file() or _is_video_sequence(p))


def _video_sequences(path: Path) -> list[Path]:
    if _is_video_sequence(path):
        return [path]
    return sorted(d for d in path.iterdir() if not d.name.startswith(".") and _is_video_sequence(d))


def video_frames(path: str | os.PathLike) -> list[Frame]:
    """Frames of a synthetic video folder: sequence = ``seq_NNNN``, frame = file stem.

    Each frame has its scan (``velodyne/<frame>.bin``), calibration (``calib/<frame>.txt``)
    and image (``image_2/<frame>.png``, which gives the size); poses are attached by
    :func:`attach_poses`.

    Raises
    ------
    FormatError
        No sequence with scans.
    """
    root = Path(path)
    frames = []
    for seq in _video_sequences(root):
        for f in sorted((seq / "velodyne").glob("*.bin")):
            key = FrameKey(seq.name, f.stem)
            calib = seq / "calib" / f"{f.stem}.txt"
            image = seq / "image_2" / f"{f.stem}.png"
            frames.append(
                Frame(
                    key=key,
                    cloud=f,
                    calib=calib if calib.is_file() else None,
                    image=image if image.is_file() else None,
                )
            )
    if not frames:
        raise FormatError(f"{root}: synthetic video folder without <sequence>/velodyne/*.bin")
    return frames


def video_masks(path: str | os.PathLike) -> dict[FrameKey, Path]:
    """Moving-object masks of a synthetic video folder (``<sequence>/moving_mask/*.png``)."""
    out = {}
    for seq in _video_sequences(Path(path)):
        for f in sorted((seq / "moving_mask").glob("*.png")):
            out[FrameKey(seq.name, f.stem)] = f
    return out


def moving_masks(frames: list[Frame], path: str | os.PathLike) -> dict[FrameKey, Path]:
    """Each frame's moving-object mask: a folder tree of PNGs matched by key, or a synthetic
    video folder (its ``moving_mask/``).

    Raises
    ------
    FormatError
        No PNG in the folder, or a frame without a mask (names the first).
    """
    from .tree import index_tree, match_keys

    p = Path(path)
    if is_synthetic_video(p):
        index = video_masks(p)
    else:
        index = index_tree(p, (".png",), option="--mask", role="mask").files
    found = match_keys([f.key for f in frames], index)
    absent = [f.key for f in frames if f.key not in found]
    if absent:
        raise FormatError(
            f"--mask: {p}: no mask for frame {absent[0]} ({len(absent)} of {len(frames)} "
            "frames lack one)"
        )
    return found


# -- nuScenes roots ------------------------------------------------------------------------------


def _nuscenes_version(path: Path) -> str | None:
    """The table version of a nuScenes root (its only ``v1.0-*/sample_data.json``), or None."""
    if not path.is_dir():
        return None
    versions = sorted(d.name for d in path.glob("v1.0-*") if (d / "sample_data.json").is_file())
    if len(versions) > 1:
        raise ParameterError(
            f"{path} holds several nuScenes versions ({', '.join(versions)}): keep one"
        )
    return versions[0] if versions else None


def accumulation_frames(
    paths: list[str | os.PathLike],
    *,
    calib: str | os.PathLike | None = None,
    image: str | os.PathLike | None = None,
    camera: int = 2,
    option: str = "CLOUD",
) -> list[Frame]:
    """Frames of scans to accumulate, sorted by key.

    A synthetic video folder gives its sequences (:func:`video_frames`); a nuScenes root
    its LIDAR_TOP key frames seen by CAM_FRONT, with ego poses and calibrations; anything
    else goes to :func:`~sparsetools.io.sources.cloud_frames` (files, folders, KITTI raw).
    ``calib`` and ``image`` replace the layouts' own (not for nuScenes).

    Raises
    ------
    FormatError
        Missing paths, no scans, or two inputs that are the same frame.
    ParameterError
        ``calib`` or ``image`` with a nuScenes root.
    """
    from . import attach, cloud_frames
    from .nuscenes import nuscenes_frames

    if not paths:
        raise ParameterError("no point clouds given")
    found: list[Frame] = []
    plain = []
    for p in map(Path, paths):
        if is_synthetic_video(p):
            frames = video_frames(p)
            if calib is not None:
                frames, _ = attach(frames, calib, "calib", role="calib", option="--calib")
            if image is not None:
                frames, _ = attach(frames, image, "image", role="image", option="--image")
            found.extend(frames)
        elif (version := _nuscenes_version(p)) is not None:
            if calib is not None or image is not None:
                raise ParameterError(
                    f"{p} is a nuScenes root, which has its own calibration and images: "
                    "leave out --calib / --image"
                )
            found.extend(
                nuscenes_frames(
                    p, version=version, sensor="LIDAR_TOP", camera="CAM_FRONT", sweeps=1
                )
            )
        else:
            plain.append(p)
    if plain:
        found.extend(cloud_frames(plain, calib=calib, image=image, camera=camera, option=option))
    by_key: dict[FrameKey, Frame] = {}
    for f in found:
        if f.key in by_key:
            raise FormatError(
                f"{by_key[f.key].cloud} and {f.cloud} are the same frame '{f.key}': give each once"
            )
        by_key[f.key] = f
    return [by_key[k] for k in sorted(by_key)]


# -- pose files ----------------------------------------------------------------------------------


def frame_number(key: FrameKey) -> int | None:
    """The frame's name read as a line number of its sequence's pose or time file (``000005``
    -> 5), or None when it is not a decimal number."""
    return int(key.frame) if key.frame.isascii() and key.frame.isdigit() else None


class FrameNumbers:
    """Frame numbers taken in each numbered file (a pose file, a times file): two frames of
    different names whose numbers are equal (``1`` and ``01``) would share one line, one of
    them silently with the other's data: refused, naming both."""

    def __init__(self):
        self._taken: dict[tuple[Path, int], FrameKey] = {}

    def take(self, path: Path, n: int, key: FrameKey) -> None:
        other = self._taken.setdefault((path, n), key)
        if other != key:
            raise FormatError(
                f"frames '{other}' and '{key}' are both frame number {n}: both would take line "
                f"{n + 1} of {path}; rename one (frame names are read as numbers)"
            )


class _PoseFiles:
    """Pose files read once each: ``path -> (N, 4, 4)``."""

    def __init__(self):
        self._poses: dict[Path, np.ndarray] = {}
        self._numbers = FrameNumbers()

    def line(self, path: Path, key: FrameKey) -> tuple[np.ndarray | None, str]:
        from ..poses import read_kitti_poses

        if path not in self._poses:
            self._poses[path] = read_kitti_poses(path)
        n = frame_number(key)
        if n is None:
            return None, f"its name '{key.frame}' is not a frame number (a line of {path.name})"
        self._numbers.take(path, n, key)
        poses = self._poses[path]
        if n >= len(poses):
            return None, f"{path} has {len(poses)} line(s); frame {key.frame} needs line {n + 1}"
        return poses[n], ""


def _sequence_pose_file(path: Path, sequence: str) -> Path | None:
    if path.is_file():
        return path
    base = path / sequence if sequence else path
    for cand in (path / f"{sequence}.txt" if sequence else None, base / VIDEO_POSES,
                 base / "poses.txt"):  # fmt: skip
        if cand is not None and cand.is_file():
            return cand
    return None


def _file_frame(path: Path, poses_frame: str) -> str:
    if poses_frame != "auto":
        return poses_frame
    name = path.name.lower()
    return "sensor" if ("velodyne" in name or "lidar" in name) else "camera"


class _CameraToSensor:
    """``T_cam_from_sensor`` of each frame's calibration (read once per file)."""

    def __init__(self, camera: int):
        self.camera = camera
        self._cache: dict[Path, np.ndarray] = {}

    def __call__(self, frame: Frame) -> np.ndarray | None:
        from ..calib import load_calibration

        if frame.calibration is not None:
            return np.asarray(frame.calibration.T_cam_from_sensor, dtype=np.float64)
        if frame.calib is None:
            return None
        if frame.calib not in self._cache:
            calib = load_calibration(frame.calib, camera=self.camera)
            self._cache[frame.calib] = np.asarray(calib.T_cam_from_sensor, dtype=np.float64)
        return self._cache[frame.calib]


# -- the layouts' own poses ----------------------------------------------------------------------


class _Oxts:
    """KITTI raw oxts poses of the Velodyne, per drive (scale and origin: the first packet)."""

    def __init__(self):
        self._first: dict[Path, tuple[Path, object]] = {}
        self._imu_to_velo: dict[Path, np.ndarray] = {}

    @staticmethod
    def drive_of(frame: Frame) -> Path | None:
        c = frame.cloud
        if c is None or c.parent.name != "data" or c.parent.parent.name != "velodyne_points":
            return None
        drive = c.parents[2]
        return drive if (drive / "oxts" / "data").is_dir() else None

    def pose(self, frame: Frame, drive: Path) -> tuple[np.ndarray | None, tuple[Path, ...], str]:
        from ..poses import oxts_poses, read_imu_to_velo, read_oxts_packet, sensor_poses

        data = drive / "oxts" / "data"
        packet_file = data / f"{frame.key.frame}.txt"
        if not packet_file.is_file():
            return None, (), f"{packet_file} is missing"
        calib_dirs = [d for d in (frame.calib, drive.parent, drive) if d is not None and d.is_dir()]
        imu_file = next((d / IMU_TO_VELO for d in calib_dirs if (d / IMU_TO_VELO).is_file()), None)
        if imu_file is None:
            return None, (), f"the drive has oxts but no {IMU_TO_VELO} in {drive.parent}"
        if drive not in self._first:
            first = min(data.glob("*.txt"))
            self._first[drive] = (first, read_oxts_packet(first))
        if imu_file not in self._imu_to_velo:
            self._imu_to_velo[imu_file] = read_imu_to_velo(imu_file)
        first_file, first = self._first[drive]
        T_imu = oxts_poses([first, read_oxts_packet(packet_file)])[1:]
        T = sensor_poses(T_imu, self._imu_to_velo[imu_file])[0]
        return T, tuple(dict.fromkeys((packet_file, first_file, imu_file))), ""


def _from_file(f: Frame, path: Path, files: _PoseFiles, poses_frame: str, cam_to_sensor,
               option: str) -> tuple[np.ndarray | None, tuple[Path, ...], str]:  # fmt: skip
    """A frame's pose from the file of its sequence (camera poses turned into sensor poses)."""
    pose_file = _sequence_pose_file(path, f.key.sequence)
    if pose_file is None:
        return None, (), f"{option} {path} holds no pose file of sequence '{f.key.sequence}'"
    T, why = files.line(pose_file, f.key)
    if T is not None and _file_frame(pose_file, poses_frame) == "camera":
        T_cam_from_sensor = cam_to_sensor(f)
        if T_cam_from_sensor is None:
            return None, (), f"{pose_file.name} holds camera poses and the frame has no calibration"
        T = T @ T_cam_from_sensor
    return T, (pose_file,), why


def _flat(T: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(T, dtype=np.float64).reshape(-1))


def attach_poses(
    frames: list[Frame],
    path: str | os.PathLike | None = None,
    *,
    poses_frame: str = "auto",
    camera: int = 2,
    option: str = "--poses",
) -> PoseAttachment:
    """Give every frame its pose (module docstring: a file given, else the layout's own).

    Parameters
    ----------
    frames : list of Frame
    path : path-like, optional
        A pose file or a folder of them (replaces the layouts' poses).
    poses_frame : {"auto", "camera", "sensor"}
        What the given file's poses are of.
    camera : int
        KITTI camera index of the calibrations (camera poses only).
    option : str
        The option ``path`` came from, for messages.

    Returns
    -------
    PoseAttachment

    Raises
    ------
    FormatError
        A pose file that cannot be read (names the file and line), or two frames whose names
        are one number (``1`` and ``01``: they would share a line).
    ParameterError
        ``path`` missing, or one file for frames of several sequences.
    """
    from ...validate import check_choice

    check_choice(poses_frame, "poses_frame", POSES_FRAMES)
    p = None if path is None else Path(path)
    if p is not None:
        if not p.exists():
            raise ParameterError(f"{p}: no such file or folder", param=option)
        sequences = sorted({f.key.sequence for f in frames})
        if p.is_file() and len(sequences) > 1:
            raise ParameterError(
                f"{p} is one pose file but the frames are {len(sequences)} sequences "
                f"({', '.join(map(repr, sequences[:3]))}...): give a folder holding "
                "<sequence>.txt or <sequence>/poses.txt",
                param=option,
            )
    files, oxts, cam_to_sensor = _PoseFiles(), _Oxts(), _CameraToSensor(camera)
    out, kinds, missing = [], [], {}
    for f in frames:
        T, used, kind, why = None, (), "", ""
        if p is not None:
            T, used, why = _from_file(f, p, files, poses_frame, cam_to_sensor, option)
            kind = "poses-file"
        elif (
            f.cloud is not None
            and f.cloud.parent.name == "velodyne"
            and (f.cloud.parent.parent / VIDEO_POSES).is_file()
        ):
            pose_file = f.cloud.parent.parent / VIDEO_POSES
            T, why = files.line(pose_file, f.key)
            used, kind = (pose_file,), "synthetic-video"
        elif f.pose is not None:
            T, kind = np.asarray(f.pose, dtype=np.float64).reshape(4, 4), "nuscenes"
        elif (drive := _Oxts.drive_of(f)) is not None:
            T, used, why = oxts.pose(f, drive)
            kind = "kitti-oxts"
        else:
            why = "its input holds no poses (no poses_velodyne.txt, oxts or nuScenes ego pose)"
        if T is None:
            missing[f.key] = why
            out.append(f)
            kinds.append("")
            continue
        extra = tuple(dict.fromkeys((*f.extra_inputs, *used)))
        out.append(replace(f, pose=_flat(T), extra_inputs=extra))
        kinds.append(kind)
    return PoseAttachment(tuple(out), tuple(kinds), missing)


@dataclass(frozen=True)
class AccumulationInputs:
    """The frames of an ``accumulate`` run, each with its pose (or none, for ICP), its
    calibration and its moving-object mask, and where the poses came from."""

    frames: list[Frame]
    pose_source: str


def accumulation_inputs(
    paths: list[str | os.PathLike],
    *,
    calib: str | os.PathLike | None = None,
    image: str | os.PathLike | None = None,
    poses: str | os.PathLike | None = None,
    poses_frame: str = "auto",
    icp: bool | None = False,
    mask: str | os.PathLike | None = None,
    camera: int = 2,
) -> AccumulationInputs:
    """:func:`accumulation_frames` with the poses attached (``icp``: none, they are registered
    later) and the masks matched by frame. ``icp=None``: the input's own poses when every
    frame has one (KITTI raw oxts, a synthetic video, nuScenes), else ICP for all.

    Raises
    ------
    ParameterError
        No frame, a frame without calibration, or ``poses`` with ``icp``.
    FormatError
        A frame without a pose (and no ``icp``) or without a mask.
    """
    frames = accumulation_frames(paths, calib=calib, image=image, camera=camera)
    if not frames:
        raise ParameterError("no frames to accumulate")
    no_calib = [f for f in frames if f.calib is None and f.calibration is None]
    if no_calib:
        raise ParameterError(
            f"no calibration for frame {no_calib[0].id} ({no_calib[0].cloud}): give --calib "
            "(a file, a KITTI raw date folder or per-frame files)", param="--calib")  # fmt: skip
    if icp is None:
        if poses is not None:
            raise ParameterError("automatic poses (icp=None) take the input's own, not a file")
        own = attach_poses(frames, None, camera=camera)
        icp = bool(own.missing)
    if icp:
        if poses is not None:
            raise ParameterError("give --poses or --icp, not both", param="--icp")
        source = "icp"
    else:
        att = attach_poses(frames, poses, poses_frame=poses_frame, camera=camera)
        if att.missing:
            key, why = next(iter(att.missing.items()))
            raise FormatError(
                f"no pose for frame {key} ({why}; {len(att.missing)} of {len(frames)} frames "
                "lack one): give --poses (a poses.txt or a folder of them) or --icp")  # fmt: skip
        frames, source = list(att.frames), att.source
    if mask is not None:
        masks = moving_masks(frames, mask)
        frames = [replace(f, mask=masks[f.key]) for f in frames]
    return AccumulationInputs(frames, source)
