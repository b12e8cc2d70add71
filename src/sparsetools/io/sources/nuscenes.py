"""nuScenes samples as frames: sequence = scene name, frame = sample token.

Each frame carries the key sweep of a sensor (``RADAR_FRONT``, ``LIDAR_TOP``...), up to
``sweeps - 1`` earlier sweeps with their transforms into the key sweep's sensor frame (each
with its own ego pose), and the calibration of the chain key sensor -> ego (sensor time) ->
global -> ego (camera time) -> camera, with the camera's intrinsics. The tables are the
frame's extra inputs (their identity decides resume).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ...calibration import Calibration
from ...errors import FormatError, UsageError
from .frame import Frame, FrameKey, Sweep

__all__ = ["nuscenes_camera_poses", "nuscenes_frames"]

log = logging.getLogger(__name__)


def _flat(T: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(T, dtype=np.float64).reshape(-1))


def nuscenes_frames(
    root: str | os.PathLike,
    *,
    version: str = "v1.0-mini",
    sensor: str = "RADAR_FRONT",
    camera: str = "CAM_FRONT",
    sweeps: int = 5,
    scenes: tuple[str, ...] | None = None,
    night: str = "any",
) -> list[Frame]:
    """One frame per sample holding key frames of both ``sensor`` and ``camera``.

    Parameters
    ----------
    root : path-like
        nuScenes root (tables in ``root/<version>/``, files relative to ``root``).
    version, sensor, camera : str
    sweeps : int
        Sweeps of ``sensor`` merged per frame (the key sweep and the previous ones).
    scenes : tuple of str, optional
        Keep only these scene names.
    night : {"any", "only", "exclude"}
        Keep every scene, only night scenes, or only day scenes (nuScenes marks night scenes
        with "night" in the scene description).

    Raises
    ------
    FormatError
        Unreadable tables, or no sample with both key frames.
    """
    from ...ops.projection import nuscenes_T_cam_from_sensor, rigid_inverse
    from ...validate import check_choice, check_int_range
    from ..nuscenes import NuScenesTables

    check_int_range(sweeps, "sweeps", low=1)
    check_choice(night, "night", ("any", "only", "exclude"))
    if sensor == camera:
        raise UsageError(f"{sensor} is the camera (--camera): give a radar or LiDAR channel",
                         param="sensor")  # fmt: skip
    tables = NuScenesTables(root, version)
    modality = {s.get("channel"): s.get("modality") for s in tables.sensors()}
    if modality.get(sensor) == "camera":
        raise UsageError(f"{sensor} is a camera, not a depth sensor: give a RADAR_* or LIDAR_TOP "
                         "channel", param="sensor")  # fmt: skip
    frames: list[Frame] = []
    missing = 0
    for sample in tables.samples():
        scene = tables.scene_name(sample)
        if scenes is not None and scene not in scenes:
            continue
        if night != "any":
            description = str((tables.scene(sample) or {}).get("description", ""))
            if ("night" in description.lower()) != (night == "only"):
                continue
        try:
            key_sd = tables.sample_data(sample["token"], sensor)
            cam = tables.sample_data(sample["token"], camera)
        except FormatError:
            missing += 1
            continue
        T_global_from_key = tables.T_global_from_ego(key_sd) @ tables.T_ego_from_sensor(key_sd)
        T_cam_from_key = nuscenes_T_cam_from_sensor(
            tables.T_ego_from_sensor(key_sd),
            tables.T_global_from_ego(key_sd),
            tables.T_global_from_ego(cam),
            tables.T_ego_from_sensor(cam),
        )
        chain = []
        for k, sd in enumerate(tables.sweeps(key_sd, sweeps)):
            if k == 0:
                continue
            T = rigid_inverse(T_global_from_key) @ (
                tables.T_global_from_ego(sd) @ tables.T_ego_from_sensor(sd)
            )
            chain.append(Sweep(tables.path(sd), _flat(T)))
        w, h = cam.get("width") or None, cam.get("height") or None
        calibration = Calibration(
            K=tables.intrinsics(cam),
            T_cam_from_sensor=T_cam_from_key,
            width=w,
            height=h,
            source=f"nuScenes {version} sample {sample['token']} {sensor}->{camera}",
        )
        frames.append(
            Frame(
                key=FrameKey(scene, sample["token"]),
                cloud=tables.path(key_sd),
                sweeps=tuple(chain),
                image=tables.path(cam),
                calibration=calibration,
                pose=_flat(T_global_from_key),
                timestamp=(
                    None if key_sd.get("timestamp") is None else float(key_sd["timestamp"]) * 1e-6
                ),
                extra_inputs=tuple(Path(p) for p in tables.table_files),
            )
        )
    if not frames:
        which = f" of scenes {', '.join(scenes)}" if scenes else ""
        if night != "any":
            which += " at night" if night == "only" else " by day"
        raise FormatError(
            f"{root}: no sample{which} of {version} has key frames of both {sensor} and {camera}"
        )
    if missing:
        log.warning("%d sample(s) lack %s or %s and were left out", missing, sensor, camera)
    return frames


def nuscenes_camera_poses(
    root: str | os.PathLike, *, version: str = "v1.0-mini", camera: str = "CAM_FRONT"
) -> dict[str, tuple[tuple[float, ...], tuple[float, ...]]]:
    """Per sample (``<scene>/<sample token>``): the camera's ``T_ego_cam`` (camera -> ego, its
    calibrated_sensor) and ``T_world_ego`` (ego -> global, the ego pose at the camera's
    timestamp), each row-major 4x4 flattened, metres. Samples without the camera are absent."""
    from ..nuscenes import NuScenesTables

    tables = NuScenesTables(root, version)
    out = {}
    for sample in tables.samples():
        try:
            cam = tables.sample_data(sample["token"], camera)
        except FormatError:
            continue
        key = str(FrameKey(tables.scene_name(sample), sample["token"]))
        out[key] = (_flat(tables.T_ego_from_sensor(cam)), _flat(tables.T_global_from_ego(cam)))
    return out
