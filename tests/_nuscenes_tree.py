"""A nuScenes v1.0-mini-style tree for scene-0061's first sample, from the real files.

Real, verbatim: the tables calibrated_sensor, sensor, sample, scene, log
(../shared/data/real/nuscenes-radar/v1.0-mini), the RADAR_FRONT key frame of the sample
(rebuilt .pcd of the verbatim CSV dump), the CAM_FRONT jpg, the LIDAR_TOP .pcd.bin
(nuscenes-mmdet3d-demo), the radar key frame's ego pose (quoted values).

DERIVED here, because ego_pose.json and sample_data.json are not available: the sample_data
records of those three files, and the ego poses at the camera and LiDAR times, computed from the
mmdetection3d info (``ego2global_at_lidar``, ``lidar2ego``, ``lidar2cam``, which includes the
ego motion between the two times) so that the tree's chain equals the info's.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

SAMPLE = "ca9a282c9e77460f8360f564131a8af5"
RADAR_TS = 1532402927664178
RADAR_CS = "f4d2a6c281f34a7eb8bb033d82321f79"
LOG = "n015-2018-07-24-11-22-45+0800"


def _quaternion(R: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return [float(w), float(x), float(y), float(z)]


def _pose(token: str, T: np.ndarray, ts: int) -> dict:
    return {"token": token, "timestamp": ts, "rotation": _quaternion(T[:3, :3]),
            "translation": [float(v) for v in T[:3, 3]]}  # fmt: skip


CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
           "CAM_BACK_RIGHT")  # fmt: skip


def build_tree(real: Path, root: Path, *, cameras: tuple[str, ...] = ("CAM_FRONT",)) -> dict:
    """Write the tree under ``root``; return the names and matrices a test needs.

    ``cameras``: the camera channels the sample has (default CAM_FRONT only, the tree as it
    always was); the other five are the demo's real images with their calibration and the
    ego pose at each camera's time derived from the info as CAM_FRONT's is. The return value
    then has ``cameras``: per channel its ``file``, ``ego_cam`` (ego -> global at the camera's
    time), ``cam2ego`` and ``lidar2cam``."""
    radar_dir, demo = real / "nuscenes-radar", real / "nuscenes-mmdet3d-demo"
    tables = root / "v1.0-mini"
    tables.mkdir(parents=True)
    for name in ("calibrated_sensor", "sensor", "sample", "scene", "log"):
        shutil.copy(radar_dir / "v1.0-mini" / f"{name}.json", tables / f"{name}.json")
    info = json.loads((demo / "calib_derived_from_pkl.json").read_text())
    cam = info["cameras"]["CAM_FRONT"]
    channel = {s["token"]: s["channel"] for s in json.loads((tables / "sensor.json").read_text())}
    cs = json.loads((tables / "calibrated_sensor.json").read_text())

    def cs_token(ch: str, match) -> str:
        return next(r["token"] for r in cs if channel[r["sensor_token"]] == ch and match(r))

    cam_cs = cs_token(
        "CAM_FRONT",
        lambda r: (
            r["camera_intrinsic"] and abs(r["camera_intrinsic"][0][0] - cam["cam2img"][0][0]) < 1e-3
        ),
    )
    lidar_cs = cs_token("LIDAR_TOP", lambda r: abs(r["translation"][0] - 0.943713) < 1e-6)
    radar_file = f"{LOG}__RADAR_FRONT__{RADAR_TS}.pcd"
    cam_file, lidar_file = cam["file"], info["lidar"]["file"]
    cam_ts = round(cam["timestamp_s"] * 1e6)
    lidar_ts = round(info["lidar_timestamp_s"] * 1e6)
    for folder, name, src in (
        ("RADAR_FRONT", radar_file, radar_dir / "scene-0061" / "radar_front_pcd_RECONSTRUCTED"),
        ("CAM_FRONT", cam_file, radar_dir / "scene-0061" / "cam_front"),
        ("LIDAR_TOP", lidar_file, demo),
    ):
        (root / "samples" / folder).mkdir(parents=True, exist_ok=True)
        shutil.copy(src / name, root / "samples" / folder / name)

    ego_lidar = np.array(info["ego2global_at_lidar"], dtype=np.float64)
    lidar2ego = np.array(info["lidar"]["lidar2ego"], dtype=np.float64)
    lidar2cam = np.array(cam["lidar2cam"], dtype=np.float64)
    cam2ego = np.array(cam["cam2ego"], dtype=np.float64)
    ego_cam = ego_lidar @ lidar2ego @ np.linalg.inv(lidar2cam) @ np.linalg.inv(cam2ego)
    radar_pose = json.loads(
        (radar_dir / "scene-0061" / f"ego_pose_RADAR_FRONT_{RADAR_TS}_DERIVED.json").read_text()
    )
    poses = [
        {k: radar_pose[k] for k in ("token", "timestamp", "rotation", "translation")},
        _pose("derived-ego-cam", ego_cam, cam_ts),
        _pose("derived-ego-lidar", ego_lidar, lidar_ts),
    ]
    common = {"sample_token": SAMPLE, "is_key_frame": True, "prev": "", "next": ""}
    sample_data = [
        {"token": "derived-sd-radar", "ego_pose_token": radar_pose["token"],
         "calibrated_sensor_token": RADAR_CS, "filename": f"samples/RADAR_FRONT/{radar_file}",
         "timestamp": RADAR_TS, "width": 0, "height": 0, **common},
        {"token": cam["sample_data_token"], "ego_pose_token": "derived-ego-cam",
         "calibrated_sensor_token": cam_cs, "filename": f"samples/CAM_FRONT/{cam_file}",
         "timestamp": cam_ts, "width": 1600, "height": 900, **common},
        {"token": "derived-sd-lidar", "ego_pose_token": "derived-ego-lidar",
         "calibrated_sensor_token": lidar_cs, "filename": f"samples/LIDAR_TOP/{lidar_file}",
         "timestamp": lidar_ts, "width": 0, "height": 0, **common},
    ]  # fmt: skip
    extra = {}
    for ch in cameras:
        c = info["cameras"][ch]
        c2e = np.array(c["cam2ego"], dtype=np.float64)
        l2c = np.array(c["lidar2cam"], dtype=np.float64)
        e_c = ego_lidar @ lidar2ego @ np.linalg.inv(l2c) @ np.linalg.inv(c2e)
        extra[ch] = {"file": root / "samples" / ch / c["file"], "ego_cam": e_c,
                     "cam2ego": c2e, "lidar2cam": l2c}  # fmt: skip
        if ch == "CAM_FRONT":
            continue
        (root / "samples" / ch).mkdir(parents=True, exist_ok=True)
        shutil.copy(demo / c["file"], root / "samples" / ch / c["file"])
        fx = c["cam2img"][0][0]
        ts = round(c["timestamp_s"] * 1e6)
        token = f"derived-ego-{ch.lower()}"
        poses.append(_pose(token, e_c, ts))
        sample_data.append(
            {"token": c["sample_data_token"], "ego_pose_token": token,
             "calibrated_sensor_token": cs_token(
                 ch, lambda r, fx=fx: r["camera_intrinsic"]
                 and abs(r["camera_intrinsic"][0][0] - fx) < 1e-3),
             "filename": f"samples/{ch}/{c['file']}", "timestamp": ts, "width": 1600,
             "height": 900, **common}
        )  # fmt: skip
    note = {"_note": "DERIVED for the sparsetools tests (see tests/_nuscenes_tree.py)"}
    (tables / "ego_pose.json").write_text(json.dumps([{**p, **note} for p in poses]))
    (tables / "sample_data.json").write_text(json.dumps([{**s, **note} for s in sample_data]))
    return {
        "radar": root / "samples" / "RADAR_FRONT" / radar_file,
        "camera": root / "samples" / "CAM_FRONT" / cam_file,
        "lidar": root / "samples" / "LIDAR_TOP" / lidar_file,
        "ego_cam": ego_cam,
        "lidar2cam": lidar2cam,
        "lidar2ego": lidar2ego,
        "ego_lidar": ego_lidar,
        **({"cameras": extra} if tuple(cameras) != ("CAM_FRONT",) else {}),
    }
