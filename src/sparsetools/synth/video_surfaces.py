"""Surface appearance of the video scenes: band-limited textures, albedo, LiDAR reflectance.

Every surface's albedo is a function of the surface point alone (textures are attached to
the street coordinates or to the object's own frame), and the shading is Lambertian sun +
hemisphere ambient, so a static surface has the same colour from every viewpoint. The only
dependence on the view is the anti-aliasing of the procedural textures: octaves finer than
the pixel footprint fade out (their pixel average is their mean), as a camera's pixel
integration would do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .primitives import HIT_GROUND, Hits, Primitives
from .roads import Road
from .video_params import STREAM_TEXTURE, StreetParams, sequence_rng
from .video_parts import (
    K_BUILDING,
    K_CANOPY,
    K_CAR_BODY,
    K_CAR_CABIN,
    K_CLOTHES,
    K_HEDGE,
    K_LAMP,
    K_POLE,
    K_SIDEWALK,
    K_SIGN,
    K_SKIN,
    K_TRUNK,
    K_WHEEL,
)

__all__ = ["SurfaceHits", "Textures", "make_textures", "surface_hits", "surfaces"]

TILE = 64


@dataclass(frozen=True)
class Textures:
    """Periodic lattices of uniform [-1, 1] values, smoothly interpolated when sampled.

    Attributes
    ----------
    a, b, c : (64, 64) float64
    """

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray


def make_textures(seed: int, sequence: int) -> Textures:
    rng = sequence_rng(seed, STREAM_TEXTURE, sequence)
    return Textures(*(rng.uniform(-1.0, 1.0, (TILE, TILE)) for _ in range(3)))


def _octaves(tile, u, v, cells_amps, footprint) -> np.ndarray:
    """Sum of value-noise octaves ``(cell metres, amplitude)`` at surface coordinates (u, v)
    in metres, octaves finer than ``footprint`` faded (None: no fading)."""
    from ._video_kernels import value_noise

    u = np.ascontiguousarray(u, dtype=np.float64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    fp = np.zeros(u.shape[0]) if footprint is None else np.ascontiguousarray(footprint)
    cells = np.array([c for c, _ in cells_amps], dtype=np.float64)
    amps = np.array([a for _, a in cells_amps], dtype=np.float64)
    out = np.empty(u.shape[0])
    value_noise(tile, u, v, cells, amps, fp, out)
    return out


@dataclass(frozen=True)
class SurfaceHits:
    """Geometry at the hit points of a ray bundle.

    Attributes
    ----------
    points : (N, 3) float64
        World hit points, metres (rays that miss: NaN).
    normals : (N, 3) float64
        Unit world normals (zero on a miss).
    local : (N, 3) float64
        Hit point in the primitive's frame (zero for the ground and misses).
    axis : (N,) int64
        Local axis of a box / cylinder-cap face, -1 for curved surfaces, 2 for the ground.
    positive : (N,) bool
        The face's normal points to +axis.
    """

    points: np.ndarray
    normals: np.ndarray
    local: np.ndarray
    axis: np.ndarray
    positive: np.ndarray


def surface_hits(prims: Primitives, hits: Hits, origin, directions, ground_normal) -> SurfaceHits:
    """Hit points, normals and local coordinates (compiled loop over rays)."""
    from ._video_kernels import hit_geometry

    n = hits.t.shape[0]
    points = np.empty((n, 3))
    normals = np.empty((n, 3))
    local = np.empty((n, 3))
    hit_geometry(
        np.ascontiguousarray(origin, dtype=np.float64),
        np.ascontiguousarray(directions, dtype=np.float64),
        hits.t,
        hits.index,
        hits.face,
        prims.centre,
        prims.rotation,
        prims.half,
        np.ascontiguousarray(ground_normal, dtype=np.float64),
        points,
        normals,
        local,
    )
    face = hits.face.astype(np.int64)
    axis = np.where((face >= 0) & (face < 6), face // 2, -1)
    axis[hits.index == HIT_GROUND] = 2
    positive = (face % 2 == 1) | (hits.index == HIT_GROUND)
    return SurfaceHits(points=points, normals=normals, local=local, axis=axis, positive=positive)


def surfaces(
    prims: Primitives,
    hits: Hits,
    geo: SurfaceHits,
    road: Road,
    street: StreetParams,
    textures: Textures,
    *,
    footprint: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Albedo and LiDAR reflectance at each hit.

    Parameters
    ----------
    footprint : (N,) float64 or None
        Size of the surface patch a ray stands for (metres); texture octaves finer than it
        fade out. None (LiDAR): no fading.

    Returns
    -------
    albedo : (N, 3) float64
        RGB in [0, 1] (zero on a miss).
    reflectance : (N,) float64
        Noise-free LiDAR reflectance in [0, 1] (zero on a miss).
    """
    n = hits.t.shape[0]
    albedo = np.zeros((n, 3))
    refl = np.zeros(n)
    fp = footprint
    g = np.nonzero(hits.index == HIT_GROUND)[0]
    if g.size:
        s, l = road.to_street(geo.points[g, 0], geo.points[g, 1])
        a, r = _ground(s, l, street, textures, None if fp is None else fp[g])
        albedo[g] = a
        refl[g] = r
    m = np.nonzero(hits.index >= 0)[0]
    if m.size == 0:
        return np.clip(albedo, 0.0, 1.0), np.clip(refl, 0.0, 1.0)
    idx = hits.index[m]
    kind = prims.kind[idx]
    base = prims.colour[idx].astype(np.float64)
    base_refl = prims.reflectance[idx].astype(np.float64)
    loc = geo.local[m]
    axis = geo.axis[m]
    pos = geo.positive[m]
    fpm = None if fp is None else fp[m]
    a = base.copy()
    r = base_refl.copy()

    def sel(k):
        return np.nonzero(kind == k)[0]

    def sub(x, i):
        return None if x is None else x[i]

    i = np.nonzero(kind == K_SIDEWALK)[0]
    if i.size:
        p = geo.points[m[i]]
        s, l = road.to_street(p[:, 0], p[:, 1])
        a[i], r[i] = _sidewalk(s, l, axis[i], textures, sub(fpm, i))
    i = sel(K_BUILDING)
    if i.size:
        a[i], r[i] = _building(
            prims, idx[i], loc[i], axis[i], base[i], base_refl[i], textures, sub(fpm, i)
        )
    i = np.nonzero((kind == K_CAR_BODY) | (kind == K_CAR_CABIN))[0]
    if i.size:
        a[i], r[i] = _car(prims, idx[i], kind[i], loc[i], axis[i], pos[i], base[i], base_refl[i])
    i = sel(K_WHEEL)
    if i.size:
        hub = (axis[i] == 2) & ((loc[i, 0] ** 2 + loc[i, 1] ** 2) < 0.17**2)
        a[i] = np.where(hub[:, None], 0.45, 0.06)
        r[i] = np.where(hub, 0.5, 0.05)
    for k, amp, cell in (
        (K_POLE, 0.04, 0.2),
        (K_LAMP, 0.03, 0.2),
        (K_TRUNK, 0.18, 0.08),
        (K_HEDGE, 0.25, 0.12),
        (K_CLOTHES, 0.05, 0.1),
        (K_SKIN, 0.0, 1.0),
    ):
        i = sel(k)
        if i.size and amp:
            q = loc[i]
            tex = _octaves(
                textures.b,
                q[:, 0] + q[:, 1],
                q[:, 2],
                ((cell, amp), (4 * cell, 0.5 * amp)),
                sub(fpm, i),
            )
            a[i] = base[i] * (1.0 + tex)[:, None]
    i = sel(K_CANOPY)
    if i.size:
        q = loc[i]
        tex = _octaves(
            textures.c,
            q[:, 0] + 0.6 * q[:, 1],
            q[:, 2] - 0.4 * q[:, 1],
            ((0.12, 0.22), (0.35, 0.22), (1.0, 0.15)),
            sub(fpm, i),
        )
        a[i] = base[i] * (1.0 + tex)[:, None]
    i = sel(K_SIGN)
    if i.size:
        # Face the plate shows to traffic: box +x face, or the +z cap of a round plate.
        front = pos[i] & (
            ((prims.shape[idx[i]] == 0) & (axis[i] == 0))
            | ((prims.shape[idx[i]] == 2) & (axis[i] == 2))
        )
        a[i] = np.where(front[:, None], base[i], 0.5)
        r[i] = np.where(front, 0.9, 0.5)
    albedo[m] = a
    refl[m] = r
    return np.clip(albedo, 0.0, 1.0), np.clip(refl, 0.0, 1.0)


def _ground(s, l, street: StreetParams, textures: Textures, fp) -> tuple[np.ndarray, np.ndarray]:
    """Asphalt with markings on the carriageway; grass or gravel in the yards."""
    al = np.abs(l)
    w = street.lane_width_m
    n_lanes = street.lanes_per_direction
    tex = _octaves(textures.a, s, l, ((0.05, 0.5), (0.22, 0.35), (1.3, 0.25), (6.0, 0.2)), fp)
    asphalt = street.asphalt_grey * (1.0 + 0.18 * tex)
    half_line = 0.06
    dashed = np.mod(s, 9.0) < 3.0
    if n_lanes == 1:
        centre = (al < half_line) & dashed
    else:
        centre = np.abs(al - 0.12) < 0.05  # double solid line
    lanes = (np.abs(al - w) < half_line) & dashed if n_lanes == 2 else np.zeros_like(centre)
    edge = np.abs(al - n_lanes * w) < half_line
    road = al <= street.road_half_width_m
    mark = road & (centre | lanes | edge)
    grey = np.where(mark, 0.78 + 0.05 * tex, asphalt)
    rgb = grey[:, None] * np.array([0.98, 1.0, 1.03])[None, :]
    refl = np.where(mark, 0.75 + 0.05 * tex, 0.12 + 0.03 * tex)
    yard = ~road
    if yard.any():
        ty = _octaves(
            textures.c,
            s[yard],
            l[yard],
            ((0.06, 0.4), (0.3, 0.3), (2.0, 0.3)),
            None if fp is None else fp[yard],
        )
        if street.grass_yards:
            rgb[yard] = np.array([0.20, 0.33, 0.11])[None, :] * (1.0 + 0.35 * ty)[:, None]
            refl[yard] = 0.35 + 0.05 * ty
        else:
            rgb[yard] = np.array([0.52, 0.50, 0.46])[None, :] * (1.0 + 0.15 * ty)[:, None]
            refl[yard] = 0.25 + 0.03 * ty
    return rgb, refl


def _sidewalk(s, l, axis, textures: Textures, fp) -> tuple[np.ndarray, np.ndarray]:
    """Paving tiles (0.5 m, with joints) on top of the slab; plain concrete curb on its sides."""
    tile = 0.5
    fs = np.mod(s, tile)
    fl = np.mod(l, tile)
    dist = np.minimum(np.minimum(fs, tile - fs), np.minimum(fl, tile - fl))
    joint = dist < 0.015
    # A joint narrower than the footprint only darkens its pixel a little (coverage).
    contrast = 0.14 if fp is None else 0.14 * np.clip(0.03 / fp, 0.0, 1.0)
    tex = _octaves(textures.b, s, l, ((0.04, 0.4), (0.25, 0.3), (1.5, 0.2)), fp)
    grey = 0.58 * (1.0 + 0.08 * tex) - np.where(joint, contrast, 0.0)
    grey = np.where(axis == 2, grey, 0.66 * (1.0 + 0.05 * tex))
    rgb = grey[:, None] * np.array([1.0, 0.99, 0.96])[None, :]
    refl = np.where(axis == 2, 0.28, 0.35) + 0.02 * tex
    return rgb, refl


def _building(prims, idx, loc, axis, base, base_refl, textures, fp):
    """Facade colour with a window grid (local frame); shop windows on the ground floor."""
    half = prims.half[idx]
    extra = prims.extra[idx].astype(np.float64)
    spacing, floor_h, win_w, win_h = (extra[:, k] for k in range(4))
    along_x = axis == 1  # walls facing the street (normal along local y)
    u = np.where(along_x, loc[:, 0] + half[:, 0], loc[:, 1] + half[:, 1])
    wall_len = np.where(along_x, 2 * half[:, 0], 2 * half[:, 1])
    z = loc[:, 2] + half[:, 2] - 0.3  # height above the lowest ground under the building
    n_cols = np.floor(wall_len / spacing)
    uc = u - 0.5 * (wall_len - n_cols * spacing)
    col = np.floor(uc / spacing)
    ur = uc / spacing - col
    storey = np.floor(z / floor_h)
    vr = z / floor_h - storey
    wall = axis != 2
    upper = (
        (storey >= 1)
        & (z < 2 * half[:, 2] - 1.2)
        & (np.abs(ur - 0.5) < 0.5 * win_w)
        & (np.abs(vr - 0.5) < 0.5 * win_h)
    )
    shop = (storey == 0) & (z > 0.7) & (z < floor_h - 0.4) & (np.abs(ur - 0.5) < 0.38)
    window = wall & (uc >= 0) & (col < n_cols) & (upper | shop)
    pane = textures.c[(col.astype(np.int64) * 7) % 64, (storey.astype(np.int64) * 5 + idx) % 64]
    glass = np.array([0.12, 0.15, 0.20])[None, :] * (1.0 + 0.4 * pane)[:, None]
    tex = _octaves(
        textures.b, loc[:, 0] + loc[:, 1], loc[:, 2], ((0.08, 0.4), (0.6, 0.4), (3.0, 0.2)), fp
    )
    wall_rgb = base * (1.0 + 0.1 * tex)[:, None]
    wall_rgb = np.where((axis == 2)[:, None], 0.35, wall_rgb)  # roofs
    rgb = np.where(window[:, None], glass, wall_rgb)
    refl = np.where(window, 0.06, base_refl + 0.03 * tex)
    return rgb, refl


def _car(prims, idx, kind, loc, axis, pos, base, base_refl):
    """Paint, glass between pillars on the cabin, head and tail lights on the body ends."""
    half = prims.half[idx]
    s = (loc[:, 0] + half[:, 0]) / (2 * half[:, 0])  # 0 at the back, 1 at the front
    w = (loc[:, 1] + half[:, 1]) / (2 * half[:, 1])
    zr = loc[:, 2] + half[:, 2]
    cabin = kind == K_CAR_CABIN
    side_glass = (axis == 1) & (s > 0.06) & (s < 0.94) & (np.abs(s - 0.5) > 0.03) & (zr > 0.05)
    end_glass = (axis == 0) & (w > 0.07) & (w < 0.93) & (zr < 2 * half[:, 2] - 0.05)
    glass = cabin & (side_glass | end_glass)
    light = (
        (~cabin)
        & (axis == 0)
        & (zr > 2 * half[:, 2] - 0.28)
        & (zr < 2 * half[:, 2] - 0.08)
        & ((w < 0.2) | (w > 0.8))
    )
    lamp = np.where(pos[:, None], np.array([0.95, 0.93, 0.85]), np.array([0.75, 0.06, 0.05]))
    rgb = np.where(glass[:, None], np.array([0.09, 0.11, 0.14]), base)
    rgb = np.where(light[:, None], lamp, rgb)
    refl = np.where(glass, 0.1, np.where(light, 0.9, base_refl))
    return rgb, refl
