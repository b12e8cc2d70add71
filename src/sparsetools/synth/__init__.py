"""Procedural scenes and sensor simulation with exact ground truth.

- :func:`generate_scene` writes a KITTI-like street sequence (camera, 64-beam LiDAR in scan
  order, dense depth, nuScenes-format radar, calibrations) and an underwater sequence.
- :func:`simulate_frame`, :class:`Rig`, :func:`street_layout` and :func:`generate_underwater`
  give the same data in memory, for tests and training.
- :func:`simulate_video` (in memory) and :func:`write_video` (KITTI-style folders) make street
  videos at 10 Hz with exact camera and LiDAR poses, moving cars and people and a moving-object
  mask (:mod:`sparsetools.synth.video` documents the API and conventions).

numba (the ray-casting kernel) is imported on the first cast, not by this import.
"""

from __future__ import annotations

from .geometry import BoxSet, RayHits, cast_rays
from .rig import Rig, hdl64_elevations_deg
from .scene import StreetFrame, ego_origin, generate_scene, simulate_frame, sun_direction
from .street import MATERIAL_NAMES, StreetLayout, make_textures, street_layout
from .underwater import UnderwaterSequence, backscatter, generate_underwater, light_cone
from .video import VideoFrame, VideoSequence, VideoSimulator, simulate_video
from .video_files import write_video
from .video_params import SequenceParams, draw_sequence_params

__all__ = [
    "MATERIAL_NAMES",
    "BoxSet",
    "RayHits",
    "Rig",
    "SequenceParams",
    "StreetFrame",
    "StreetLayout",
    "UnderwaterSequence",
    "VideoFrame",
    "VideoSequence",
    "VideoSimulator",
    "backscatter",
    "cast_rays",
    "draw_sequence_params",
    "ego_origin",
    "generate_scene",
    "generate_underwater",
    "hdl64_elevations_deg",
    "light_cone",
    "make_textures",
    "simulate_frame",
    "simulate_video",
    "street_layout",
    "sun_direction",
    "write_video",
]
