"""One input path for one role -> its files by frame key; several inputs merged into frames;
the files of another input attached to frames by key."""

from __future__ import annotations

import os
from pathlib import Path

from ...errors import FormatError, ParameterError
from .frame import Frame, FrameKey, FrameList
from .kitti import (
    is_kitti_depth_completion,
    is_kitti_object,
    is_kitti_raw,
    is_kitti_raw_calib_dir,
    is_kitti_selection_maps,
    is_kitti_val_selection,
    kitti_depth_completion_index,
    kitti_object_index,
    kitti_raw_index,
    kitti_selection_maps_index,
    kitti_val_selection_index,
)
from .tree import (
    CALIB_SUFFIXES,
    CLOUD_SUFFIXES,
    DEPTH_SUFFIXES,
    IMAGE_SUFFIXES,
    FileIndex,
    index_tree,
    match_keys,
)
from .video import VIDEO_ROLES, is_video_folder, video_index

__all__ = ["ROLES", "attach", "index_input", "is_shared_calibration", "merge_frames"]

#: Role of an input -> (file suffixes, the role its files have in a sparsetools output folder).
ROLES = {
    "cloud": (CLOUD_SUFFIXES, "cloud"),
    "image": (IMAGE_SUFFIXES, "image"),
    "sparse": (DEPTH_SUFFIXES, "depth"),
    "gt": (DEPTH_SUFFIXES, "depth"),
    "depth": (DEPTH_SUFFIXES, "depth"),
    "confidence": (DEPTH_SUFFIXES, "confidence"),
    "calib": (CALIB_SUFFIXES, "calib"),
}


def index_input(
    path: str | os.PathLike,
    role: str,
    *,
    option: str,
    camera: int = 2,
    name: str | None = None,
) -> FileIndex:
    """The files of one input path for ``role``, keyed by frame.

    Parameters
    ----------
    path : path-like
        A file or a folder (any layout of the module docstring).
    role : {"cloud", "image", "sparse", "gt", "depth", "confidence", "calib"}
    option : str
        The option the path came from, for messages.
    camera : int
        KITTI camera index (``image_02``, ``proj_depth/*/image_02``).
    name : str, optional
        KITTI depth-completion map set (``velodyne_raw``, ``groundtruth``, ...).

    Raises
    ------
    FormatError
        Missing path, no files, or two files that are one frame.
    """
    if role not in ROLES:
        raise ParameterError(f"unknown input role {role!r}")
    suffixes, recorded_role = ROLES[role]
    p = Path(path)
    if p.is_dir():
        if is_video_folder(p) and role in VIDEO_ROLES:
            return video_index(p, role, option=option)
        if role in ("cloud", "image") and is_kitti_raw(p):
            return kitti_raw_index(p, what=role, camera=camera, option=option)
        if role in ("sparse", "gt", "depth", "confidence") and is_kitti_depth_completion(p):
            dc_role = role if role in ("sparse", "gt") else "sparse"
            return kitti_depth_completion_index(
                p, role=dc_role, name=name, camera=camera, option=option
            )
        if is_kitti_val_selection(p) and role in ("image", "sparse", "gt", "calib"):
            return kitti_val_selection_index(p, role=role, camera=camera, option=option)
        if role == "cloud" and is_kitti_object(p):
            return kitti_object_index(p, camera=camera)
        if role == "image" and is_kitti_object(p):
            base = p / "training" if (p / "training").is_dir() else p
            return index_tree(base / f"image_{camera}", suffixes, option=option)
        if role in ("sparse", "gt", "depth") and is_kitti_selection_maps(p):
            return kitti_selection_maps_index(p, camera=camera, option=option)
        if role == "calib" and is_kitti_raw_calib_dir(p):
            raise ParameterError(
                f"{option}: {p} is one KITTI raw calibration, not a folder of files"
            )
    return index_tree(p, suffixes, option=option, role=recorded_role)


def is_shared_calibration(path: str | os.PathLike) -> bool:
    """A calibration shared by every frame: one file, or a KITTI raw calibration folder."""
    p = Path(path)
    return p.is_file() or is_kitti_raw_calib_dir(p)


#: What a file of each role is called in messages.
_ROLE_NOUNS = {"image": "image", "calib": "calibration", "depth": "depth map",
               "sparse": "sparse depth map", "gt": "ground-truth depth map",
               "confidence": "confidence map", "cloud": "point cloud"}  # fmt: skip


def attach(
    frames: list[Frame],
    path: str | os.PathLike | None,
    field: str,
    *,
    role: str,
    option: str,
    shared_ok: bool = True,
    camera: int = 2,
    name: str | None = None,
    required: bool = False,
) -> tuple[list[Frame], int]:
    """Give every frame its file of another input (``field``: ``image``, ``calib``, ``depth``,
    ``gt``).

    A single file (or a KITTI raw calibration folder for ``calib``) is shared by every frame
    when ``shared_ok`` (or when there is one frame); a folder is indexed and matched by key.
    A frame without a match gets the path its file would have
    (``DIR/<sequence>/<frame>.<first suffix>``) so it fails in its own job, and is counted;
    with ``required`` an unmatched frame is an error naming the first one instead.

    Returns
    -------
    frames : list of Frame
    unmatched : int

    Raises
    ------
    FormatError
        ``required`` and a frame has no file in ``path``.
    """
    from dataclasses import replace

    if path is None:
        return frames, 0
    p = Path(path)
    if not p.exists():
        raise FormatError(f"{option}: {p}: no such file or folder")
    if (p.is_file() or (field == "calib" and is_kitti_raw_calib_dir(p))) and (
        shared_ok or len(frames) == 1
    ):
        if isinstance(frames, FrameList):
            return frames.with_shared(**{field: p}), 0
        return [replace(f, **{field: p}) for f in frames], 0
    if p.is_file():
        raise ParameterError(
            f"{option}: {p} is one file but {len(frames)} frames were given: pass a folder of "
            "files matched by frame"
        )
    index = index_input(p, role, option=option, camera=camera, name=name)
    found = match_keys([f.key for f in frames], index.files)
    suffix = ROLES[role][0][0]
    out = []
    for f in frames:
        out.append(replace(f, **{field: found.get(f.key) or f.key.path(p, suffix)}))
    unmatched = len(frames) - len(found)
    if unmatched and required:
        first = next(f for f in out if f.key not in found)
        raise FormatError(
            f"{option}: {p}: no {_ROLE_NOUNS.get(role, role)} for frame {first.key} (expected "
            f"{getattr(first, field)}; {unmatched} of {len(frames)} frames lack one)"
        )
    return out, unmatched


def merge_frames(indexes, field: str) -> list[Frame]:
    """Frames of several indexed inputs, each file in ``Frame.<field>``, sorted by key.

    Parameters
    ----------
    indexes : iterable of FileIndex
        One index per given path (see :func:`index_input`).
    field : str
        The :class:`Frame` field the files go in (``"image"``, ``"depth"``, ...).

    Raises
    ------
    FormatError
        Two inputs hold the same frame.
    """
    frames: dict[FrameKey, Frame] = {}
    for index in indexes:
        for key, f in index.files.items():
            if key in frames:
                raise FormatError(
                    f"{getattr(frames[key], field)} and {f} are the same frame '{key}': give "
                    "each once, or folders whose frames differ"
                )
            frames[key] = Frame(key=key, **{field: f})
    return [frames[k] for k in sorted(frames)]
