"""Everything drawn per video sequence: street, road shape, rig mounting, drive, lighting.

:func:`draw_sequence_params` draws a :class:`SequenceParams` from
``SeedSequence([seed, STREAM_PARAMS, sequence])``; nothing in it depends on the number of
frames, so frame k of a 30-frame run equals frame k of a 100-frame run. Every field is
recorded in the sequence's ``scene.json`` (:meth:`SequenceParams.to_dict`). Replace fields
with :func:`dataclasses.replace` to force a scenario (a stop, a lane change, ...).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .roads import Road

__all__ = [
    "DriveParams",
    "LightParams",
    "RigParams",
    "SequenceParams",
    "StreetParams",
    "draw_sequence_params",
    "sequence_rng",
]

# Random streams of the video mode (the single-frame mode uses 1..5).
STREAM_PARAMS, STREAM_BLOCK, STREAM_ACTORS, STREAM_LIDAR, STREAM_TEXTURE, STREAM_NOISE = range(
    11, 17
)

_SKIES = (
    # (horizon, zenith, sun glow): clear blue, hazy, overcast, warm evening
    ((0.80, 0.86, 0.93), (0.30, 0.50, 0.82), (1.00, 0.95, 0.85)),
    ((0.86, 0.88, 0.90), (0.55, 0.66, 0.82), (1.00, 0.97, 0.92)),
    ((0.78, 0.79, 0.80), (0.62, 0.64, 0.67), (0.85, 0.85, 0.85)),
    ((0.95, 0.80, 0.62), (0.38, 0.45, 0.68), (1.00, 0.82, 0.55)),
)


def sequence_rng(seed: int, stream: int, sequence: int, *ids: int) -> np.random.Generator:
    """Generator of one random stream of one sequence (``SeedSequence([seed, stream, sequence,
    *ids])``): independent of worker count and frame order."""
    return np.random.default_rng(np.random.SeedSequence([seed, stream, sequence, *ids]))


@dataclass(frozen=True)
class StreetParams:
    """Cross-section and furniture of the street (metres unless stated).

    Attributes
    ----------
    lanes_per_direction : int
        1 or 2 driving lanes each way; the ego drives on the right (y < 0).
    lane_width_m, parking_width_m, sidewalk_width_m, curb_height_m : float
    setback_m : float
        Front yard between the sidewalk and the building facades.
    building_height_m, building_width_m, building_depth_m : (float, float)
        Ranges the buildings are drawn from.
    alley_probability : float
        Chance of a gap before each building.
    parked_car_probability : float
        Chance that a parking slot is taken.
    tree_spacing_m : float
        Mean distance between street trees along each side (0 = no trees).
    lamp_spacing_m : float
        Mean distance between street lamps along each side.
    sign_probability : float
        Chance of a traffic sign per 50 m block and side.
    hedges : bool
        Hedges along the front yards (when the setback leaves room).
    pedestrians_per_100m : float
        Pedestrians per 100 m of each sidewalk.
    walking_fraction : float
        Share of pedestrians that walk (the others stand).
    moving_cars : int
        Cars driving in the lanes the ego never uses.
    facade_palette : int
        Colour scheme of the facades (index into the renderer's palettes).
    asphalt_grey : float
        Albedo of the road surface.
    grass_yards : bool
        Front yards of grass (else gravel).
    """

    lanes_per_direction: int
    lane_width_m: float
    parking_width_m: float
    sidewalk_width_m: float
    curb_height_m: float
    setback_m: float
    building_height_m: tuple[float, float]
    building_width_m: tuple[float, float]
    building_depth_m: tuple[float, float]
    alley_probability: float
    parked_car_probability: float
    tree_spacing_m: float
    lamp_spacing_m: float
    sign_probability: float
    hedges: bool
    pedestrians_per_100m: float
    walking_fraction: float
    moving_cars: int
    facade_palette: int
    asphalt_grey: float
    grass_yards: bool

    @property
    def road_half_width_m(self) -> float:
        """Centre line to curb: the driving lanes plus the parking lane."""
        return self.lanes_per_direction * self.lane_width_m + self.parking_width_m

    @property
    def building_line_m(self) -> float:
        """Centre line to the facades."""
        return self.road_half_width_m + self.sidewalk_width_m + self.setback_m

    def lane_centre_m(self, lane: int) -> float:
        """Lateral offset of a lane: ``lane`` 0.. on the ego side counted from the centre
        line (negative l), ``-1, -2`` the oncoming lanes (positive l)."""
        if lane >= 0:
            return -(lane + 0.5) * self.lane_width_m
        return (-lane - 0.5) * self.lane_width_m


@dataclass(frozen=True)
class RigParams:
    """Mounting of the sensors on the ego car (metres, degrees).

    Attributes
    ----------
    camera_height_m : float
        Camera centre above the road.
    camera_pitch_deg : float
        Optical axis below the road plane (positive = looking down).
    camera_ahead_m : float
        Camera ahead of the LiDAR along the car.
    lidar_above_camera_m : float
        LiDAR centre above the camera centre.
    """

    camera_height_m: float
    camera_pitch_deg: float
    camera_ahead_m: float
    lidar_above_camera_m: float

    @property
    def lidar_height_m(self) -> float:
        return self.camera_height_m + self.lidar_above_camera_m


@dataclass(frozen=True)
class DriveParams:
    """Motion of the ego car.

    Attributes
    ----------
    speed_mps : float
        Cruise speed from frame 0 (0 = standing still), as progress along the street's centre
        line: on the curve the ego, ``l`` metres off it, covers ``(1 - curvature l)`` times
        that, and a lane change adds its sideways motion (both within a few per cent).
    lane : int
        Start lane (0 = next to the centre line; see :meth:`StreetParams.lane_centre_m`).
    lane_change_to : int
        Target lane of a lane change, -1 for none.
    lane_change_start_m, lane_change_length_m : float
        Distance driven when the change starts, and the distance it takes.
    brake_time_s : float
        Time braking starts (``inf`` = never); the car then decelerates to a stop and stays.
    deceleration_mps2 : float
    start_s_m : float
        Arc length of the ego at frame 0.
    """

    speed_mps: float
    lane: int
    lane_change_to: int
    lane_change_start_m: float
    lane_change_length_m: float
    brake_time_s: float
    deceleration_mps2: float
    start_s_m: float = 0.0

    @property
    def stop_time_s(self) -> float:
        """Time the car comes to rest (``inf`` when it does not; 0 when it never moves)."""
        if self.speed_mps <= 0.0:
            return 0.0
        if not math.isfinite(self.brake_time_s):
            return math.inf
        return self.brake_time_s + self.speed_mps / self.deceleration_mps2


@dataclass(frozen=True)
class LightParams:
    """Sun and sky (directions in the scene frame; radiometric values relative).

    Attributes
    ----------
    sun_azimuth_deg, sun_elevation_deg : float
    sun_intensity : float
        Weight of the Lambertian sun term.
    ambient : float
        Weight of the sky (hemisphere) term.
    sky_horizon, sky_zenith, sun_glow : (float, float, float)
        Sky colours, RGB in [0, 1].
    """

    sun_azimuth_deg: float
    sun_elevation_deg: float
    sun_intensity: float
    ambient: float
    sky_horizon: tuple[float, float, float]
    sky_zenith: tuple[float, float, float]
    sun_glow: tuple[float, float, float]

    @property
    def sun_direction(self) -> np.ndarray:
        """(3,) unit vector towards the sun."""
        az, el = math.radians(self.sun_azimuth_deg), math.radians(self.sun_elevation_deg)
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


@dataclass(frozen=True)
class SequenceParams:
    """All parameters of one video sequence (see :func:`draw_sequence_params`)."""

    seed: int
    sequence: int
    street: StreetParams
    road: Road
    rig: RigParams
    drive: DriveParams
    light: LightParams

    def to_dict(self) -> dict:
        """JSON-ready nested dict (``inf`` written as None)."""

        def clean(v):
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            if isinstance(v, float):
                return None if not math.isfinite(v) else round(v, 9)
            return v

        out = clean(asdict(self))
        out["street"]["road_half_width_m"] = round(self.street.road_half_width_m, 9)
        out["street"]["building_line_m"] = round(self.street.building_line_m, 9)
        out["road"]["turn_angle_deg"] = round(math.degrees(self.road.turn_angle), 6)
        out["road"]["slope_deg"] = round(math.degrees(math.atan(self.road.grade)), 6)
        out["rig"]["lidar_height_m"] = round(self.rig.lidar_height_m, 9)
        out["drive"]["stop_time_s"] = clean(self.drive.stop_time_s)
        return out


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def draw_sequence_params(seed: int, sequence: int) -> SequenceParams:
    """Draw the street, road, rig, drive and light of one sequence.

    Parameters
    ----------
    seed : int
        Global seed (>= 0).
    sequence : int
        Sequence index (>= 0): each gets its own street and drive.
    """
    rng = sequence_rng(seed, STREAM_PARAMS, sequence)
    lanes = 2 if rng.random() < 0.45 else 1
    lo_h = _u(rng, 4.0, 12.0)
    street = StreetParams(
        lanes_per_direction=lanes,
        lane_width_m=_u(rng, 3.0, 3.7),
        parking_width_m=_u(rng, 2.2, 2.7),
        sidewalk_width_m=_u(rng, 3.0, 5.5),
        curb_height_m=_u(rng, 0.10, 0.18),
        setback_m=_u(rng, 0.0, 6.0) if rng.random() < 0.6 else 0.0,
        building_height_m=(lo_h, lo_h + _u(rng, 3.0, 30.0)),
        building_width_m=(_u(rng, 5.0, 10.0), _u(rng, 12.0, 28.0)),
        building_depth_m=(8.0, _u(rng, 10.0, 18.0)),
        alley_probability=_u(rng, 0.0, 0.3),
        parked_car_probability=_u(rng, 0.2, 0.9),
        tree_spacing_m=_u(rng, 7.0, 25.0) if rng.random() < 0.65 else 0.0,
        lamp_spacing_m=_u(rng, 22.0, 45.0),
        sign_probability=_u(rng, 0.1, 0.7),
        hedges=bool(rng.random() < 0.4),
        pedestrians_per_100m=_u(rng, 0.0, 7.0),
        walking_fraction=_u(rng, 0.3, 0.9),
        moving_cars=int(rng.integers(1, 7)) if rng.random() < 0.85 else 0,
        facade_palette=int(rng.integers(0, 4)),
        asphalt_grey=_u(rng, 0.20, 0.36),
        grass_yards=bool(rng.random() < 0.5),
    )
    # Road: a slight turn about half the time, a grade about two thirds of the time.
    if rng.random() < 0.5:
        radius = _u(rng, 120.0, 500.0)
        curvature = (1.0 if rng.random() < 0.5 else -1.0) / radius
        angle = math.radians(_u(rng, 8.0, 30.0))
        turn_start, turn_length = _u(rng, 5.0, 45.0), angle * radius
    else:
        curvature, turn_start, turn_length = 0.0, 0.0, 0.0
        rng.random()  # keep the stream aligned for the draws below
        rng.random()
        rng.random()
        rng.random()
    slope = _u(rng, -4.0, 4.0) if rng.random() < 0.65 else 0.0
    road = Road(
        turn_start_m=turn_start,
        turn_length_m=turn_length,
        curvature_per_m=curvature,
        grade=math.tan(math.radians(slope)),
    )
    camera_height = _u(rng, 1.30, 1.95)
    rig = RigParams(
        camera_height_m=camera_height,
        camera_pitch_deg=_u(rng, -2.0, 5.0),
        camera_ahead_m=_u(rng, 0.1, 0.6),
        lidar_above_camera_m=_u(rng, 0.05, 0.35),
    )
    speed = 0.0 if rng.random() < 0.08 else _u(rng, 2.0, 15.0)
    lane = int(rng.integers(0, lanes))
    change = lanes == 2 and rng.random() < 0.4
    brake = rng.random() < 0.3
    drive = DriveParams(
        speed_mps=speed,
        lane=lane,
        lane_change_to=(1 - lane) if change else -1,
        lane_change_start_m=_u(rng, 0.0, 15.0),
        lane_change_length_m=_u(rng, 25.0, 45.0),
        brake_time_s=_u(rng, 0.3, 2.0) if brake else math.inf,
        deceleration_mps2=_u(rng, 3.0, 7.0),
    )
    sky = _SKIES[int(rng.integers(0, len(_SKIES)))]
    overcast = sky is _SKIES[2]
    light = LightParams(
        sun_azimuth_deg=_u(rng, -180.0, 180.0),
        sun_elevation_deg=_u(rng, 12.0, 65.0),
        sun_intensity=_u(rng, 0.15, 0.3) if overcast else _u(rng, 0.5, 0.85),
        ambient=_u(rng, 0.55, 0.75) if overcast else _u(rng, 0.28, 0.45),
        sky_horizon=sky[0],
        sky_zenith=sky[1],
        sun_glow=sky[2],
    )
    return SequenceParams(
        seed=int(seed),
        sequence=int(sequence),
        street=street,
        road=road,
        rig=rig,
        drive=drive,
        light=light,
    )
