"""The frames of image commands (``lowlight-synth``, ``equalize``, ``defocus-synth``,
``dark-channel``, ``underwater``): images given as files and folders, with the depth maps
and calibrations matched to them by frame."""

from __future__ import annotations

import os
from pathlib import Path

from ...errors import FormatError, ParameterError
from .frame import Frame
from .index import attach, index_input, merge_frames
from .tree import IMAGE_SUFFIXES

__all__ = ["image_frames", "images_with_depth"]


def image_frames(paths, *, option: str = "IMAGE") -> list[Frame]:
    """Images given as files and/or folders (a folder tree: ``DIR/<sequence>/<frame>.png``;
    a folder written by sparsetools: its recorded images), as frames sorted by key.

    Raises
    ------
    ParameterError
        No path given.
    FormatError
        A path does not exist, a folder holds no image, a file is not a PNG/JPEG, or two
        files are the same frame.
    """
    paths = list(paths)
    if not paths:
        raise ParameterError("no images given")

    def index(p: Path):
        if p.is_file() and p.suffix.lower() not in IMAGE_SUFFIXES:
            raise FormatError(f"{p}: not a PNG or JPEG image")
        return index_input(p, "image", option=option)

    return merge_frames((index(p) for p in map(Path, paths)), "image")


def images_with_depth(
    images,
    *,
    depth: str | os.PathLike | None,
    calib: str | os.PathLike | None = None,
    depth_required: bool = True,
) -> list[Frame]:
    """Image frames, each with its depth map (one file for a single image, else a folder
    matched by frame) and its calibration (one file shared by every image, or a folder of
    per-frame files).

    Raises
    ------
    FormatError
        An image without a depth map (with ``depth_required``) or without a calibration.
    """
    frames = image_frames(images)
    if depth is None and depth_required:
        raise ParameterError("give the images' depth maps", param="depth")
    frames, _ = attach(frames, depth, "depth", role="depth", option="--depth", shared_ok=False,
                       required=True)  # fmt: skip
    frames, _ = attach(frames, calib, "calib", role="calib", option="--calib", required=True)
    return frames
