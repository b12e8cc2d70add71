"""Camera and LiDAR of the video scenes: anti-aliased rendering, depth, moving mask, scans.

Camera: every pixel is shaded as the mean of an ``antialias x antialias`` grid of rays
(colour), plus its centre ray (depth, and with the others the moving mask). Shading is
``albedo * (ambient * (0.7 + 0.3 n_z) + sun * max(n . sun_dir, 0))``: Lambertian plus a
hemisphere ambient term, no specular, no haze, no exposure change, no vignetting, so a
static surface looks the same from every viewpoint. The sky depends only on the ray
direction (a gradient with elevation and a glow around the sun).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .primitives import BVH, HIT_NONE, Primitives, cast, rotate
from .roads import Road
from .video_params import LightParams, StreetParams
from .video_surfaces import Textures, surface_hits, surfaces

__all__ = ["CameraModel", "FrameScene", "render_camera", "scan_lidar"]

#: Surfaces are rendered up to this camera depth (farther: sky); depth truth stops at 250 m.
CAMERA_RENDER_M = 400.0
CAMERA_TRUTH_M = 250.0
#: Rays per chunk (bounds the memory of a large image).
CHUNK = 1 << 18


@dataclass(frozen=True)
class FrameScene:
    """What the sensors see at one frame: the street and the actors at their places.

    Attributes
    ----------
    road : Road
    street : StreetParams
    light : LightParams
    textures : Textures
    primitives : Primitives
        Static primitives followed by the actors' (indices of hits count through both).
    bvhs : tuple of BVH
        The static BVH and the actors' BVH, in the same order.
    """

    road: Road
    street: StreetParams
    light: LightParams
    textures: Textures
    primitives: Primitives
    bvhs: tuple[BVH, ...]

    @property
    def ground(self) -> tuple[np.ndarray, float]:
        return self.road.ground_normal, 0.0


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with its per-pixel ray offsets.

    Attributes
    ----------
    width, height : int
    K : (3, 3) float64
    antialias : int
        Colour samples per pixel along each axis (1 = the pixel centre only).
    """

    width: int
    height: int
    K: np.ndarray
    antialias: int = 2

    def rays(self, du: float, dv: float) -> np.ndarray:
        """(H*W, 3) camera-frame rays through pixel centres shifted by (du, dv) pixels,
        row-major, with unit z (so the ray parameter of a hit is its depth)."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        x = (np.arange(self.width, dtype=np.float64) + du - cx) / fx
        y = (np.arange(self.height, dtype=np.float64) + dv - cy) / fy
        d = np.empty((self.height, self.width, 3))
        d[:, :, 0] = x[None, :]
        d[:, :, 1] = y[:, None]
        d[:, :, 2] = 1.0
        return d.reshape(-1, 3)

    @property
    def sample_offsets(self) -> list[tuple[float, float]]:
        n = self.antialias
        steps = [(k + 0.5) / n - 0.5 for k in range(n)]
        return [(du, dv) for dv in steps for du in steps]


def _sky(light: LightParams, d_unit: np.ndarray) -> np.ndarray:
    """Sky colour per unit ray direction (N, 3)."""
    horizon = np.asarray(light.sky_horizon)
    zenith = np.asarray(light.sky_zenith)
    e = np.clip(d_unit[:, 2] * 2.2, 0.0, 1.0)
    sky = horizon[None, :] * (1.0 - e[:, None]) + zenith[None, :] * e[:, None]
    sun = light.sun_direction
    g = np.maximum(d_unit[:, 0] * sun[0] + d_unit[:, 1] * sun[1] + d_unit[:, 2] * sun[2], 0.0)
    g = g * g
    g = g * g
    g = g * g  # g^8: a soft glow around the sun
    return sky + (0.35 * light.sun_intensity * g)[:, None] * np.asarray(light.sun_glow)[None, :]


def _shade(scene: FrameScene, origin, d, *, fx: float, spacing: float):
    """Colour (N, 3) in [0, 1+], hits, for camera rays ``d`` (scene frame, unit camera z)."""
    hits = cast(origin, d, scene.bvhs, ground=scene.ground, t_max=CAMERA_RENDER_M)
    geo = surface_hits(scene.primitives, hits, origin, d, scene.road.ground_normal)
    length = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    unit = d / length[:, None]
    n = geo.normals
    cos_inc = np.abs(n[:, 0] * unit[:, 0] + n[:, 1] * unit[:, 1] + n[:, 2] * unit[:, 2])
    # Patch of surface one ray stands for: range x pixel angle / samples, stretched by slant.
    footprint = np.where(hits.hit, hits.t * length, 0.0) * (spacing / fx)
    footprint = footprint / np.maximum(cos_inc, 0.15)
    albedo, _ = surfaces(
        scene.primitives,
        hits,
        geo,
        scene.road,
        scene.street,
        scene.textures,
        footprint=np.maximum(footprint, 1e-4),
    )
    light = scene.light
    sun = light.sun_direction
    lambert = np.maximum(n[:, 0] * sun[0] + n[:, 1] * sun[1] + n[:, 2] * sun[2], 0.0)
    irradiance = light.ambient * (0.7 + 0.3 * n[:, 2]) + light.sun_intensity * lambert
    colour = albedo * irradiance[:, None]
    sky = ~hits.hit
    colour[sky] = _sky(light, unit[sky])
    return colour, hits


def render_camera(
    scene: FrameScene,
    camera: CameraModel,
    T_scene_from_cam: np.ndarray,
    *,
    noise: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast one camera frame.

    Parameters
    ----------
    scene : FrameScene
    camera : CameraModel
    T_scene_from_cam : (4, 4) float64
        Camera pose in the scene frame, metres.
    noise : (H*W, 3) float64, optional
        Added to the colour (in [0, 1] units) before rounding.

    Returns
    -------
    image : (H, W, 3) uint8
        RGB, mean of the ``antialias^2`` samples, rounded.
    depth : (H, W) float32, metres
        Camera z of the surface at each pixel centre, 0 for sky and beyond 250 m.
    moving : (H, W) bool
        Some sample (or the centre ray) of the pixel sees a moving object.
    """
    R = T_scene_from_cam[:3, :3]
    origin = T_scene_from_cam[:3, 3]
    n_pix = camera.width * camera.height
    offsets = camera.sample_offsets
    colour = np.zeros((n_pix, 3))
    moving = np.zeros(n_pix, dtype=bool)
    depth = np.zeros(n_pix, dtype=np.float32)
    spacing = 1.0 / camera.antialias
    fx = float(camera.K[0, 0])
    for du, dv in offsets + ([] if camera.antialias % 2 else [(0.0, 0.0)]):
        shade = (du, dv) in offsets
        d_all = rotate(R, camera.rays(du, dv))
        for a in range(0, n_pix, CHUNK):
            d = d_all[a : a + CHUNK]
            if shade:
                c, hits = _shade(scene, origin, d, fx=fx, spacing=spacing)
                colour[a : a + CHUNK] += c
            else:
                hits = cast(origin, d, scene.bvhs, ground=scene.ground, t_max=CAMERA_RENDER_M)
            idx = hits.index
            hit_prim = idx >= 0
            mv = np.zeros(idx.shape[0], dtype=bool)
            mv[hit_prim] = scene.primitives.moving[idx[hit_prim]]
            moving[a : a + CHUNK] |= mv
            if du == 0.0 and dv == 0.0:
                truth = hits.hit & (hits.t <= CAMERA_TRUTH_M)
                depth[a : a + CHUNK] = np.where(truth, hits.t, 0.0).astype(np.float32)
    colour /= len(offsets)
    if noise is not None:
        colour += noise
    image = np.rint(np.clip(colour, 0.0, 1.0) * 255.0).astype(np.uint8)
    h, w = camera.height, camera.width
    return image.reshape(h, w, 3), depth.reshape(h, w), moving.reshape(h, w)


def scan_lidar(
    scene: FrameScene,
    directions_velo: np.ndarray,
    T_scene_from_velo: np.ndarray,
    *,
    azimuth_steps: int,
    min_range: float,
    max_range: float,
    range_noise: float,
    reflectance_noise: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """One instantaneous revolution of the LiDAR at its own pose.

    Parameters
    ----------
    directions_velo : (L * azimuth_steps, 3) float64
        Unit rays in scan order (Velodyne frame), laser by laser.
    T_scene_from_velo : (4, 4) float64
    rng : numpy.random.Generator
        Range and reflectance noise (drawn for every ray, hit or not).

    Returns
    -------
    points : (N, 4) float32
        x, y, z (Velodyne frame, metres) and reflectance in [0, 1], scan order.
    ring : (N,) uint8
        Laser index, 0 = highest.
    """
    R = T_scene_from_velo[:3, :3]
    origin = T_scene_from_velo[:3, 3]
    d = rotate(R, directions_velo)
    hits = cast(origin, d, scene.bvhs, ground=scene.ground, t_max=max_range)
    geo = surface_hits(scene.primitives, hits, origin, d, scene.road.ground_normal)
    _, refl = surfaces(
        scene.primitives, hits, geo, scene.road, scene.street, scene.textures, footprint=None
    )
    n_rays = d.shape[0]
    r = hits.t + rng.normal(0.0, range_noise, n_rays)
    refl_noise = rng.normal(0.0, reflectance_noise, n_rays)
    keep = (hits.index != HIT_NONE) & (hits.t >= min_range) & (r > 0)
    n = geo.normals
    cos_inc = np.abs(n[:, 0] * d[:, 0] + n[:, 1] * d[:, 1] + n[:, 2] * d[:, 2])
    reflectance = np.clip(refl * (0.55 + 0.45 * cos_inc) + refl_noise, 0.0, 1.0)
    idx = np.nonzero(keep)[0]
    points = np.empty((idx.size, 4), dtype=np.float32)
    points[:, :3] = directions_velo[idx] * r[idx, None]
    points[:, 3] = reflectance[idx]
    ring = (idx // azimuth_steps).astype(np.uint8)
    return points, ring
