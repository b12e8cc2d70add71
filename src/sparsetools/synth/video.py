"""Synthetic street videos with exact camera and LiDAR poses, in memory.

Stable API (other modules and tests import these)::

    from sparsetools.synth.video import simulate_video

    seq = simulate_video(0, n_frames=30, image_size=(416, 128))     # VideoSequence
    f = seq.frames[5]                                                 # VideoFrame
    f.image            # (H, W, 3) uint8 RGB
    f.depth            # (H, W) float32 metres, camera z; 0 = sky / beyond 250 m
    f.moving_mask      # (H, W) bool, pixels of moving cars and walking people
    f.points, f.ring   # (N, 4) float32 x y z reflectance (Velodyne frame), (N,) uint8 laser
    f.T_world_from_cam, f.T_world_from_velo   # (4, 4) float64; world = frame 0's camera
    f.K, f.T_cam_from_velo                    # (3, 3), (4, 4): constant over a sequence
    f.actors           # tuple of ActorPose (cars, people) in the world frame
    seq.poses_cam, seq.poses_velo, seq.times  # (N, 4, 4), (N, 4, 4), (N,) seconds
    simulate_video(0, static=True)            # no moving cars, nobody walks

- ``simulate_video(seed, *, sequence=0, n_frames=30, image_size=(416, 128), static=False,
  antialias=2, lidar=True, image_noise=0.0, params=None) -> VideoSequence``
- :class:`VideoSimulator` makes one frame at a time (``.frame(k)``); :func:`simulate_video`
  and :func:`sparsetools.synth.video_files.write_video` use it.
- :func:`sparsetools.synth.video_params.draw_sequence_params` gives the drawn parameters;
  pass a modified copy as ``params`` to force a scenario.

Conventions: poses are ``T_world_from_sensor`` with the world = the first frame's camera
(KITTI odometry: x right, y down, z forward), so ``T_world_from_cam`` of frame 0 is the
identity and ``T_world_from_velo == T_world_from_cam @ T_cam_from_velo`` for every frame.
Frames are 0.1 s apart (10 Hz). The scene itself is built in a gravity-aligned *scene* frame
(x along the street's start, y left, z up; :attr:`VideoSequence.T_scene_from_world`).

Randomness: the sequence's parameters, its street blocks and actors, and each frame's LiDAR
noise (and optional image noise) come from ``SeedSequence([seed, stream, sequence, ...])``,
so a frame is the same whatever the number of workers or the order of generation, and the
same seed gives the same bytes on one machine.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..calibration import Calibration
from ..errors import ParameterError
from .actors import actor_primitives, actor_state, actors_for
from .motion import FRAME_RATE_HZ, ego_state, mounting, rigid_inverse, travelled
from .primitives import Primitives, build_bvh
from .rig import Rig
from .video_params import (
    STREAM_LIDAR,
    STREAM_NOISE,
    SequenceParams,
    draw_sequence_params,
    sequence_rng,
)
from .video_render import CameraModel, FrameScene, render_camera, scan_lidar
from .video_street import static_street
from .video_surfaces import make_textures

__all__ = [
    "ActorPose",
    "VideoFrame",
    "VideoSequence",
    "VideoSimulator",
    "simulate_video",
]

#: Street kept behind the first frame (LiDAR range) and ahead of the last: beyond the
#: camera's 400 m render range, so no frame sees where the street ends.
BEHIND_M, AHEAD_M = 130.0, 420.0


@dataclass(frozen=True)
class ActorPose:
    """A car or person at one frame.

    Attributes
    ----------
    actor_id : int
    kind : str
        ``"car"`` or ``"pedestrian"``.
    moving : bool
        It moves (it is in ``moving_mask`` where visible).
    T_world_from_actor : (4, 4) float64
        Actor frame (x forward, y left, z up, origin on the ground under its centre).
    half_extents : (3,) float64, metres
        Its bounding box is ``|x| <= h_x, |y| <= h_y, 0 <= z <= 2 h_z`` in the actor frame.
    """

    actor_id: int
    kind: str
    moving: bool
    T_world_from_actor: np.ndarray
    half_extents: np.ndarray


@dataclass(frozen=True)
class VideoFrame:
    """Everything simulated at one frame (see the module docstring for the conventions).

    Attributes
    ----------
    index : int
    time_s : float
        ``index / 10``.
    image : (H, W, 3) uint8
    depth : (H, W) float32, metres
    moving_mask : (H, W) bool
    points : (N, 4) float32
        LiDAR scan in scan order (empty when simulated without LiDAR).
    ring : (N,) uint8
    T_world_from_cam, T_world_from_velo : (4, 4) float64
    K : (3, 3) float64
    T_cam_from_velo : (4, 4) float64
    speed_mps : float
        Ego speed, m/s (progress along the street's centre line, see ``DriveParams``).
    actors : tuple of ActorPose
    """

    index: int
    time_s: float
    image: np.ndarray
    depth: np.ndarray
    moving_mask: np.ndarray
    points: np.ndarray
    ring: np.ndarray
    T_world_from_cam: np.ndarray
    T_world_from_velo: np.ndarray
    K: np.ndarray
    T_cam_from_velo: np.ndarray
    speed_mps: float
    actors: tuple


@dataclass(frozen=True)
class VideoSequence:
    """One simulated sequence.

    Attributes
    ----------
    params : SequenceParams
        Everything drawn for it.
    frames : tuple of VideoFrame
    K : (3, 3) float64
    T_cam_from_velo : (4, 4) float64
    T_scene_from_world : (4, 4) float64
        The world (frame 0's camera) in the gravity-aligned scene frame.
    width, height : int
    static : bool
    """

    params: SequenceParams
    frames: tuple
    K: np.ndarray
    T_cam_from_velo: np.ndarray
    T_scene_from_world: np.ndarray
    width: int
    height: int
    static: bool

    @property
    def poses_cam(self) -> np.ndarray:
        """(N, 4, 4) ``T_world_from_cam``."""
        return np.stack([f.T_world_from_cam for f in self.frames])

    @property
    def poses_velo(self) -> np.ndarray:
        """(N, 4, 4) ``T_world_from_velo``."""
        return np.stack([f.T_world_from_velo for f in self.frames])

    @property
    def times(self) -> np.ndarray:
        """(N,) seconds."""
        return np.array([f.time_s for f in self.frames])


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ParameterError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


class VideoSimulator:
    """One sequence, frame by frame (its street, actors and rig are built once).

    Parameters
    ----------
    seed, sequence : int
        Global seed and sequence index (>= 0).
    n_frames : int
        Frames of the sequence (>= 1); the street covers the whole drive.
    image_size : (W, H)
        Camera size in pixels (>= 16 each); intrinsics are KITTI's scaled to the width.
    static : bool
        No moving cars; pedestrians stand still.
    antialias : int
        Colour samples per pixel along each axis (1-4).
    lidar : bool
        Simulate the LiDAR (off: empty point arrays, faster).
    image_noise : float
        Standard deviation of Gaussian image noise, grey levels (0 = none).
    params : SequenceParams, optional
        Use these instead of the drawn ones.
    """

    def __init__(
        self,
        seed: int,
        sequence: int = 0,
        *,
        n_frames: int = 30,
        image_size: tuple[int, int] = (416, 128),
        static: bool = False,
        antialias: int = 2,
        lidar: bool = True,
        image_noise: float = 0.0,
        params: SequenceParams | None = None,
    ) -> None:
        self.seed = _check_int("seed", seed, 0)
        self.sequence = _check_int("sequence", sequence, 0)
        self.n_frames = _check_int("n_frames", n_frames, 1)
        try:
            width, height = (int(v) for v in image_size)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"image_size must be (W, H), got {image_size!r}") from exc
        if width < 16 or height < 16:
            raise ParameterError(f"image_size must be at least 16x16, got {width}x{height}")
        self.antialias = _check_int("antialias", antialias, 1)
        if self.antialias > 4:
            raise ParameterError(f"antialias must be 1..4, got {antialias}")
        if not (isinstance(image_noise, (int, float)) and math.isfinite(image_noise)) or (
            image_noise < 0
        ):
            raise ParameterError(f"image_noise must be a finite number >= 0, got {image_noise!r}")
        self.image_noise = float(image_noise)
        self.static = bool(static)
        self.lidar = bool(lidar)
        self.params = params if params is not None else draw_sequence_params(seed, sequence)
        if not isinstance(self.params, SequenceParams):
            raise ParameterError("params must be a SequenceParams (see draw_sequence_params)")

        p = self.params
        T_base_from_cam, T_base_from_velo = mounting(p.rig)
        self.T_base_from_cam = T_base_from_cam
        self.T_base_from_velo = T_base_from_velo
        self.T_cam_from_velo = rigid_inverse(T_base_from_cam) @ T_base_from_velo
        self.rig = dataclasses.replace(
            Rig.kitti(width, height),
            T_cam_from_velo=self.T_cam_from_velo,
            lidar_height=p.rig.lidar_height_m,
        )
        self.camera = CameraModel(width, height, self.rig.K, antialias=self.antialias)
        self.ego = [ego_state(p.road, p.street, p.drive, k) for k in range(self.n_frames)]
        T_cam0 = self.ego[0].T_scene_from_base @ T_base_from_cam
        self.T_scene_from_world = T_cam0
        self._world_from_scene = rigid_inverse(T_cam0)
        start = p.drive.start_s_m
        end = start + travelled(p.drive, (self.n_frames - 1) / FRAME_RATE_HZ)[0]
        self.s_range = (start - BEHIND_M, end + AHEAD_M)
        self.street = static_street(p, *self.s_range)
        self.actors = actors_for(p, *self.s_range, static=self.static)
        self.textures = make_textures(self.seed, self.sequence)
        self._static_bvh = build_bvh(self.street.primitives)

    # -- poses -----------------------------------------------------------------------------------
    def T_scene_from_cam(self, k: int) -> np.ndarray:
        """(4, 4) camera pose of frame ``k`` in the scene frame (what the renderer uses)."""
        return self.ego[k].T_scene_from_base @ self.T_base_from_cam

    def T_world_from_cam(self, k: int) -> np.ndarray:
        """(4, 4) camera pose of frame ``k``; frame 0 (and any frame at its pose) is exactly I."""
        T = self.T_scene_from_cam(k)
        if np.array_equal(T, self.T_scene_from_world):
            return np.eye(4)
        return self._world_from_scene @ T

    def T_world_from_velo(self, k: int) -> np.ndarray:
        return self.T_world_from_cam(k) @ self.T_cam_from_velo

    @property
    def calibration(self) -> Calibration:
        """Velodyne -> camera calibration (the KITTI calib file of every frame)."""
        return dataclasses.replace(self.rig.calibration, source="synthetic video rig")

    # -- frames ----------------------------------------------------------------------------------
    def _check_frame(self, k) -> int:
        k = _check_int("frame", k, 0)
        if k >= self.n_frames:
            raise ParameterError(f"frame must be < n_frames = {self.n_frames}, got {k}")
        return k

    def scene_at(self, k: int) -> FrameScene:
        """The street with the actors placed at frame ``k``."""
        states = [actor_state(self.params, a, self.ego[k].time_s) for a in self.actors]
        dynamic = actor_primitives(self.actors, states) if states else Primitives.empty()
        return FrameScene(
            road=self.params.road,
            street=self.params.street,
            light=self.params.light,
            textures=self.textures,
            primitives=Primitives.concat([self.street.primitives, dynamic]),
            bvhs=(self._static_bvh, build_bvh(dynamic, split="median")),
        )

    def actor_poses(self, k: int) -> tuple[ActorPose, ...]:
        out = []
        for a in self.actors:
            st = actor_state(self.params, a, self.ego[k].time_s)
            out.append(
                ActorPose(
                    actor_id=st.actor_id,
                    kind=st.kind,
                    moving=st.moving,
                    T_world_from_actor=self._world_from_scene @ st.T_scene_from_actor,
                    half_extents=st.half_extents,
                )
            )
        return tuple(out)

    def frame(self, k: int) -> VideoFrame:
        """Simulate frame ``k`` (0 <= k < n_frames)."""
        k = self._check_frame(k)
        scene = self.scene_at(k)
        T_cam = self.T_scene_from_cam(k)
        noise = None
        if self.image_noise > 0:
            rng = sequence_rng(self.seed, STREAM_NOISE, self.sequence, k)
            noise = rng.normal(
                0.0, self.image_noise / 255.0, (self.camera.height * self.camera.width, 3)
            )
        image, depth, moving = render_camera(scene, self.camera, T_cam, noise=noise)
        if self.lidar:
            rig = self.rig
            points, ring = scan_lidar(
                scene,
                rig.lidar_directions,
                T_cam @ self.T_cam_from_velo,
                azimuth_steps=rig.azimuth_steps,
                min_range=rig.lidar_min_range,
                max_range=rig.lidar_max_range,
                range_noise=rig.lidar_range_noise,
                reflectance_noise=rig.reflectance_noise,
                rng=sequence_rng(self.seed, STREAM_LIDAR, self.sequence, k),
            )
        else:
            points, ring = np.zeros((0, 4), dtype=np.float32), np.zeros(0, dtype=np.uint8)
        return VideoFrame(
            index=k,
            time_s=self.ego[k].time_s,
            image=image,
            depth=depth,
            moving_mask=moving,
            points=points,
            ring=ring,
            T_world_from_cam=self.T_world_from_cam(k),
            T_world_from_velo=self.T_world_from_velo(k),
            K=self.rig.K.copy(),
            T_cam_from_velo=self.T_cam_from_velo.copy(),
            speed_mps=self.ego[k].speed_mps,
            actors=self.actor_poses(k),
        )

    def frames(self) -> Iterator[VideoFrame]:
        """All frames in order, one at a time."""
        for k in range(self.n_frames):
            yield self.frame(k)

    def sequence_result(self, frames) -> VideoSequence:
        return VideoSequence(
            params=self.params,
            frames=tuple(frames),
            K=self.rig.K.copy(),
            T_cam_from_velo=self.T_cam_from_velo.copy(),
            T_scene_from_world=self.T_scene_from_world.copy(),
            width=self.camera.width,
            height=self.camera.height,
            static=self.static,
        )


def simulate_video(
    seed: int,
    *,
    sequence: int = 0,
    n_frames: int = 30,
    image_size: tuple[int, int] = (416, 128),
    static: bool = False,
    antialias: int = 2,
    lidar: bool = True,
    image_noise: float = 0.0,
    params: SequenceParams | None = None,
) -> VideoSequence:
    """Simulate one street video sequence in memory (see :class:`VideoSimulator` for the
    parameters and the module docstring for the conventions).

    Returns
    -------
    VideoSequence
    """
    sim = VideoSimulator(
        seed,
        sequence,
        n_frames=n_frames,
        image_size=image_size,
        static=static,
        antialias=antialias,
        lidar=lidar,
        image_noise=image_noise,
        params=params,
    )
    return sim.sequence_result(sim.frames())
