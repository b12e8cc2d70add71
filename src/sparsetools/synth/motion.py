"""Ego motion of the video scenes and the mounting of camera and LiDAR on the ego car.

Frames are ``FRAME_RATE_HZ`` = 10 Hz apart. The ego car's *base* frame is x forward, y left,
z up (the ground normal), origin on the road under the LiDAR; the speed profile is constant
cruise, then optionally constant deceleration to a stop (analytic, so every pose is exact);
the lateral offset follows a cosine blend between lane centres over the lane-change distance;
the heading is the road heading plus the angle of the lateral motion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .roads import Road
from .video_params import DriveParams, RigParams, StreetParams

__all__ = [
    "FRAME_RATE_HZ",
    "R_BASE_FROM_CAM_LEVEL",
    "EgoState",
    "ego_state",
    "mounting",
    "pose",
    "rigid_inverse",
    "travelled",
]

FRAME_RATE_HZ = 10.0
#: Camera axes (x right, y down, z forward) in base axes (x forward, y left, z up).
R_BASE_FROM_CAM_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def pose(R: np.ndarray, t) -> np.ndarray:
    """(4, 4) rigid transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform."""
    R = T[:3, :3]
    return pose(R.T, -(R.T @ T[:3, 3]))


def travelled(drive: DriveParams, time_s: float) -> tuple[float, float]:
    """Distance driven since frame 0 and the speed at ``time_s`` (metres, m/s)."""
    v0 = drive.speed_mps
    if v0 <= 0.0:
        return 0.0, 0.0
    tb = drive.brake_time_s
    if time_s <= tb:
        return v0 * time_s, v0
    a = drive.deceleration_mps2
    tau = min(time_s - tb, v0 / a)
    return v0 * tb + v0 * tau - 0.5 * a * tau * tau, max(v0 - a * tau, 0.0)


def _lateral(street: StreetParams, drive: DriveParams, distance: float) -> tuple[float, float]:
    """Lateral offset of the ego (metres) and its derivative along the road (dl/ds)."""
    l_a = street.lane_centre_m(drive.lane)
    if drive.lane_change_to < 0:
        return l_a, 0.0
    l_b = street.lane_centre_m(drive.lane_change_to)
    u = (distance - drive.lane_change_start_m) / drive.lane_change_length_m
    if u <= 0.0:
        return l_a, 0.0
    if u >= 1.0:
        return l_b, 0.0
    blend = 0.5 - 0.5 * math.cos(math.pi * u)
    slope = 0.5 * math.pi * math.sin(math.pi * u) / drive.lane_change_length_m
    return l_a + (l_b - l_a) * blend, (l_b - l_a) * slope


@dataclass(frozen=True)
class EgoState:
    """The ego car at one frame.

    Attributes
    ----------
    time_s : float
    distance_m : float
        Driven since frame 0.
    speed_mps : float
    s_m, l_m : float
        Street coordinates of the base origin.
    T_scene_from_base : (4, 4) float64
        Base frame (x forward, y left, z ground normal) in the scene frame, metres.
    """

    time_s: float
    distance_m: float
    speed_mps: float
    s_m: float
    l_m: float
    T_scene_from_base: np.ndarray


def ego_state(road: Road, street: StreetParams, drive: DriveParams, frame: int) -> EgoState:
    """Exact pose of the ego car at ``frame`` (time ``frame / FRAME_RATE_HZ``)."""
    time_s = frame / FRAME_RATE_HZ
    distance, speed = travelled(drive, time_s)
    s = drive.start_s_m + distance
    l, dl_ds = _lateral(street, drive, distance)
    x, y, psi = road.point(s, l)
    # Tangent of the path: (1 - k l) along the centre line plus dl/ds across it.
    k = (
        road.curvature_per_m
        if road.curved and road.turn_start_m < s < (road.turn_start_m + road.turn_length_m)
        else 0.0
    )
    yaw = psi + math.atan2(dl_ds, 1.0 - k * l)
    R = road.surface_rotation(yaw)
    z = road.ground_z(x)
    return EgoState(
        time_s=time_s,
        distance_m=distance,
        speed_mps=speed,
        s_m=s,
        l_m=l,
        T_scene_from_base=pose(R, (x, y, z)),
    )


def mounting(rig: RigParams) -> tuple[np.ndarray, np.ndarray]:
    """``(T_base_from_cam, T_base_from_velo)``, each (4, 4) float64, metres.

    The LiDAR is level with the car (its axes are the base axes) at ``lidar_height_m``; the
    camera is ``camera_ahead_m`` ahead of it at ``camera_height_m``, pitched down by
    ``camera_pitch_deg`` about its x axis.
    """
    a = math.radians(rig.camera_pitch_deg)
    c, s = math.cos(a), math.sin(a)
    # Rotating about camera x by -pitch turns the optical axis (cam z) towards cam +y (down).
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])
    T_base_from_cam = pose(
        R_BASE_FROM_CAM_LEVEL @ Rx, (rig.camera_ahead_m, 0.0, rig.camera_height_m)
    )
    T_base_from_velo = pose(np.eye(3), (0.0, 0.0, rig.lidar_height_m))
    return T_base_from_cam, T_base_from_velo
