"""Actors of the video scenes: moving cars in the free lanes, pedestrians on the sidewalks
(walking or standing), placed per frame from their trajectories.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .motion import pose
from .primitives import Primitives
from .roads import rotation_z
from .video_params import STREAM_ACTORS, SequenceParams, sequence_rng
from .video_parts import car_parts, car_reflectance, pedestrian_parts, place
from .video_street import BLOCK_M, BLOCK_OFFSET

__all__ = ["ACTOR_ID_BASE", "Actor", "ActorState", "actor_primitives", "actor_state", "actors_for"]

#: Actor ids start here (static objects have small ids).
ACTOR_ID_BASE = 1 << 40


@dataclass(frozen=True)
class Actor:
    """A car or a person that follows the street at constant speed (0 = stands still).

    Attributes
    ----------
    actor_id : int
    kind : str
        ``"car"`` or ``"pedestrian"``.
    s0_m, l_m : float
        Street coordinates at time 0.
    direction : int
        +1 along the street, -1 against it.
    speed_mps : float
    heading_offset : float, radians
        Added to the street heading (a standing person looks anywhere).
    parts : tuple
        Parts in the actor's frame.
    half_extents : (3,) float64, metres
        Half size of the actor's bounding box, centred at ``(0, 0, half_extents[2])``.
    reflectance : float
    """

    actor_id: int
    kind: str
    s0_m: float
    l_m: float
    direction: int
    speed_mps: float
    heading_offset: float
    parts: tuple
    half_extents: np.ndarray
    reflectance: float

    @property
    def moving(self) -> bool:
        return self.speed_mps > 0.0

    def to_dict(self) -> dict:
        return {
            "actor_id": self.actor_id,
            "kind": self.kind,
            "s0_m": round(self.s0_m, 6),
            "l_m": round(self.l_m, 6),
            "direction": self.direction,
            "speed_mps": round(self.speed_mps, 6),
            "heading_offset_rad": round(self.heading_offset, 6),
            "size_m": [round(2 * float(v), 4) for v in self.half_extents],
            "colour": [round(float(c), 3) for c in self.parts[0][5]],
        }


@dataclass(frozen=True)
class ActorState:
    """Where an actor is at one frame.

    Attributes
    ----------
    actor_id : int
    kind : str
    moving : bool
    T_scene_from_actor : (4, 4) float64
        Actor frame (x forward, y left, z up, origin on the ground) in the scene frame.
    half_extents : (3,) float64, metres
        Bounding box ``[-h, h]`` around ``(0, 0, h_z)`` in the actor frame.
    """

    actor_id: int
    kind: str
    moving: bool
    T_scene_from_actor: np.ndarray
    half_extents: np.ndarray


def actors_for(params: SequenceParams, s_min: float, s_max: float, *, static: bool) -> list[Actor]:
    """Moving cars (none when ``static``) and the pedestrians of ``[s_min, s_max]``.

    Moving cars use the lanes the ego never drives in (the oncoming lanes, and the other lane
    of its own direction when it does not change lanes); the first is an oncoming car 25-70 m
    ahead of the ego at frame 0. Pedestrians walk along the sidewalks (stand when ``static``).
    """
    st, dr = params.street, params.drive
    rng = sequence_rng(params.seed, STREAM_ACTORS, params.sequence)
    actors: list[Actor] = []
    lanes = [-(i + 1) for i in range(st.lanes_per_direction)]
    if st.lanes_per_direction == 2 and dr.lane_change_to < 0:
        lanes.append(1 - dr.lane)
    lane_speed = {lane: float(rng.uniform(4.0, 14.0)) for lane in lanes}
    placed: dict[int, list[float]] = {lane: [] for lane in lanes}
    for k in range(st.moving_cars):
        lane = -1 if k == 0 else lanes[int(rng.integers(len(lanes)))]
        s0 = dr.start_s_m + (
            float(rng.uniform(25.0, 70.0)) if k == 0 else float(rng.uniform(-60.0, 250.0))
        )
        length = float(rng.uniform(3.9, 4.9))
        parts, half = car_parts(rng, length)
        # Cars in one lane share its speed; keep them 6 m apart bumper to bumper.
        while any(abs(s0 - o) < length + 6.0 for o in placed[lane]):
            s0 += length + 6.0
        placed[lane].append(s0)
        if static:
            continue
        direction = 1 if lane >= 0 else -1
        actors.append(
            Actor(
                actor_id=ACTOR_ID_BASE + k,
                kind="car",
                s0_m=s0,
                l_m=st.lane_centre_m(lane),
                direction=direction,
                speed_mps=lane_speed[lane],
                heading_offset=0.0 if direction > 0 else math.pi,
                parts=tuple(parts),
                half_extents=half,
                reflectance=car_reflectance(parts),
            )
        )
    # Pedestrians: per side one flow of walkers (one direction and speed, so nobody walks
    # through anybody) in a band next to the trees, people standing in a band behind it;
    # drawn per 50 m block and side from their own stream, at least 1 m apart.
    flow = {
        side: (1 if rng.random() < 0.5 else -1, float(rng.uniform(0.9, 1.6))) for side in (-1, 1)
    }
    inner = st.road_half_width_m + 1.4  # clear of the trunks (<= 1.02 m from the curb)
    outer = st.road_half_width_m + st.sidewalk_width_m - 0.35
    band = 0.5 * (outer - inner - 0.65)  # walkers' and standers' bands, 0.65 m apart
    for block in range(math.floor(s_min / BLOCK_M), math.floor(s_max / BLOCK_M) + 1):
        brng = sequence_rng(params.seed, STREAM_ACTORS, params.sequence, block + BLOCK_OFFSET)
        for side in (-1, 1):
            n = int(brng.poisson(st.pedestrians_per_100m * BLOCK_M / 100.0))
            taken: dict[bool, list[float]] = {True: [], False: []}
            for j in range(n):
                s0 = block * BLOCK_M + float(brng.uniform(0.5, BLOCK_M - 0.5))
                walking = bool(brng.random() < st.walking_fraction)
                lo = inner if walking else outer - band
                l = side * float(brng.uniform(lo, lo + band))
                facing = float(brng.uniform(-math.pi, math.pi))
                parts, half = pedestrian_parts(brng)
                if any(abs(s0 - o) < 1.0 for o in taken[walking]):
                    continue
                taken[walking].append(s0)
                direction, speed = flow[side]
                moving = walking and not static
                actors.append(
                    Actor(
                        actor_id=ACTOR_ID_BASE
                        + (block + BLOCK_OFFSET) * 1000
                        + (side + 1) * 100
                        + j,
                        kind="pedestrian",
                        s0_m=s0,
                        l_m=l,
                        direction=direction,
                        speed_mps=speed if moving else 0.0,
                        heading_offset=(0.0 if direction > 0 else math.pi) if walking else facing,
                        parts=tuple(parts),
                        half_extents=half,
                        reflectance=0.3,
                    )
                )
    return actors


def actor_state(params: SequenceParams, actor: Actor, time_s: float) -> ActorState:
    """Pose of ``actor`` at ``time_s``: cars lie on the road surface, people stand upright
    on the sidewalk."""
    road = params.road
    s = actor.s0_m + actor.direction * actor.speed_mps * time_s
    x, y, psi = road.point(s, actor.l_m)
    heading = psi + actor.heading_offset
    if actor.kind == "car":
        R = road.surface_rotation(heading)
        z = road.ground_z(x)
    else:
        R = rotation_z(heading)
        z = road.ground_z(x, above=params.street.curb_height_m)
    return ActorState(
        actor_id=actor.actor_id,
        kind=actor.kind,
        moving=actor.moving,
        T_scene_from_actor=pose(R, (x, y, z)),
        half_extents=actor.half_extents,
    )


def actor_primitives(actors: list[Actor], states: list[ActorState]) -> Primitives:
    """Primitives of all actors at their given states."""
    rows: list[tuple] = []
    for actor, state in zip(actors, states, strict=True):
        T = state.T_scene_from_actor
        rows += place(
            actor.parts, T[:3, :3], T[:3, 3], actor.actor_id, actor.reflectance, actor.moving
        )
    return Primitives.from_rows(rows)
