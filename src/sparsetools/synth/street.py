"""Procedural street: layout of boxes, materials, textures, per-hit albedo and reflectance.

World frame: x along the street (the ego drives towards +x), y to the left, z up, metres;
the ground is the plane z = 0. Cross-section of the street (|y|, metres)::

    0 .. 3.5     driving lanes (ego in the right lane, centre y = -1.75), dashed centre line
    3.5 .. 6.0   parking lanes (parked cars), solid edge line at |y| = 3.5
    6.0 .. 30    sidewalk slab, 0.15 m high (the curb is its street-facing side)
    >= 10 .. 11.5  building facades (boxes standing on the sidewalk)

The layout is made of 50 m blocks along x, each drawn from its own seed
``SeedSequence([seed, STREAM_BLOCK, block + BLOCK_OFFSET])``, so the scene around a frame
does not depend on how many frames are generated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import HIT_GROUND, BoxSet, RayHits

__all__ = [
    "BLOCK_LENGTH",
    "EGO_LANE_Y",
    "KIND_NAMES",
    "MATERIAL_NAMES",
    "RADAR_MATERIALS",
    "StreetLayout",
    "TextureBank",
    "make_textures",
    "street_layout",
    "surface_properties",
]

# -- street cross-section (metres) -------------------------------------------------------------
BLOCK_LENGTH = 50.0
LANE_WIDTH = 3.5
ROAD_HALF_WIDTH = 6.0
CURB_HEIGHT = 0.15
SIDEWALK_OUTER = 30.0
BUILDING_LINE = 10.0
PARKING_Y = 4.75
EGO_LANE_Y = -1.75
MARKING_HALF_WIDTH = 0.075
DASH_LENGTH = 3.0
DASH_PERIOD = 9.0
TILE_SIZE = 0.6
#: Added to block numbers so that SeedSequence entropy stays non-negative behind x = 0.
BLOCK_OFFSET = 1 << 20
STREAM_BLOCK = 1
STREAM_TEXTURE = 2

# -- object kinds (one per box) ----------------------------------------------------------------
KIND_SIDEWALK, KIND_BUILDING, KIND_CAR_BODY, KIND_CAR_CABIN, KIND_POLE = range(5)
KIND_NAMES = ("sidewalk", "building", "car_body", "car_cabin", "pole")

# -- surface materials (per hit) ---------------------------------------------------------------
(
    SKY,
    ROAD,
    MARKING,
    SIDEWALK,
    CURB,
    FACADE,
    WINDOW,
    CAR_BODY,
    CAR_GLASS,
    POLE,
    GROUND,
    TYRE,
    CAR_LIGHT,
) = range(13)
MATERIAL_NAMES = (
    "sky",
    "road",
    "marking",
    "sidewalk",
    "curb",
    "facade",
    "window",
    "car_body",
    "car_glass",
    "pole",
    "ground",
    "tyre",
    "car_light",
)
#: Materials a radar sees (metal and walls); road, sidewalk and curb give no radar return.
RADAR_MATERIALS = (FACADE, WINDOW, CAR_BODY, CAR_GLASS, POLE, TYRE, CAR_LIGHT)

_FACADE_COLOURS = np.array(
    [
        (0.78, 0.72, 0.60),
        (0.70, 0.70, 0.68),
        (0.62, 0.33, 0.25),
        (0.88, 0.86, 0.80),
        (0.55, 0.60, 0.62),
        (0.80, 0.62, 0.45),
        (0.66, 0.56, 0.50),
    ]
)
_CAR_COLOURS = np.array(
    [
        (0.85, 0.85, 0.85),
        (0.08, 0.08, 0.09),
        (0.60, 0.62, 0.64),
        (0.65, 0.08, 0.07),
        (0.10, 0.20, 0.55),
        (0.10, 0.30, 0.18),
        (0.85, 0.70, 0.10),
        (0.35, 0.36, 0.38),
    ]
)


@dataclass(frozen=True)
class StreetLayout:
    """Boxes of a stretch of street.

    Attributes
    ----------
    lo, hi : (B, 3) float64, metres
        Box corners in the world frame.
    kind : (B,) int8
        Index into :data:`KIND_NAMES`.
    side : (B,) int8
        -1 right of the street (y < 0), +1 left, 0 on the road itself.
    object_id : (B,) int64
        Physical object (a car's body and cabin share one).
    colour : (B, 3) float32
        Base albedo in [0, 1] (RGB).
    reflectance : (B,) float32
        Base LiDAR reflectance in [0, 1].
    window : (B, 4) float32
        Buildings: column spacing (m), floor height (m), window width and height as
        fractions of them; zero for other kinds.
    boxes : BoxSet
        The same boxes grouped for ray casting.
    """

    lo: np.ndarray
    hi: np.ndarray
    kind: np.ndarray
    side: np.ndarray
    object_id: np.ndarray
    colour: np.ndarray
    reflectance: np.ndarray
    window: np.ndarray
    boxes: BoxSet = field(repr=False)

    def __len__(self) -> int:
        return int(self.lo.shape[0])

    def records(self, *, decimals: int = 3) -> list[dict]:
        """One JSON-ready dict per box (kind, object id, side, corners, colour)."""
        out = []
        for i in range(len(self)):
            out.append(
                {
                    "kind": KIND_NAMES[int(self.kind[i])],
                    "object_id": int(self.object_id[i]),
                    "side": int(self.side[i]),
                    "lo": [round(float(v), decimals) for v in self.lo[i]],
                    "hi": [round(float(v), decimals) for v in self.hi[i]],
                    "colour": [round(float(v), 3) for v in self.colour[i]],
                }
            )
        return out


def _block_rows(seed: int, block: int) -> list[tuple]:
    """Objects of one 50 m block: rows (kind, side, local id, lo, hi, colour, refl, window)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, STREAM_BLOCK, block + BLOCK_OFFSET]))
    x0 = block * BLOCK_LENGTH
    x1 = x0 + BLOCK_LENGTH
    rows: list[tuple] = []
    no_window = (0.0, 0.0, 0.0, 0.0)

    def add(kind, side, oid, lo, hi, colour, refl, window=no_window):
        rows.append((kind, side, oid, lo, hi, tuple(float(c) for c in colour), float(refl), window))

    oid = 0
    for side in (-1, 1):
        # Buildings fill the block along x, with the odd alley between them.
        x = x0
        while x < x1 - 1.0:
            if rng.random() < 0.15:
                x += rng.uniform(1.5, 3.0)
                continue
            width = min(rng.uniform(8.0, 20.0), x1 - x)
            front = BUILDING_LINE + rng.uniform(0.0, 1.5)
            depth = rng.uniform(8.0, 14.0)
            height = rng.uniform(6.0, 24.0)
            colour = _FACADE_COLOURS[rng.integers(len(_FACADE_COLOURS))] * rng.uniform(0.9, 1.05)
            window = (
                float(rng.uniform(2.2, 3.2)),
                float(rng.uniform(2.8, 3.6)),
                float(rng.uniform(0.4, 0.6)),
                float(rng.uniform(0.4, 0.6)),
            )
            y_near, y_far = side * front, side * (front + depth)
            add(
                KIND_BUILDING,
                side,
                oid,
                (x, min(y_near, y_far), 0.0),
                (x + width, max(y_near, y_far), height),
                np.clip(colour, 0, 1),
                rng.uniform(0.3, 0.5),
                window,
            )
            oid += 1
            x += width
        # Parked cars in the parking lane, bumper to bumper with gaps.
        x = x0 + rng.uniform(0.0, 4.0)
        while True:
            if rng.random() < 0.25:
                x += rng.uniform(2.0, 8.0)
                continue
            length = rng.uniform(3.9, 4.8)
            if x + length > x1 - 0.5:
                break
            _add_car(add, rng, side, oid, x, side * PARKING_Y + rng.uniform(-0.15, 0.15), length)
            oid += 1
            x += length + rng.uniform(0.8, 3.0)
        # A street lamp on the sidewalk near the curb, with an arm over the parking lane.
        if rng.random() < 0.8:
            xp = x0 + rng.uniform(5.0, BLOCK_LENGTH - 5.0)
            yp = side * (ROAD_HALF_WIDTH + 0.35)
            top = rng.uniform(5.0, 7.0)
            grey = (0.45, 0.46, 0.48)
            add(
                KIND_POLE,
                side,
                oid,
                (xp - 0.08, yp - 0.08, 0.0),
                (xp + 0.08, yp + 0.08, top),
                grey,
                0.6,
            )
            arm_end = side * (ROAD_HALF_WIDTH - 1.5)
            add(
                KIND_POLE,
                side,
                oid,
                (xp - 0.06, min(yp, arm_end), top - 0.15),
                (xp + 0.06, max(yp, arm_end), top),
                grey,
                0.6,
            )
            oid += 1
    # Now and then a car stopped in the opposite lane (the ego's lane stays free).
    if rng.random() < 0.35:
        xc = x0 + rng.uniform(2.0, BLOCK_LENGTH - 7.0)
        _add_car(
            add, rng, 0, oid, xc, LANE_WIDTH / 2 + rng.uniform(-0.2, 0.2), rng.uniform(3.9, 4.8)
        )
        oid += 1
    return rows


def _add_car(add, rng, side, oid, x, yc, length) -> None:
    width = rng.uniform(1.7, 1.9)
    body_top = 0.2 + rng.uniform(0.75, 0.9)
    colour = _CAR_COLOURS[rng.integers(len(_CAR_COLOURS))]
    luminance = float(colour @ np.array([0.299, 0.587, 0.114]))
    refl = 0.3 + 0.3 * luminance + rng.uniform(0.0, 0.1)
    add(
        KIND_CAR_BODY,
        side,
        oid,
        (x, yc - width / 2, 0.2),
        (x + length, yc + width / 2, body_top),
        colour,
        refl,
    )
    c0 = x + length * rng.uniform(0.2, 0.3)
    c1 = x + length * rng.uniform(0.75, 0.85)
    add(
        KIND_CAR_CABIN,
        side,
        oid,
        (c0, yc - width / 2 + 0.08, body_top),
        (c1, yc + width / 2 - 0.08, body_top + rng.uniform(0.45, 0.6)),
        colour,
        refl,
    )


def street_layout(seed: int, x_min: float, x_max: float) -> StreetLayout:
    """The boxes of the street between ``x_min`` and ``x_max`` (whole blocks, plus sidewalks).

    Parameters
    ----------
    seed : int
        Scene seed (>= 0).
    x_min, x_max : float, metres
        Stretch of street needed; every block overlapping it is included, and the two
        sidewalk slabs span exactly ``[x_min, x_max]``.

    Returns
    -------
    StreetLayout
        Boxes ordered for ray casting (grouped by kind and side, then along x).
    """
    first = math.floor(x_min / BLOCK_LENGTH)
    last = math.floor(x_max / BLOCK_LENGTH)
    rows = []
    for block in range(first, last + 1):
        for kind, side, local, lo, hi, colour, refl, window in _block_rows(seed, block):
            rows.append((kind, side, block * 1000 + local, lo, hi, colour, refl, window))
    for side in (-1, 1):
        y_in, y_out = side * ROAD_HALF_WIDTH, side * SIDEWALK_OUTER
        rows.append(
            (
                KIND_SIDEWALK,
                side,
                -(1000 + side),
                (x_min, min(y_in, y_out), -1.0),
                (x_max, max(y_in, y_out), CURB_HEIGHT),
                (0.58, 0.57, 0.55),
                0.3,
                (0.0, 0.0, 0.0, 0.0),
            )
        )
    # Group by (kind, side) and sweep along x so each group's bounding box stays small.
    rows.sort(key=lambda r: (r[0], r[1], r[3][0], r[2]))
    kind = np.array([r[0] for r in rows], dtype=np.int8)
    side = np.array([r[1] for r in rows], dtype=np.int8)
    lo = np.array([r[3] for r in rows], dtype=np.float64).reshape(-1, 3)
    hi = np.array([r[4] for r in rows], dtype=np.float64).reshape(-1, 3)
    # Cars (body + cabin) and poles (mast + arm) are grouped together with their own kind.
    group_key = kind.astype(np.int64) * 4 + side + 1
    group_key[kind == KIND_CAR_CABIN] = KIND_CAR_BODY * 4 + side[kind == KIND_CAR_CABIN] + 1
    return StreetLayout(
        lo=lo,
        hi=hi,
        kind=kind,
        side=side,
        object_id=np.array([r[2] for r in rows], dtype=np.int64),
        colour=np.array([r[5] for r in rows], dtype=np.float32).reshape(-1, 3),
        reflectance=np.array([r[6] for r in rows], dtype=np.float32),
        window=np.array([r[7] for r in rows], dtype=np.float32).reshape(-1, 4),
        boxes=BoxSet.from_corners(lo, hi, group_size=6, group_key=group_key),
    )


# -- textures ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class TextureBank:
    """Periodic noise tiles sampled by world coordinates.

    Attributes
    ----------
    fine : (S, S) float32
        Grainy noise, zero mean, about unit amplitude (asphalt grain, concrete).
    coarse : (S, S) float32
        Smooth blotches, zero mean, about unit amplitude (wear, stains).
    """

    fine: np.ndarray
    coarse: np.ndarray

    @property
    def size(self) -> int:
        return int(self.fine.shape[0])

    def sample(self, tile: np.ndarray, u: np.ndarray, v: np.ndarray, texel: float) -> np.ndarray:
        """Nearest-texel lookup of ``tile`` at metres ``(u, v)`` with texels of ``texel`` m."""
        s = tile.shape[0]
        i = np.floor(np.asarray(u) / texel).astype(np.int64) % s
        j = np.floor(np.asarray(v) / texel).astype(np.int64) % s
        return tile[j, i]


def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Periodic value noise: random lattice values, smoothstep-interpolated, in [-1, 1]."""
    lattice = rng.uniform(-1.0, 1.0, (cells, cells))
    t = np.arange(size) * (cells / size)
    i0 = np.floor(t).astype(np.int64)
    f = t - i0
    f = f * f * (3.0 - 2.0 * f)
    i1 = (i0 + 1) % cells
    rows0 = lattice[i0][:, i0] * (1 - f)[None, :] + lattice[i0][:, i1] * f[None, :]
    rows1 = lattice[i1][:, i0] * (1 - f)[None, :] + lattice[i1][:, i1] * f[None, :]
    return rows0 * (1 - f)[:, None] + rows1 * f[:, None]


def make_textures(seed: int, *, size: int = 256) -> TextureBank:
    """The seed's texture tiles (``SeedSequence([seed, STREAM_TEXTURE])``)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, STREAM_TEXTURE]))
    white = rng.standard_normal((size, size))
    # A 2x2 periodic box blur keeps the grain but removes single-texel sparkle.
    grain = 0.25 * (
        white + np.roll(white, 1, 0) + np.roll(white, 1, 1) + np.roll(white, (1, 1), (0, 1))
    )
    fine = 0.7 * grain / grain.std() + 0.5 * _value_noise(rng, size, 32)
    coarse = _value_noise(rng, size, 8) + 0.5 * _value_noise(rng, size, 16)
    return TextureBank(fine=fine.astype(np.float32), coarse=coarse.astype(np.float32))


# -- per-hit surface properties ----------------------------------------------------------------
def surface_properties(
    layout: StreetLayout, textures: TextureBank, hits: RayHits
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Material, albedo and LiDAR reflectance at each hit.

    Parameters
    ----------
    layout : StreetLayout
        The boxes the rays were cast against (``hits.index`` indexes them).
    textures : TextureBank
    hits : RayHits

    Returns
    -------
    material : (N,) uint8
        Index into :data:`MATERIAL_NAMES` (``SKY`` on a miss).
    albedo : (N, 3) float32
        Diffuse RGB albedo in [0, 1] (zero on a miss).
    reflectance : (N,) float32
        Noise-free LiDAR reflectance in [0, 1] (zero on a miss).
    """
    n = hits.t.shape[0]
    material = np.zeros(n, dtype=np.uint8)
    albedo = np.zeros((n, 3), dtype=np.float32)
    refl = np.zeros(n, dtype=np.float32)
    p = hits.points
    idx = hits.index
    axis = hits.face // 2

    # Ground: asphalt with markings on the carriageway, plain concrete elsewhere (alleys).
    g = np.nonzero(idx == HIT_GROUND)[0]
    if g.size:
        x, y = p[g, 0], p[g, 1]
        ay = np.abs(y)
        grain = textures.sample(textures.fine, x, y, 0.04)
        blotch = textures.sample(textures.coarse, x, y, 0.25)
        road = ay <= ROAD_HALF_WIDTH
        centre = (ay < MARKING_HALF_WIDTH) & (np.mod(x, DASH_PERIOD) < DASH_LENGTH)
        edge = np.abs(ay - LANE_WIDTH) < MARKING_HALF_WIDTH
        mark = road & (centre | edge)
        grey = 0.30 + 0.05 * grain + 0.03 * blotch
        grey = np.where(mark, 0.82 + 0.04 * grain, np.where(road, grey, grey + 0.08))
        material[g] = np.where(mark, MARKING, np.where(road, ROAD, GROUND))
        albedo[g] = (grey[:, None] * np.array([0.98, 1.0, 1.04])).astype(np.float32)
        refl[g] = np.where(mark, 0.78 + 0.06 * grain, np.where(road, 0.12 + 0.04 * grain, 0.22))

    b_all = np.nonzero(idx >= 0)[0]
    if b_all.size == 0:
        return material, np.clip(albedo, 0, 1), np.clip(refl, 0, 1)
    kind = layout.kind[idx[b_all]]

    # Sidewalk slab: paving tiles on top, curb on the sides.
    s = b_all[kind == KIND_SIDEWALK]
    if s.size:
        x, y = p[s, 0], p[s, 1]
        top = axis[s] == 2
        fx = np.mod(x, TILE_SIZE)
        fy = np.mod(y, TILE_SIZE)
        joint = (np.minimum(fx, TILE_SIZE - fx) < 0.02) | (np.minimum(fy, TILE_SIZE - fy) < 0.02)
        grain = textures.sample(textures.fine, x + p[s, 2], y, 0.03)
        grey = np.where(joint, 0.42, 0.58) + 0.03 * grain
        grey = np.where(top, grey, 0.66 + 0.03 * grain)
        material[s] = np.where(top, SIDEWALK, CURB)
        albedo[s] = (grey[:, None] * np.array([1.0, 0.99, 0.96])).astype(np.float32)
        refl[s] = np.where(top, 0.28, 0.35) + 0.02 * grain

    # Buildings: facade colour with a window grid on the walls; shop windows at street level.
    b = b_all[kind == KIND_BUILDING]
    if b.size:
        _building(layout, textures, p[b], idx[b], axis[b], b, material, albedo, refl)

    c = b_all[(kind == KIND_CAR_BODY) | (kind == KIND_CAR_CABIN)]
    if c.size:
        _car(layout, p[c], idx[c], axis[c], hits.face[c], c, material, albedo, refl)

    q = b_all[kind == KIND_POLE]
    if q.size:
        material[q] = POLE
        albedo[q] = layout.colour[idx[q]]
        refl[q] = layout.reflectance[idx[q]]
    return material, np.clip(albedo, 0, 1), np.clip(refl, 0, 1)


def _building(layout, textures, p, box, axis, out, material, albedo, refl) -> None:
    lo, hi = layout.lo[box], layout.hi[box]
    spacing, floor_h, win_w, win_h = (layout.window[box, k].astype(np.float64) for k in range(4))
    # Horizontal coordinate along the wall: x on walls facing the street, y on side walls.
    along_x = axis == 1
    u = np.where(
        along_x, p[:, 0] - lo[:, 0], np.abs(p[:, 1] - np.where(lo[:, 1] > 0, lo[:, 1], hi[:, 1]))
    )
    wall_len = np.where(along_x, hi[:, 0] - lo[:, 0], hi[:, 1] - lo[:, 1])
    z = p[:, 2]
    n_cols = np.floor(wall_len / spacing)
    offset = 0.5 * (wall_len - n_cols * spacing)
    uc = u - offset
    col = np.floor(uc / spacing)
    ur = uc / spacing - col
    storey = np.floor(z / floor_h)
    vr = z / floor_h - storey
    inside_cols = (uc >= 0) & (col < n_cols)
    wall = axis != 2
    upper = (
        (storey >= 1)
        & (z < hi[:, 2] - 0.8)
        & (np.abs(ur - 0.5) < 0.5 * win_w)
        & (np.abs(vr - 0.5) < 0.5 * win_h)
    )
    shop = (storey == 0) & (z > 0.7) & (z < floor_h - 0.4) & (np.abs(ur - 0.5) < 0.38)
    is_window = wall & inside_cols & (upper | shop)
    # Each window pane gets its own brightness (curtains, lights) from the noise tile.
    pane = textures.coarse[
        (col.astype(np.int64) * 37) % textures.size,
        (storey.astype(np.int64) * 11 + box * 7) % textures.size,
    ]
    glass = np.array([0.14, 0.17, 0.22])[None, :] * (1.0 + 0.35 * pane[:, None])
    grain = textures.sample(textures.fine, p[:, 0] + p[:, 1], z, 0.05)
    wall_rgb = layout.colour[box].astype(np.float64) * (0.95 + 0.05 * grain)[:, None]
    wall_rgb = np.where((axis == 2)[:, None], wall_rgb * 0.7, wall_rgb)
    material[out] = np.where(is_window, WINDOW, FACADE)
    albedo[out] = np.where(is_window[:, None], glass, wall_rgb).astype(np.float32)
    refl[out] = np.where(is_window, 0.06, layout.reflectance[box] + 0.03 * grain)


def _car(layout, p, box, axis, face, out, material, albedo, refl) -> None:
    lo, hi = layout.lo[box], layout.hi[box]
    colour = layout.colour[box].astype(np.float64)
    base_refl = layout.reflectance[box].astype(np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    length = hi[:, 0] - lo[:, 0]
    s = (x - lo[:, 0]) / length
    w = (y - lo[:, 1]) / (hi[:, 1] - lo[:, 1])
    cabin = layout.kind[box] == KIND_CAR_CABIN
    mat = np.full(box.shape[0], CAR_BODY, dtype=np.uint8)
    # Cabin: glass between pillars on the sides, a framed windscreen front and back.
    side_glass = (axis == 1) & (s > 0.06) & (s < 0.94) & (np.abs(s - 0.5) > 0.025)
    end_glass = (axis == 0) & (w > 0.06) & (w < 0.94) & (z < hi[:, 2] - 0.05)
    mat[cabin & (side_glass | end_glass)] = CAR_GLASS
    # Body: wheels on the sides, lights at the ends.
    body = ~cabin
    wheel_r = 0.33
    dz = z - wheel_r
    near_front = (x - (lo[:, 0] + 0.2 * length)) ** 2 + dz**2 < wheel_r**2
    near_back = (x - (hi[:, 0] - 0.2 * length)) ** 2 + dz**2 < wheel_r**2
    mat[body & (axis == 1) & (near_front | near_back)] = TYRE
    light = (
        body & (axis == 0) & (z > hi[:, 2] - 0.3) & (z < hi[:, 2] - 0.1) & ((w < 0.2) | (w > 0.8))
    )
    mat[light] = CAR_LIGHT
    # Right-hand traffic: only cars right of the centre line face +x. Headlights are white.
    heading_pos = layout.side[box] < 0
    front = (face % 2 == 1) == heading_pos
    lamp = np.where(front[:, None], np.array([0.95, 0.93, 0.85]), np.array([0.75, 0.06, 0.05]))
    rgb = colour.copy()
    rgb = np.where((mat == CAR_GLASS)[:, None], np.array([0.10, 0.12, 0.15]), rgb)
    rgb = np.where((mat == TYRE)[:, None], np.array([0.05, 0.05, 0.05]), rgb)
    rgb = np.where((mat == CAR_LIGHT)[:, None], lamp, rgb)
    material[out] = mat
    albedo[out] = rgb.astype(np.float32)
    refl[out] = np.select(
        [mat == CAR_GLASS, mat == TYRE, mat == CAR_LIGHT], [0.10, 0.05, 0.9], base_refl
    )
