"""The frames of depth-map commands: sparse maps to densify, and radar maps (or radar
``.pcd`` files) to expand with their images, calibrations and LiDAR reference maps."""

from __future__ import annotations

import os
from pathlib import Path

from ...errors import FormatError, ParameterError
from .frame import Frame
from .index import attach, index_input, merge_frames
from .tree import index_tree

__all__ = ["RADAR_SUFFIXES", "depth_frames", "radar_frames"]

#: A radar input is a projected depth map (``project``'s output) or a nuScenes radar .pcd.
RADAR_SUFFIXES = (".png", ".pcd")


def depth_frames(paths, *, role: str = "sparse", option: str = "SPARSE") -> list[Frame]:
    """Depth maps (KITTI uint16 PNG or ``.npy`` metres) given as files, folder trees,
    sparsetools output folders (read through their record) or KITTI depth-completion trees,
    as frames (the map in ``Frame.depth``) sorted by key.

    Raises
    ------
    FormatError
        A path without depth maps, or two inputs that are one frame.
    """
    paths = list(paths)
    if not paths:
        raise ParameterError(f"no {'sparse ' if role == 'sparse' else ''}depth maps given")
    return merge_frames((index_input(Path(p), role, option=option) for p in paths), "depth")


def radar_frames(
    paths,
    *,
    image: str | os.PathLike | None = None,
    calib: str | os.PathLike | None = None,
    lidar: str | os.PathLike | None = None,
) -> list[Frame]:
    """Radar inputs as frames (the radar in ``Frame.depth``), each with its camera image,
    calibration and LiDAR reference map (``Frame.gt``) when given.

    Files are taken as given, folders expanded to their ``*.png`` / ``*.pcd``; in a folder,
    ``<frame>_sweep<k>.pcd`` (or ``.png``) is left out when ``<frame>.pcd`` (or ``.png``) is
    there too: those are the single sweeps of a merged multi-sweep frame (the layout
    ``synth-scene`` writes). A folder written by ``project`` is read through its record.
    ``image`` and ``lidar`` are one file for a single frame or folders matched by frame;
    ``calib`` is one file shared by every frame or a folder of per-frame files.

    Raises
    ------
    FormatError
        No radar input in a path, or a frame without its image, calibration or LiDAR map.
    """
    paths = list(paths)
    if not paths:
        raise ParameterError("no radar inputs given")

    def index(p: Path):
        if p.is_file() and p.suffix.lower() not in RADAR_SUFFIXES:
            raise FormatError(
                f"{p}: not a radar input (expected a depth .png or a nuScenes radar .pcd)"
            )
        if p.is_dir() and not any(p.iterdir()):
            raise FormatError(f"{p}: no radar depth PNG or .pcd file in this folder")
        try:
            return index_tree(p, RADAR_SUFFIXES, option="RADAR", role="depth")
        except FormatError:
            return index_input(p, "depth", option="RADAR")  # a KITTI depth-completion tree

    frames = merge_frames((index(p) for p in map(Path, paths)), "depth")
    frames, _ = attach(frames, image, "image", role="image", option="--image", shared_ok=False,
                       required=True)  # fmt: skip
    frames, _ = attach(frames, calib, "calib", role="calib", option="--calib", required=True)
    if lidar is not None and Path(lidar).is_file() and len(frames) > 1:
        raise ParameterError(
            f"{lidar} is one LiDAR depth file but {len(frames)} radar frames were given: pass "
            "a folder of LiDAR depth maps matched by frame",
            param="lidar",
        )
    frames, _ = attach(frames, lidar, "gt", role="depth", option="--lidar", shared_ok=False,
                       required=True)  # fmt: skip
    return frames
