"""KITTI-like sensor rig: pinhole camera, HDL-64E-like spinning LiDAR, front radar.

Frames: the Velodyne frame is x forward, y left, z up; the camera frame x right, y down,
z forward; the radar frame x forward, y left, z up. In the synthetic world the ego never
turns, so the Velodyne axes are the world axes and a pose is the Velodyne's position.

Everything that ends up in a file is computed with IEEE-exact arithmetic (sums, products,
``math`` trigonometry on small tables, no BLAS), so the same seed gives the same bytes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..calibration import Calibration, resize_intrinsics
from ..errors import ParameterError
from ..io.nuscenes import RADAR_FIELDS
from .geometry import cast_rays
from .street import (
    KIND_BUILDING,
    KIND_CAR_BODY,
    KIND_CAR_CABIN,
    KIND_POLE,
    RADAR_MATERIALS,
    StreetLayout,
    TextureBank,
    surface_properties,
)

__all__ = [
    "KITTI_HEIGHT",
    "KITTI_K",
    "KITTI_WIDTH",
    "Rig",
    "hdl64_elevations_deg",
    "radar_sweep",
    "render_camera",
    "scan_lidar",
]

KITTI_WIDTH, KITTI_HEIGHT = 1242, 375
#: Intrinsics of KITTI's P2, 2011_09_26 (pixels).
KITTI_K = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
#: Rotation taking Velodyne axes to camera axes: velo x -> cam z, velo y -> -cam x, velo z -> -cam y.
R_CAM_FROM_VELO = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
#: The Velodyne origin in camera coordinates: 0.08 m above and 0.27 m behind the camera.
T_CAM_FROM_VELO_TRANSLATION = np.array([0.0, -0.08, -0.27])

_FIELD = {name: i for i, name in enumerate(RADAR_FIELDS)}


def hdl64_elevations_deg() -> np.ndarray:
    """(64,) float64 laser elevations in degrees, laser 0 highest.

    Upper block: 32 lasers from +2.0 to -8.33 deg (~1/3 deg apart); lower block: 32 lasers
    from -8.83 to -24.8 deg (~1/2 deg apart), as on the HDL-64E of KITTI.
    """
    return np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])


def _kitti_intrinsics(width: int, height: int) -> np.ndarray:
    """KITTI's K scaled to ``width``; ``height`` crops (or extends) rows evenly about it."""
    scale = width / KITTI_WIDTH
    K = resize_intrinsics(KITTI_K, scale)
    # Calibration.resized would give round(375 s) rows; other heights crop/extend both edges.
    top = 0.5 * (max(1, round(KITTI_HEIGHT * scale)) - height)
    K[1, 2] -= top
    return K


@dataclass(frozen=True)
class Rig:
    """Sensor models and mounting of the synthetic KITTI-like car.

    Attributes
    ----------
    width, height : int
        Camera image size, pixels.
    K : (3, 3) float64
        Camera intrinsics (KITTI P2 scaled to the width; see :meth:`kitti`).
    T_cam_from_velo : (4, 4) float64
        Velodyne -> camera.
    T_velo_from_radar : (4, 4) float64
        Radar -> Velodyne (translation only: both frames are x forward, y left, z up).
    lidar_height : float, metres
        Velodyne above the ground (the camera is 0.08 m lower, at 1.65 m).
    laser_elevations_deg : (64,) float64
        Laser 0 is the highest.
    azimuth_steps : int
        LiDAR firings per laser and revolution.
    lidar_max_range, lidar_min_range : float, metres
    lidar_range_noise : float, metres
        Standard deviation of the Gaussian range noise.
    reflectance_noise : float
        Standard deviation of the reflectance noise.
    camera_max_depth : float, metres
        Farther surfaces are shaded as haze and get no ground-truth depth.
    radar_fov_deg, radar_rays, radar_max_range : float, int, float
        Horizontal fan of +-``radar_fov_deg``, ``radar_rays`` candidate directions.
    radar_range_noise : float, metres
    radar_azimuth_noise_deg : float
    radar_returns : (int, int)
        Returns per sweep drawn uniformly in this closed range.
    radar_clutter : (int, int)
        Clutter points per sweep drawn uniformly in this closed range.
    radar_sweeps : int
        Sweeps per frame (0 = key frame, newest).
    """

    width: int
    height: int
    K: np.ndarray
    T_cam_from_velo: np.ndarray
    T_velo_from_radar: np.ndarray
    lidar_height: float = 1.73
    laser_elevations_deg: np.ndarray = field(default_factory=hdl64_elevations_deg)
    azimuth_steps: int = 2000
    lidar_max_range: float = 120.0
    lidar_min_range: float = 1.0
    lidar_range_noise: float = 0.015
    reflectance_noise: float = 0.02
    camera_max_depth: float = 250.0
    radar_fov_deg: float = 60.0
    radar_rays: int = 481
    radar_max_range: float = 100.0
    radar_range_noise: float = 0.2
    radar_azimuth_noise_deg: float = 1.0
    radar_returns: tuple[int, int] = (30, 60)
    radar_clutter: tuple[int, int] = (2, 6)
    radar_sweeps: int = 5

    @classmethod
    def kitti(cls, width: int = KITTI_WIDTH, height: int = KITTI_HEIGHT) -> Rig:
        """The KITTI-like rig with a ``width`` x ``height`` camera.

        The intrinsics are KITTI's scaled by ``s = width / 1242`` (``f' = s f``,
        ``c' = s (c + 0.5) - 0.5``, as :meth:`Calibration.resized`); a height other than
        ``round(375 s)`` crops or extends the image evenly at top and bottom.
        """
        if int(width) != width or int(height) != height or width < 16 or height < 16:
            raise ParameterError(f"image size must be at least 16x16 pixels, got {width}x{height}")
        T = np.eye(4)
        T[:3, :3] = R_CAM_FROM_VELO
        T[:3, 3] = T_CAM_FROM_VELO_TRANSLATION
        T_radar = np.eye(4)
        # Front bumper: 2.5 m ahead of the Velodyne, 0.5 m above the ground.
        T_radar[:3, 3] = (2.5, 0.0, 0.5 - 1.73)
        return cls(
            width=int(width),
            height=int(height),
            K=_kitti_intrinsics(width, height),
            T_cam_from_velo=T,
            T_velo_from_radar=T_radar,
        )

    # -- calibrations ---------------------------------------------------------------------------
    @property
    def P(self) -> np.ndarray:
        """(3, 4) projection matrix ``[K | 0]``."""
        return np.hstack([self.K, np.zeros((3, 1))])

    @property
    def calibration(self) -> Calibration:
        """Velodyne -> camera calibration (written as the KITTI calib file)."""
        return Calibration(
            K=self.K,
            T_cam_from_sensor=self.T_cam_from_velo,
            width=self.width,
            height=self.height,
            P=self.P,
            source="synthetic KITTI-like rig",
        )

    @property
    def T_cam_from_radar(self) -> np.ndarray:
        return self.T_cam_from_velo @ self.T_velo_from_radar

    @property
    def radar_calibration(self) -> Calibration:
        """Radar -> camera calibration."""
        return Calibration(
            K=self.K,
            T_cam_from_sensor=self.T_cam_from_radar,
            width=self.width,
            height=self.height,
            P=self.P,
            source="synthetic front radar",
        )

    @property
    def camera_in_velo(self) -> np.ndarray:
        """(3,) camera centre in Velodyne coordinates, metres."""
        R = self.T_cam_from_velo[:3, :3]
        return -(R.T @ self.T_cam_from_velo[:3, 3])

    @property
    def radar_in_velo(self) -> np.ndarray:
        return self.T_velo_from_radar[:3, 3].copy()

    # -- ray bundles (constant per rig) ---------------------------------------------------------
    @cached_property
    def camera_directions(self) -> np.ndarray:
        """(H*W, 3) float64 ray of each pixel centre in Velodyne axes, with unit camera z.

        Row-major over (v, u), so the ray parameter of a hit is the camera depth.
        """
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        x = (np.arange(self.width, dtype=np.float64) - cx) / fx
        y = (np.arange(self.height, dtype=np.float64) - cy) / fy
        cam = np.empty((self.height, self.width, 3))
        cam[:, :, 0] = x[None, :]
        cam[:, :, 1] = y[:, None]
        cam[:, :, 2] = 1.0
        cam = cam.reshape(-1, 3)
        R = self.T_cam_from_velo[:3, :3]
        # velo = R^T cam, written out elementwise (exact for the axis permutation, no BLAS).
        out = np.zeros_like(cam)
        for j in range(3):
            for k in range(3):
                if R[k, j] != 0.0:
                    out[:, j] += R[k, j] * cam[:, k]
        return out

    @cached_property
    def lidar_directions(self) -> np.ndarray:
        """(64 * azimuth_steps, 3) unit rays in scan order: laser 0 (highest) first.

        Each laser sweeps the full turn in increasing azimuth ``atan2(y, x)``, starting just
        left of straight ahead (0 deg) and coming back to it, as in KITTI's raw ``.bin`` files:
        with azimuth taken in [0, 360) a new laser shows as a jump back of ~360 deg (in
        atan2's (-180, 180] the jump back happens mid-ring, behind the car, as on real scans).
        """
        step = 360.0 / self.azimuth_steps
        az = [math.radians((k + 0.5) * step) for k in range(self.azimuth_steps)]
        el = [math.radians(float(e)) for e in self.laser_elevations_deg]
        ca = np.array([math.cos(a) for a in az])
        sa = np.array([math.sin(a) for a in az])
        ce = np.array([math.cos(e) for e in el])
        se = np.array([math.sin(e) for e in el])
        d = np.empty((len(el), len(az), 3))
        d[:, :, 0] = ce[:, None] * ca[None, :]
        d[:, :, 1] = ce[:, None] * sa[None, :]
        d[:, :, 2] = se[:, None]
        return d.reshape(-1, 3)

    @cached_property
    def radar_azimuths_deg(self) -> np.ndarray:
        return np.linspace(-self.radar_fov_deg, self.radar_fov_deg, self.radar_rays)

    @cached_property
    def radar_directions(self) -> np.ndarray:
        """(radar_rays, 3) horizontal unit rays of the radar fan."""
        a = [math.radians(float(v)) for v in self.radar_azimuths_deg]
        return np.array([[math.cos(v), math.sin(v), 0.0] for v in a]).reshape(-1, 3)

    def to_dict(self) -> dict:
        """JSON-ready description of the rig (written into ``scene.json``)."""
        return {
            "camera": {
                "width": self.width,
                "height": self.height,
                "K": self.K.tolist(),
                "P2": self.P.tolist(),
                "height_above_ground_m": round(self.lidar_height + self.camera_in_velo[2], 6),
                "max_depth_m": self.camera_max_depth,
            },
            "T_cam_from_velo": self.T_cam_from_velo.tolist(),
            "lidar": {
                "model": "HDL-64E-like",
                "height_above_ground_m": self.lidar_height,
                "lasers": len(self.laser_elevations_deg),
                "laser_elevations_deg": [round(float(e), 6) for e in self.laser_elevations_deg],
                "azimuth_steps": self.azimuth_steps,
                "azimuth_start_deg": 180.0 / self.azimuth_steps,
                "azimuth_direction": "increasing atan2(y, x) from straight ahead, one full turn per laser",
                "scan_order": "laser by laser (0 = highest), each a full turn",
                "max_range_m": self.lidar_max_range,
                "min_range_m": self.lidar_min_range,
                "range_noise_sigma_m": self.lidar_range_noise,
                "reflectance_noise_sigma": self.reflectance_noise,
            },
            "radar": {
                "T_velo_from_radar": self.T_velo_from_radar.tolist(),
                "T_cam_from_radar": self.T_cam_from_radar.tolist(),
                "fov_deg": [-self.radar_fov_deg, self.radar_fov_deg],
                "candidate_rays": self.radar_rays,
                "max_range_m": self.radar_max_range,
                "range_noise_sigma_m": self.radar_range_noise,
                "azimuth_noise_sigma_deg": self.radar_azimuth_noise_deg,
                "returns_per_sweep": list(self.radar_returns),
                "clutter_per_sweep": list(self.radar_clutter),
                "sweeps": self.radar_sweeps,
                "ego_motion_between_sweeps": "none (static ego: every sweep pose is identity)",
            },
        }


# -- sensors -----------------------------------------------------------------------------------
_SKY_HORIZON = np.array([0.80, 0.85, 0.92])
_SKY_ZENITH = np.array([0.33, 0.52, 0.82])


def render_camera(
    rig: Rig,
    layout: StreetLayout,
    textures: TextureBank,
    velo_origin: np.ndarray,
    *,
    sun: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the camera image and its dense ground-truth depth.

    Parameters
    ----------
    rig : Rig
    layout : StreetLayout
    textures : TextureBank
    velo_origin : (3,) float, metres
        Velodyne position in the world (the camera sits at ``rig.camera_in_velo`` from it).
    sun : (3,) float
        Unit vector towards the sun (world frame).

    Returns
    -------
    rgb : (H, W, 3) uint8
        Lambertian shading (sun + sky ambient) of textured surfaces, haze with distance,
        a sky gradient where no surface is hit.
    depth : (H, W) float32, metres
        Camera z of the surface seen at each pixel centre; 0 for sky and beyond
        ``rig.camera_max_depth``.
    """
    origin = np.asarray(velo_origin, dtype=np.float64) + rig.camera_in_velo
    d = rig.camera_directions
    hits = cast_rays(origin, d, layout.boxes, t_max=rig.camera_max_depth)
    _, albedo, _ = surface_properties(layout, textures, hits)
    n = hits.normals.astype(np.float64)
    sun = np.asarray(sun, dtype=np.float64)
    lambert = np.maximum(n[:, 0] * sun[0] + n[:, 1] * sun[1] + n[:, 2] * sun[2], 0.0)
    # Hemisphere ambient: faces looking up see more sky than walls do.
    light = 0.32 + 0.12 * n[:, 2] + 0.75 * lambert
    colour = albedo.astype(np.float64) * light[:, None]
    hit = hits.hit
    r = np.where(hit, hits.t, 0.0) / rig.camera_max_depth
    haze = 0.85 * r * r
    colour = colour * (1.0 - haze[:, None]) + _SKY_HORIZON[None, :] * haze[:, None]
    # Sky: gradient with the ray's elevation (world z of the unit ray).
    length = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    s = np.clip(2.5 * d[:, 2] / length, 0.0, 1.0)
    sky = _SKY_HORIZON[None, :] * (1.0 - s[:, None]) + _SKY_ZENITH[None, :] * s[:, None]
    colour = np.where(hit[:, None], colour, sky)
    rgb = np.rint(np.clip(colour, 0.0, 1.0) * 255.0).astype(np.uint8)
    depth = np.where(hit, hits.t, 0.0).astype(np.float32)
    return rgb.reshape(rig.height, rig.width, 3), depth.reshape(rig.height, rig.width)


def scan_lidar(
    rig: Rig,
    layout: StreetLayout,
    textures: TextureBank,
    velo_origin: np.ndarray,
    *,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """One revolution of the HDL-64E-like LiDAR.

    Parameters
    ----------
    rig, layout, textures
    velo_origin : (3,) float, metres
        Velodyne position in the world.
    rng : numpy.random.Generator
        Range and reflectance noise.

    Returns
    -------
    points : (N, 4) float32
        x, y, z (Velodyne frame, metres) and reflectance in [0, 1], in scan order (laser by
        laser, highest first, each in increasing azimuth). Rays without a return within
        ``[lidar_min_range, lidar_max_range]`` are dropped.
    ring : (N,) uint8
        Laser index of each point, 0 = highest.
    """
    d = rig.lidar_directions
    hits = cast_rays(
        np.asarray(velo_origin, dtype=np.float64), d, layout.boxes, t_max=rig.lidar_max_range
    )
    _, _, refl = surface_properties(layout, textures, hits)
    n_rays = d.shape[0]
    # Draw noise for every ray (hit or not) so the random stream does not depend on the scene.
    r = hits.t + rng.normal(0.0, rig.lidar_range_noise, n_rays)
    refl_noise = rng.normal(0.0, rig.reflectance_noise, n_rays)
    keep = hits.hit & (hits.t >= rig.lidar_min_range) & (r > 0)
    n = hits.normals.astype(np.float64)
    cos_inc = np.abs(n[:, 0] * d[:, 0] + n[:, 1] * d[:, 1] + n[:, 2] * d[:, 2])
    reflectance = np.clip(refl * (0.55 + 0.45 * cos_inc) + refl_noise, 0.0, 1.0)
    idx = np.nonzero(keep)[0]
    points = np.empty((idx.size, 4), dtype=np.float32)
    points[:, :3] = d[idx] * r[idx, None]
    points[:, 3] = reflectance[idx]
    ring = (idx // rig.azimuth_steps).astype(np.uint8)
    return points, ring


def radar_sweep(
    rig: Rig,
    layout: StreetLayout,
    textures: TextureBank,
    velo_origin: np.ndarray,
    *,
    rng: np.random.Generator,
    hits=None,
) -> np.ndarray:
    """One sweep of the front radar, as nuScenes radar points.

    The radar is a single horizontal fan (z = 0 in the radar frame, 0.5 m above the ground)
    that returns only on walls, cars and poles. A random subset of the candidate directions
    (cars weighted 3x, poles 2x, walls 1x) becomes returns, with Gaussian range and azimuth
    noise; a few clutter points are added, about half of them flagged invalid.

    Parameters
    ----------
    rig, layout, textures
    velo_origin : (3,) float, metres
        Velodyne position in the world.
    rng : numpy.random.Generator
    hits : RayHits, optional
        The fan already cast from this position (sweeps of one frame share it).

    Returns
    -------
    (M, 18) float64
        Columns in :data:`sparsetools.io.nuscenes.RADAR_FIELDS` order, radar frame
        (x forward, y left, z up, metres). Real returns: ``dyn_prop = 1`` (stationary),
        ``ambig_state = 3``, ``invalid_state = 0``, so the devkit's default filters keep them.
    """
    if hits is None:
        hits = cast_radar(rig, layout, velo_origin)
    material, _, _ = surface_properties(layout, textures, hits)
    cand = np.nonzero(hits.hit & np.isin(material, RADAR_MATERIALS) & (hits.t >= 1.0))[0]
    kind = layout.kind[hits.index[cand]]
    weight = np.select(
        [(kind == KIND_CAR_BODY) | (kind == KIND_CAR_CABIN), kind == KIND_POLE], [3.0, 2.0], 1.0
    )
    lo, hi = rig.radar_returns
    n_want = int(rng.integers(lo, hi + 1))
    m = min(n_want, cand.size)
    chosen = (
        np.sort(rng.choice(cand.size, size=m, replace=False, p=weight / weight.sum()))
        if m
        else np.zeros(0, dtype=np.int64)
    )
    ray = cand[chosen]
    kind = kind[chosen]
    rng_r = hits.t[ray] + rng.normal(0.0, rig.radar_range_noise, m)
    az = rig.radar_azimuths_deg[ray] + rng.normal(0.0, rig.radar_azimuth_noise_deg, m)
    real = np.zeros((m, len(RADAR_FIELDS)))
    _polar_to_xy(real, rng_r, az)
    real[:, _FIELD["dyn_prop"]] = 1
    rcs = np.where(
        kind == KIND_BUILDING,
        rng.uniform(5.0, 25.0, m),
        np.where(kind == KIND_POLE, rng.uniform(-5.0, 5.0, m), rng.uniform(0.0, 15.0, m)),
    )
    real[:, _FIELD["rcs"]] = np.round(rcs * 2.0) / 2.0  # ARS 408 reports RCS in 0.5 dBsm steps
    vel = rng.normal(0.0, 0.05, (m, 2))
    real[:, _FIELD["vx"]] = vel[:, 0]
    real[:, _FIELD["vy"]] = vel[:, 1]
    real[:, _FIELD["vx_comp"]] = vel[:, 0]  # ego static: compensated = raw
    real[:, _FIELD["vy_comp"]] = vel[:, 1]
    real[:, _FIELD["is_quality_valid"]] = 1
    real[:, _FIELD["ambig_state"]] = 3
    real[:, _FIELD["x_rms"]] = rng.integers(2, 6, m)
    real[:, _FIELD["y_rms"]] = rng.integers(3, 8, m)
    real[:, _FIELD["invalid_state"]] = 0
    real[:, _FIELD["pdh0"]] = 1
    real[:, _FIELD["vx_rms"]] = rng.integers(2, 5, m)
    real[:, _FIELD["vy_rms"]] = rng.integers(2, 5, m)

    lo, hi = rig.radar_clutter
    k = int(rng.integers(lo, hi + 1))
    clutter = np.zeros((k, len(RADAR_FIELDS)))
    _polar_to_xy(
        clutter, rng.uniform(3.0, 80.0, k), rng.uniform(-rig.radar_fov_deg, rig.radar_fov_deg, k)
    )
    clutter[:, _FIELD["dyn_prop"]] = rng.choice([0, 3, 4, 6], k)
    clutter[:, _FIELD["rcs"]] = np.round(rng.uniform(-10.0, 0.0, k) * 2.0) / 2.0
    vel = rng.normal(0.0, 2.0, (k, 2))
    clutter[:, _FIELD["vx"]] = vel[:, 0]
    clutter[:, _FIELD["vy"]] = vel[:, 1]
    clutter[:, _FIELD["vx_comp"]] = vel[:, 0]
    clutter[:, _FIELD["vy_comp"]] = vel[:, 1]
    clutter[:, _FIELD["is_quality_valid"]] = rng.integers(0, 2, k)
    clutter[:, _FIELD["ambig_state"]] = rng.choice([3, 3, 3, 1, 2], k)
    clutter[:, _FIELD["x_rms"]] = rng.integers(8, 20, k)
    clutter[:, _FIELD["y_rms"]] = rng.integers(8, 20, k)
    # Half the clutter carries a non-zero invalid_state (low RCS, near-field artefact, ...).
    clutter[:, _FIELD["invalid_state"]] = np.where(
        rng.random(k) < 0.5, 0, rng.choice([1, 2, 4, 8, 16], k)
    )
    clutter[:, _FIELD["pdh0"]] = rng.integers(3, 7, k)
    clutter[:, _FIELD["vx_rms"]] = rng.integers(6, 15, k)
    clutter[:, _FIELD["vy_rms"]] = rng.integers(6, 15, k)

    points = np.concatenate([real, clutter])[rng.permutation(m + k)]
    points[:, _FIELD["id"]] = np.arange(m + k)
    return points


def cast_radar(rig: Rig, layout: StreetLayout, velo_origin: np.ndarray):
    """Cast the radar fan from the radar mounted on the car at ``velo_origin`` (world)."""
    origin = np.asarray(velo_origin, dtype=np.float64) + rig.radar_in_velo
    return cast_rays(
        origin, rig.radar_directions, layout.boxes, t_max=rig.radar_max_range, ground_z=None
    )


def _polar_to_xy(out: np.ndarray, r: np.ndarray, az_deg: np.ndarray) -> None:
    a = [math.radians(float(v)) for v in az_deg]
    out[:, _FIELD["x"]] = r * np.array([math.cos(v) for v in a]).reshape(-1)
    out[:, _FIELD["y"]] = r * np.array([math.sin(v) for v in a]).reshape(-1)
    out[:, _FIELD["z"]] = 0.0
