"""``write_video``: synthetic street videos on disk (KITTI raw / odometry style layout).

Layout (``<frame>`` = 10-digit frame number, ``<sequence>`` = ``seq_0000``, ...)::

    OUT/video.json                         how the folder was made (for ``--check``)
    OUT/<sequence>/image_2/<frame>.png     RGB
    OUT/<sequence>/velodyne/<frame>.bin    KITTI float32 x y z r, scan order
    OUT/<sequence>/velodyne_ring/<frame>.npy  (N,) uint8 laser of each point
    OUT/<sequence>/depth_gt/<frame>.png    dense true depth, KITTI uint16 (m * 256)
    OUT/<sequence>/moving_mask/<frame>.png uint8 0 / 255
    OUT/<sequence>/calib/<frame>.txt       KITTI object calib
    OUT/<sequence>/poses.txt               T_world_from_cam, KITTI odometry format
    OUT/<sequence>/poses_velodyne.txt      T_world_from_velo, same world and format
    OUT/<sequence>/poses/<frame>.txt       4x4 T_world_from_cam
    OUT/<sequence>/times.txt               seconds (10 Hz)
    OUT/<sequence>/scene.json              every parameter drawn for the sequence

Frames are simulated independently (per-frame random streams), so any number of worker
processes writes the same bytes.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import OutputError, ParameterError
from ..io.atomic import atomic_path
from ..io.calib import write_kitti_object_calib
from ..io.image import write_depth_png, write_image
from ..io.kitti import write_velodyne_bin
from ..io.poses import write_kitti_poses, write_pose_matrix, write_times
from .motion import FRAME_RATE_HZ
from .video import VideoSimulator
from .video_parts import KIND_NAMES

__all__ = ["VIDEO_FORMAT_VERSION", "VideoSettings", "sequence_name", "write_video"]

#: Bumped whenever the bytes written for a seed change.
VIDEO_FORMAT_VERSION = 1
GENERATOR = "sparsetools.synth.write_video"


def sequence_name(sequence: int) -> str:
    return f"seq_{sequence:04d}"


def frame_name(frame: int) -> str:
    return f"{frame:010d}"


@dataclass(frozen=True)
class VideoSettings:
    """What ``write_video`` makes (also recorded in ``video.json``).

    Attributes
    ----------
    seed : int
    sequences : int
    n_frames : int
    image_size : (int, int)
        (W, H) pixels.
    static : bool
    antialias : int
    image_noise : float
        Grey levels.
    """

    seed: int
    sequences: int
    n_frames: int
    image_size: tuple[int, int]
    static: bool = False
    antialias: int = 2
    image_noise: float = 0.0

    def simulator(self, sequence: int) -> VideoSimulator:
        return VideoSimulator(
            self.seed,
            sequence,
            n_frames=self.n_frames,
            image_size=self.image_size,
            static=self.static,
            antialias=self.antialias,
            image_noise=self.image_noise,
        )

    def to_dict(self) -> dict:
        return {
            "seed": self.seed,
            "sequences": self.sequences,
            "frames": self.n_frames,
            "image_size": list(self.image_size),
            "static": self.static,
            "antialias": self.antialias,
            "image_noise_sigma": self.image_noise,
        }


# One simulator per sequence per process (workers reuse it across that sequence's frames).
_SIMULATORS: dict[tuple, VideoSimulator] = {}


def _simulator(settings: VideoSettings, sequence: int) -> VideoSimulator:
    key = (settings, sequence)
    if key not in _SIMULATORS:
        _SIMULATORS.clear()
        _SIMULATORS[key] = settings.simulator(sequence)
    return _SIMULATORS[key]


def _write_frame(task: tuple[VideoSettings, int, int, str, bool]) -> int:
    """Simulate and write one frame; returns its LiDAR point count."""
    settings, sequence, k, root, overwrite = task
    sim = _simulator(settings, sequence)
    f = sim.frame(k)
    out = Path(root) / sequence_name(sequence)
    name = frame_name(k)
    write_image(out / "image_2" / f"{name}.png", f.image, overwrite=overwrite)
    write_velodyne_bin(out / "velodyne" / f"{name}.bin", f.points, overwrite=overwrite)
    _write_npy(out / "velodyne_ring" / f"{name}.npy", f.ring, overwrite=overwrite)
    write_depth_png(out / "depth_gt" / f"{name}.png", f.depth, overwrite=overwrite)
    mask = f.moving_mask.astype(np.uint8) * np.uint8(255)
    _write_mask(out / "moving_mask" / f"{name}.png", mask, overwrite=overwrite)
    write_kitti_object_calib(out / "calib" / f"{name}.txt", sim.calibration, overwrite=overwrite)
    write_pose_matrix(out / "poses" / f"{name}.txt", f.T_world_from_cam, overwrite=overwrite)
    return int(f.points.shape[0])


def _write_mask(path: Path, mask: np.ndarray, *, overwrite: bool) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(mask, dtype=np.uint8))
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 PNG
        raise OutputError(f"{path}: OpenCV failed to encode the mask")
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(buf.tobytes())


def _write_npy(path: Path, array: np.ndarray, *, overwrite: bool) -> None:
    with atomic_path(path, overwrite=overwrite) as tmp, open(tmp, "wb") as fh:
        np.save(fh, np.ascontiguousarray(array), allow_pickle=False)


def _write_json(path: Path, obj, *, overwrite: bool) -> None:
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(json.dumps(obj, indent=1) + "\n", encoding="utf-8")


def _scene_record(sim: VideoSimulator, settings: VideoSettings, lidar_points: list[int]) -> dict:
    rig = sim.rig
    p = sim.params
    counts: dict[str, int] = {}
    for o in sim.street.objects:
        counts[o["kind"]] = counts.get(o["kind"], 0) + 1
    return {
        "generator": GENERATOR,
        "sparsetools_version": __version__,
        "format_version": VIDEO_FORMAT_VERSION,
        "seed": settings.seed,
        "sequence": p.sequence,
        "name": sequence_name(p.sequence),
        "frames": settings.n_frames,
        "frame_names": [frame_name(k) for k in range(settings.n_frames)],
        "frame_rate_hz": FRAME_RATE_HZ,
        "static": settings.static,
        "antialias": settings.antialias,
        "image_noise_sigma": settings.image_noise,
        "conventions": {
            "poses": "T_world_from_sensor, world = frame 0's camera (x right, y down, "
            "z forward); poses_velodyne.txt uses the same world, so line k equals "
            "T_world_from_cam[k] @ T_cam_from_velo",
            "scene_frame": "gravity-aligned: x along the street's start, y left, z up; the "
            "ground is z = grade * x; street coordinates s (along the centre line) and l "
            "(left of it)",
            "depth": "camera z, metres; 0 = sky or beyond 250 m",
            "moving_mask": "255 where a pixel's centre or colour samples see a moving car or "
            "a walking person",
            "shading": "Lambertian sun + hemisphere ambient, textures fixed to surfaces, no "
            "specular, haze, vignetting or exposure change",
        },
        "params": p.to_dict(),
        "camera": {
            "width": rig.width,
            "height": rig.height,
            "K": rig.K.tolist(),
            "height_above_road_m": p.rig.camera_height_m,
            "pitch_down_deg": p.rig.camera_pitch_deg,
            "max_render_depth_m": 400.0,
            "max_truth_depth_m": 250.0,
        },
        "lidar": {
            "model": "HDL-64E-like, instantaneous revolution at the frame's pose",
            "height_above_road_m": p.rig.lidar_height_m,
            "laser_elevations_deg": [round(float(e), 6) for e in rig.laser_elevations_deg],
            "azimuth_steps": rig.azimuth_steps,
            "scan_order": "laser by laser (0 = highest), each a full turn of increasing "
            "azimuth from straight ahead",
            "min_range_m": rig.lidar_min_range,
            "max_range_m": rig.lidar_max_range,
            "range_noise_sigma_m": rig.lidar_range_noise,
            "reflectance_noise_sigma": rig.reflectance_noise,
        },
        "T_cam_from_velo": sim.T_cam_from_velo.tolist(),
        "T_base_from_cam": sim.T_base_from_cam.tolist(),
        "T_base_from_velo": sim.T_base_from_velo.tolist(),
        "T_scene_from_world": sim.T_scene_from_world.tolist(),
        "ego": [
            {
                "frame": k,
                "time_s": e.time_s,
                "distance_m": round(e.distance_m, 9),
                "speed_mps": round(e.speed_mps, 9),
                "s_m": round(e.s_m, 9),
                "l_m": round(e.l_m, 9),
            }
            for k, e in enumerate(sim.ego)
        ],
        "street": {
            "s_range_m": [round(v, 6) for v in sim.s_range],
            "kinds": list(KIND_NAMES),
            "object_counts": counts,
            "objects": sim.street.objects,
        },
        "actors": [a.to_dict() for a in sim.actors],
        "lidar_points": lidar_points,
    }


def write_video(
    out_dir: str | os.PathLike,
    *,
    seed: int = 0,
    sequences: int = 1,
    n_frames: int = 30,
    image_size: tuple[int, int] = (416, 128),
    static: bool = False,
    antialias: int = 2,
    image_noise: float = 0.0,
    workers: int = 1,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Write ``sequences`` synthetic street videos of ``n_frames`` frames each.

    Parameters
    ----------
    out_dir : path-like
        Output folder (created); see the module docstring for the layout.
    seed : int
        Global seed; sequence i is drawn from (seed, i).
    sequences, n_frames : int
        >= 1 each.
    image_size : (W, H)
        Pixels, >= 16 each.
    static : bool
        No moving cars, nobody walks.
    antialias : int
        Colour samples per pixel along each axis (1-4).
    image_noise : float
        Gaussian image noise, grey levels (0 = none).
    workers : int
        Processes simulating frames in parallel (same bytes for any number).
    overwrite : bool
        Write into a non-empty folder, replacing files of the same names.
    progress : callable(n_done), optional
        Called as frames complete.

    Returns
    -------
    dict
        Summary: out_dir, seed, sequences (names), frames, image_size, files_written,
        lidar_points (per sequence, per frame), seconds.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ParameterError(f"workers must be an integer >= 1, got {workers!r}")
    if isinstance(sequences, bool) or not isinstance(sequences, int) or sequences < 1:
        raise ParameterError(f"sequences must be an integer >= 1, got {sequences!r}")
    settings = VideoSettings(
        seed=seed,
        sequences=sequences,
        n_frames=n_frames,
        image_size=tuple(image_size),
        static=bool(static),
        antialias=antialias,
        image_noise=float(image_noise) if isinstance(image_noise, (int, float)) else image_noise,
    )
    # Validates every argument (ParameterError) before anything is written.
    first = settings.simulator(0)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a folder")
    if out.is_dir() and not overwrite and any(out.iterdir()):
        raise OutputError(f"{out} is not empty (use --overwrite to replace its files)")

    start = time.perf_counter()
    tasks = [
        (settings, i, k, str(out), overwrite) for i in range(sequences) for k in range(n_frames)
    ]
    if workers == 1:
        _SIMULATORS.clear()
        _SIMULATORS[(settings, 0)] = first
        counts = []
        for n, task in enumerate(tasks):
            counts.append(_write_frame(task))
            if progress is not None:
                progress(n + 1)
    else:
        counts = []
        with ProcessPoolExecutor(max_workers=workers) as pool:
            chunk = max(1, n_frames // workers)
            for n, c in enumerate(pool.map(_write_frame, tasks, chunksize=chunk)):
                counts.append(c)
                if progress is not None:
                    progress(n + 1)
    names = []
    per_sequence = []
    for i in range(sequences):
        sim = first if i == 0 else settings.simulator(i)
        seq = out / sequence_name(i)
        poses = np.stack([sim.T_world_from_cam(k) for k in range(n_frames)])
        write_kitti_poses(seq / "poses.txt", poses, overwrite=overwrite)
        write_kitti_poses(
            seq / "poses_velodyne.txt",
            np.stack([sim.T_world_from_velo(k) for k in range(n_frames)]),
            overwrite=overwrite,
        )
        write_times(seq / "times.txt", [e.time_s for e in sim.ego], overwrite=overwrite)
        points = counts[i * n_frames : (i + 1) * n_frames]
        _write_json(seq / "scene.json", _scene_record(sim, settings, points), overwrite=overwrite)
        names.append(sequence_name(i))
        per_sequence.append(points)
    record = {
        "generator": GENERATOR,
        "sparsetools_version": __version__,
        "format_version": VIDEO_FORMAT_VERSION,
        **settings.to_dict(),
        "sequence_names": names,
    }
    _write_json(out / "video.json", record, overwrite=overwrite)
    per_frame_files = 7  # image, scan, rings, depth, mask, calib, 4x4 pose
    return {
        "out_dir": str(out),
        "seed": settings.seed,
        "sequences": names,
        "frames": n_frames,
        "image_size": f"{settings.image_size[0]}x{settings.image_size[1]}",
        "static": settings.static,
        "files_written": sequences * (n_frames * per_frame_files + 4) + 1,
        "lidar_points": per_sequence,
        "seconds": round(time.perf_counter() - start, 3),
    }
