"""Parts of the video scenes' objects in their own frames, kinds and colour palettes.

An object's frame is x forward, y left, z up with the origin on the ground under its centre;
a part is ``(centre (3,), rotation (3, 3), half (3,), shape, kind, colour)`` in that frame,
and :func:`place` turns parts into primitive rows at a pose.
"""

from __future__ import annotations

import numpy as np

from .primitives import SHAPE_BOX, SHAPE_CYLINDER, SHAPE_ELLIPSOID

__all__ = [
    "CAR_COLOURS",
    "FACADE_PALETTES",
    "KIND_NAMES",
    "SIGN_COLOURS",
    "car_parts",
    "car_reflectance",
    "pedestrian_parts",
    "place",
]

KIND_NAMES = (
    "sidewalk",
    "building",
    "car_body",
    "car_cabin",
    "wheel",
    "pole",
    "lamp",
    "sign",
    "trunk",
    "canopy",
    "hedge",
    "clothes",
    "skin",
)
(
    K_SIDEWALK,
    K_BUILDING,
    K_CAR_BODY,
    K_CAR_CABIN,
    K_WHEEL,
    K_POLE,
    K_LAMP,
    K_SIGN,
    K_TRUNK,
    K_CANOPY,
    K_HEDGE,
    K_CLOTHES,
    K_SKIN,
) = range(len(KIND_NAMES))


FACADE_PALETTES = (
    ((0.78, 0.72, 0.60), (0.70, 0.70, 0.68), (0.62, 0.33, 0.25), (0.88, 0.86, 0.80)),
    ((0.55, 0.60, 0.62), (0.66, 0.56, 0.50), (0.80, 0.62, 0.45), (0.45, 0.42, 0.40)),
    ((0.92, 0.90, 0.84), (0.85, 0.80, 0.70), (0.75, 0.78, 0.80), (0.90, 0.75, 0.60)),
    ((0.50, 0.28, 0.22), (0.58, 0.36, 0.26), (0.42, 0.40, 0.38), (0.70, 0.60, 0.50)),
)
CAR_COLOURS = (
    (0.85, 0.85, 0.85),
    (0.08, 0.08, 0.09),
    (0.60, 0.62, 0.64),
    (0.65, 0.08, 0.07),
    (0.10, 0.20, 0.55),
    (0.10, 0.30, 0.18),
    (0.85, 0.70, 0.10),
    (0.35, 0.36, 0.38),
)
CLOTHES = (
    (0.15, 0.15, 0.18),
    (0.55, 0.10, 0.10),
    (0.20, 0.30, 0.55),
    (0.80, 0.78, 0.70),
    (0.35, 0.45, 0.25),
    (0.60, 0.50, 0.30),
    (0.45, 0.45, 0.48),
)
SKIN = ((0.85, 0.68, 0.55), (0.65, 0.48, 0.35), (0.45, 0.32, 0.22), (0.92, 0.78, 0.66))
SIGN_COLOURS = ((0.75, 0.08, 0.08), (0.10, 0.25, 0.65), (0.90, 0.90, 0.88), (0.90, 0.72, 0.08))
I3 = np.eye(3)
#: Local z along local y: wheels (cylinders) turn about the car's y axis.
R_WHEEL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: Local z along local x: round sign plates face along x.
R_PLATE = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


def car_parts(rng: np.random.Generator, length: float) -> tuple[list[tuple], np.ndarray]:
    """Body, cabin, four wheels of a car ``length`` m long; also its (3,) half extents."""
    width = float(rng.uniform(1.7, 1.9))
    body_top = 0.25 + float(rng.uniform(0.7, 0.85))
    cabin_top = body_top + float(rng.uniform(0.45, 0.6))
    colour = CAR_COLOURS[int(rng.integers(len(CAR_COLOURS)))]
    c0 = length * (float(rng.uniform(0.2, 0.3)) - 0.5)
    c1 = length * (float(rng.uniform(0.75, 0.82)) - 0.5)
    r = 0.32
    parts = [
        (
            (0.0, 0.0, 0.5 * (0.25 + body_top)),
            I3,
            (length / 2, width / 2, 0.5 * (body_top - 0.25)),
            SHAPE_BOX,
            K_CAR_BODY,
            colour,
        ),
        (
            (0.5 * (c0 + c1), 0.0, 0.5 * (body_top + cabin_top)),
            I3,
            (0.5 * (c1 - c0), width / 2 - 0.08, 0.5 * (cabin_top - body_top)),
            SHAPE_BOX,
            K_CAR_CABIN,
            colour,
        ),
    ]
    for wx in (length / 2 - 0.75, -(length / 2 - 0.75)):
        for wy in (width / 2 - 0.12, -(width / 2 - 0.12)):
            parts.append(
                ((wx, wy, r), R_WHEEL, (r, r, 0.11), SHAPE_CYLINDER, K_WHEEL, (0.05, 0.05, 0.05))
            )
    return parts, np.array([length / 2, width / 2, cabin_top / 2])


def pedestrian_parts(rng: np.random.Generator) -> tuple[list[tuple], np.ndarray]:
    """Legs, torso, arms and head of a person facing local +x; also the half extents."""
    height = float(rng.uniform(1.5, 1.92))
    leg = 0.47 * height
    torso = 0.33 * height
    shirt = CLOTHES[int(rng.integers(len(CLOTHES)))]
    trousers = CLOTHES[int(rng.integers(len(CLOTHES)))]
    skin = SKIN[int(rng.integers(len(SKIN)))]
    hw = float(rng.uniform(0.17, 0.22))  # half shoulder width
    # Feet sink 2 cm into the ground so no gap shows on a slope.
    parts = [
        (
            (0.0, 0.09, 0.5 * leg - 0.01),
            I3,
            (0.07, 0.065, 0.5 * leg + 0.01),
            SHAPE_BOX,
            K_CLOTHES,
            trousers,
        ),
        (
            (0.0, -0.09, 0.5 * leg - 0.01),
            I3,
            (0.07, 0.065, 0.5 * leg + 0.01),
            SHAPE_BOX,
            K_CLOTHES,
            trousers,
        ),
        ((0.0, 0.0, leg + 0.5 * torso), I3, (0.12, hw, 0.5 * torso), SHAPE_BOX, K_CLOTHES, shirt),
        (
            (0.0, hw + 0.05, leg + torso * 0.55),
            I3,
            (0.05, 0.045, 0.42 * torso),
            SHAPE_BOX,
            K_CLOTHES,
            shirt,
        ),
        (
            (0.0, -hw - 0.05, leg + torso * 0.55),
            I3,
            (0.05, 0.045, 0.42 * torso),
            SHAPE_BOX,
            K_CLOTHES,
            shirt,
        ),
    ]
    head = height - leg - torso
    parts.append(
        (
            (0.0, 0.0, leg + torso + 0.5 * head),
            I3,
            (0.095, 0.085, 0.5 * head),
            SHAPE_ELLIPSOID,
            K_SKIN,
            skin,
        )
    )
    return parts, np.array([0.13, hw + 0.1, height / 2])


def place(parts, R: np.ndarray, origin, object_id: int, refl: float, moving: bool) -> list[tuple]:
    """Primitive rows of ``parts`` placed with world-from-object rotation ``R`` at ``origin``."""
    o = np.asarray(origin, dtype=np.float64)
    rows = []
    for centre, R_local, half, shape, kind, colour in parts:
        c = o + R @ np.asarray(centre, dtype=np.float64)
        rows.append((c, R @ R_local, half, shape, kind, object_id, colour, refl, moving))
    return rows


def car_reflectance(parts) -> float:
    colour = np.array(parts[0][5])
    return float(0.3 + 0.3 * (colour @ np.array([0.299, 0.587, 0.114])))
