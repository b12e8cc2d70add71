"""Static objects of a video street: buildings, sidewalk slabs, parked cars, trees, lamps,
signs and hedges, drawn per 50 m block of street arc length from
``(seed, STREAM_BLOCK, sequence, block)``, so the street around a frame does not depend on how
many frames are made.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .primitives import SHAPE_BOX, SHAPE_CYLINDER, SHAPE_ELLIPSOID, Primitives
from .roads import Road, rotation_z
from .video_params import STREAM_BLOCK, SequenceParams, sequence_rng
from .video_parts import (
    FACADE_PALETTES,
    I3,
    K_BUILDING,
    K_CANOPY,
    K_HEDGE,
    K_LAMP,
    K_POLE,
    K_SIDEWALK,
    K_SIGN,
    K_TRUNK,
    R_PLATE,
    SIGN_COLOURS,
    car_parts,
    car_reflectance,
    place,
)

__all__ = ["BLOCK_M", "BLOCK_OFFSET", "StaticStreet", "static_street"]

BLOCK_M = 50.0
#: Added to block numbers so that SeedSequence entropy stays non-negative behind s = 0.
BLOCK_OFFSET = 1 << 20


@dataclass(frozen=True)
class StaticStreet:
    """The static primitives of a stretch of street and one record per object.

    Attributes
    ----------
    primitives : Primitives
    objects : list of dict
        JSON-ready: kind, object id, street coordinates, size, colour.
    """

    primitives: Primitives
    objects: list


def _upright_box(
    road: Road,
    s0,
    s1,
    l0,
    l1,
    z_top_above,
    kind,
    oid,
    colour,
    refl,
    *,
    above: float = 0.0,
    extra=(0.0, 0.0, 0.0, 0.0),
) -> tuple:
    """An upright box over street rectangle [s0, s1] x [l0, l1], from below the ground up to
    ``z_top_above`` over the ground at its centre (``above``: base height, e.g. the curb)."""
    sm, lm = 0.5 * (s0 + s1), 0.5 * (l0 + l1)
    x, y, psi = road.point(sm, lm)
    R = rotation_z(psi)
    half_x, half_y = 0.5 * (s1 - s0), 0.5 * abs(l1 - l0)
    # Lowest ground under the footprint (the plane z = grade x), so nothing floats.
    reach_x = abs(half_x * math.cos(psi)) + abs(half_y * math.sin(psi))
    z_lo = min(road.ground_z(x - reach_x), road.ground_z(x + reach_x)) - 0.3
    z_hi = road.ground_z(x, above=above) + z_top_above
    c = (x, y, 0.5 * (z_lo + z_hi))
    half = (half_x, half_y, 0.5 * (z_hi - z_lo))
    return (c, R, half, SHAPE_BOX, kind, oid, colour, refl, False, extra)


def _sidewalk_rows(params: SequenceParams, s_min: float, s_max: float) -> list[tuple]:
    """Sidewalk slabs (top at the curb height, 0.5 m deep) on both sides, as segments that
    follow the curve (overlapping a little there so no wedge opens between them)."""
    road, st = params.road, params.street
    rows = []
    l_in, width = st.road_half_width_m, st.sidewalk_width_m
    # Segment ends on a fixed grid of arc length (25 m, 3 m on the arc: chord error < 1 cm
    # at R >= 120 m), so the slabs around a place do not depend on the street's extent.
    step = 3.0 if road.curved else 25.0
    edges = [
        float(v) for v in np.arange(math.floor(s_min / step), math.ceil(s_max / step) + 1) * step
    ]
    if road.curved:
        s_a, s_b = road.turn_start_m - 25.0, road.turn_start_m + road.turn_length_m + 25.0
        edges = [e for e in edges if s_a <= e <= s_b or e % 25.0 == 0.0]
    grow = 0.5 * abs(road.curvature_per_m) * 3.0 * (l_in + width) + 0.02 if road.curved else 0.0
    n = road.ground_normal
    depth = 0.5
    for side in (-1, 1):
        lc = side * (l_in + 0.5 * width)
        for i in range(len(edges) - 1):
            s0, s1 = edges[i] - grow, edges[i + 1] + grow
            sm = 0.5 * (s0 + s1)
            x, y, psi = road.point(sm, lc)
            R = road.surface_rotation(psi)
            # Centre half-way between the slab top (curb height) and its bottom.
            mid = 0.5 * (st.curb_height_m - depth)
            c = np.array([x, y, road.ground_z(x)]) + mid * n
            half = (0.5 * (s1 - s0), 0.5 * width, 0.5 * (st.curb_height_m + depth))
            rows.append(
                (c, R, half, SHAPE_BOX, K_SIDEWALK, -(10 + side), (0.6, 0.6, 0.58), 0.3, False)
            )
    return rows


def _block_rows(params: SequenceParams, block: int) -> tuple[list[tuple], list[dict]]:
    rng = sequence_rng(params.seed, STREAM_BLOCK, params.sequence, block + BLOCK_OFFSET)
    road, st = params.road, params.street
    b0, b1 = block * BLOCK_M, (block + 1) * BLOCK_M
    rows: list[tuple] = []
    objects: list[dict] = []
    palette = FACADE_PALETTES[st.facade_palette]
    oid = block * 1000

    def record(kind, s, l, size, colour, heading=0.0):
        objects.append(
            {
                "kind": kind,
                "object_id": oid,
                "s_m": round(s, 4),
                "l_m": round(l, 4),
                "heading_rad": round(heading, 6),
                "size_m": [round(float(v), 4) for v in size],
                "colour": [round(float(c), 3) for c in colour],
            }
        )

    curb = st.road_half_width_m
    walk_edge = curb + st.sidewalk_width_m
    for side in (-1, 1):
        # Buildings fill the block, with the odd alley.
        s = b0
        while s < b1 - 1.0:
            if rng.random() < st.alley_probability:
                s += float(rng.uniform(1.5, 4.0))
                continue
            width = min(float(rng.uniform(*st.building_width_m)), b1 - s)
            front = st.building_line_m + float(rng.uniform(0.0, 1.0))
            depth = float(rng.uniform(*st.building_depth_m))
            height = float(rng.uniform(*st.building_height_m))
            colour = np.clip(
                np.array(palette[int(rng.integers(len(palette)))]) * rng.uniform(0.88, 1.06),
                0.0,
                1.0,
            )
            window = (
                float(rng.uniform(2.2, 3.4)),
                float(rng.uniform(2.8, 3.6)),
                float(rng.uniform(0.35, 0.6)),
                float(rng.uniform(0.4, 0.6)),
            )
            rows.append(
                _upright_box(
                    road,
                    s,
                    s + width,
                    side * front,
                    side * (front + depth),
                    height,
                    K_BUILDING,
                    oid,
                    tuple(colour),
                    float(rng.uniform(0.3, 0.5)),
                    extra=window,
                )
            )
            record(
                "building",
                s + width / 2,
                side * (front + depth / 2),
                (width, depth, height),
                colour,
            )
            objects[-1]["window"] = [round(w, 4) for w in window]
            oid += 1
            s += width
        # Hedges along the front yards.
        if st.hedges and st.setback_m >= 1.2:
            h = float(rng.uniform(0.8, 1.4))
            w = float(rng.uniform(0.5, 0.8))
            l0 = walk_edge + 0.2
            for s0 in np.arange(b0, b1, 10.0):
                if rng.random() < 0.2:
                    continue
                green = (0.16, float(rng.uniform(0.3, 0.4)), 0.12)
                rows.append(
                    _upright_box(
                        road, s0, s0 + 9.5, side * l0, side * (l0 + w), h, K_HEDGE, oid, green, 0.4
                    )
                )
                record("hedge", s0 + 4.75, side * (l0 + w / 2), (9.5, w, h), green)
                oid += 1
        # Parked cars, facing the traffic of their side.
        s = b0 + float(rng.uniform(0.0, 4.0))
        heading_off = 0.0 if side < 0 else math.pi
        lp = side * (st.lanes_per_direction * st.lane_width_m + 0.5 * st.parking_width_m)
        while True:
            length = float(rng.uniform(3.9, 4.9))
            if s + length > b1 - 0.5:
                break
            if rng.random() < st.parked_car_probability:
                parts, half = car_parts(rng, length)
                l = lp + float(rng.uniform(-0.15, 0.15))
                x, y, psi = road.point(s + length / 2, l)
                R = road.surface_rotation(psi + heading_off)
                rows += place(
                    parts, R, (x, y, road.ground_z(x)), oid, car_reflectance(parts), False
                )
                record("parked_car", s + length / 2, l, 2 * half, parts[0][5], psi + heading_off)
                oid += 1
            s += length + float(rng.uniform(0.8, 3.0))
        # Street trees near the curb.
        trees = []
        if st.tree_spacing_m > 0:
            s = b0 + float(rng.uniform(0.0, st.tree_spacing_m))
            while s < b1:
                trees.append(s)
                l = side * (curb + float(rng.uniform(0.5, 0.8)))
                trunk_h = float(rng.uniform(2.3, 3.6))
                r = float(rng.uniform(0.12, 0.22))
                cx, cy, cz = (
                    float(rng.uniform(1.2, 2.4)),
                    float(rng.uniform(1.2, 2.4)),
                    float(rng.uniform(1.3, 2.6)),
                )
                green = (
                    float(rng.uniform(0.12, 0.25)),
                    float(rng.uniform(0.28, 0.45)),
                    float(rng.uniform(0.08, 0.18)),
                )
                x, y, psi = road.point(s, l)
                R = rotation_z(psi + float(rng.uniform(0.0, math.pi)))
                z0 = road.ground_z(x, above=st.curb_height_m)
                centre_z = max(trunk_h + 0.3 * cz, 2.3 + cz)
                parts = [
                    (
                        (0.0, 0.0, 0.5 * centre_z - 0.2),
                        I3,
                        (r, r, 0.5 * centre_z + 0.2),
                        SHAPE_CYLINDER,
                        K_TRUNK,
                        (0.33, 0.25, 0.18),
                    ),
                    ((0.0, 0.0, centre_z), I3, (cx, cy, cz), SHAPE_ELLIPSOID, K_CANOPY, green),
                ]
                rows += place(parts, R, (x, y, z0), oid, 0.4, False)
                record("tree", s, l, (2 * cx, 2 * cy, centre_z + cz), green)
                oid += 1
                s += st.tree_spacing_m * float(rng.uniform(0.7, 1.3))
        # Street lamps (mast, arm over the road, lamp head), kept clear of the trees.
        s = b0 + float(rng.uniform(0.0, st.lamp_spacing_m))
        while s < b1:
            if all(abs(s - t) > 1.5 for t in trees):
                top = float(rng.uniform(5.0, 8.0))
                arm = float(rng.uniform(1.5, 3.0))
                l = side * (curb + 0.35)
                x, y, psi = road.point(s, l)
                # Local y points from the mast over the road.
                R = rotation_z(psi + (0.0 if side > 0 else math.pi))
                z0 = road.ground_z(x, above=st.curb_height_m)
                grey = (0.42, 0.43, 0.45)
                parts = [
                    (
                        (0.0, 0.0, 0.5 * top - 0.2),
                        I3,
                        (0.09, 0.09, 0.5 * top + 0.2),
                        SHAPE_CYLINDER,
                        K_POLE,
                        grey,
                    ),
                    (
                        (0.0, -0.5 * arm, top - 0.06),
                        I3,
                        (0.05, 0.5 * arm, 0.06),
                        SHAPE_BOX,
                        K_POLE,
                        grey,
                    ),
                    (
                        (0.0, -arm, top - 0.2),
                        I3,
                        (0.3, 0.15, 0.08),
                        SHAPE_BOX,
                        K_LAMP,
                        (0.85, 0.85, 0.8),
                    ),
                ]
                rows += place(parts, R, (x, y, z0), oid, 0.6, False)
                record("lamp", s, l, (0.6, arm, top), grey)
                oid += 1
            s += st.lamp_spacing_m * float(rng.uniform(0.8, 1.2))
        # A traffic sign now and then, facing the traffic of its side.
        if rng.random() < st.sign_probability:
            s = b0 + float(rng.uniform(3.0, BLOCK_M - 3.0))
            if all(abs(s - t) > 1.5 for t in trees):
                l = side * (curb + 0.4)
                x, y, psi = road.point(s, l)
                R = rotation_z(psi + (math.pi if side < 0 else 0.0))
                z0 = road.ground_z(x, above=st.curb_height_m)
                colour = SIGN_COLOURS[int(rng.integers(len(SIGN_COLOURS)))]
                round_plate = rng.random() < 0.5
                plate = (
                    ((0.0, 0.0, 2.45), R_PLATE, (0.3, 0.3, 0.02), SHAPE_CYLINDER, K_SIGN, colour)
                    if round_plate
                    else ((0.0, 0.0, 2.45), I3, (0.02, 0.3, 0.3), SHAPE_BOX, K_SIGN, colour)
                )
                parts = [
                    (
                        (0.06, 0.0, 1.2),
                        I3,
                        (0.035, 0.035, 1.4),
                        SHAPE_CYLINDER,
                        K_POLE,
                        (0.55, 0.56, 0.58),
                    ),
                    plate,
                ]
                rows += place(parts, R, (x, y, z0), oid, 0.9, False)
                record("sign", s, l, (0.05, 0.6, 2.75), colour)
                oid += 1
    return rows, objects


def static_street(params: SequenceParams, s_min: float, s_max: float) -> StaticStreet:
    """Static primitives of every block overlapping ``[s_min, s_max]`` plus the sidewalks."""
    rows = _sidewalk_rows(params, s_min, s_max)
    objects: list[dict] = []
    for block in range(math.floor(s_min / BLOCK_M), math.floor(s_max / BLOCK_M) + 1):
        r, o = _block_rows(params, block)
        rows += r
        objects += o
    return StaticStreet(primitives=Primitives.from_rows(rows), objects=objects)
