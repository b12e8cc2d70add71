"""The ``synth-scene --video`` layout: ``VIDEO/<sequence>/{image_2,velodyne,depth_gt,calib,
moving_mask}/<frame>.*`` with ``poses.txt`` (camera poses, KITTI odometry format) and
``times.txt`` per sequence.

A role's files are keyed ``(<sequence>, <frame>)``, so the images, scans, depth and
calibrations of one frame match each other across roles; the index also carries each frame's
camera pose (``T_world_from_cam``, line ``frame_index`` of ``poses.txt``) and time.
"""

from __future__ import annotations

import os
from pathlib import Path

from ...errors import FormatError
from .frame import FrameKey
from .tree import FileIndex, file_stem

__all__ = ["VIDEO_ROLES", "is_video_folder", "video_index"]

#: Role -> (sub-folder, suffixes).
VIDEO_ROLES = {
    "image": ("image_2", (".png",)),
    "cloud": ("velodyne", (".bin",)),
    "gt": ("depth_gt", (".png",)),
    "depth": ("depth_gt", (".png",)),
    "calib": ("calib", (".txt",)),
    "mask": ("moving_mask", (".png",)),
}


def _is_sequence(p: Path) -> bool:
    return (p / "image_2").is_dir() and (p / "poses.txt").is_file()


def is_video_folder(path: str | os.PathLike) -> bool:
    """A synthetic video folder (``video.json`` beside its sequences) or one sequence of it."""
    p = Path(path)
    return p.is_dir() and ((p / "video.json").is_file() or _is_sequence(p))


def _sequences(root: Path) -> list[Path]:
    if _is_sequence(root):
        return [root]
    return sorted(d for d in root.iterdir() if not d.name.startswith(".") and _is_sequence(d))


def video_index(path: str | os.PathLike, role: str, *, option: str) -> FileIndex:
    """Files of one role of a video folder, with the camera pose and time of each frame.

    Raises
    ------
    FormatError
        A role the layout does not hold, no files, unreadable poses, or two frames whose
        names are one number (``1`` and ``01``: they would share a pose line).
    """
    from ..poses import read_kitti_poses, read_times
    from .poses import FrameNumbers, frame_number

    root = Path(path)
    if role not in VIDEO_ROLES:
        raise FormatError(f"{option}: a synthetic video folder holds no {role} files")
    sub, suffixes = VIDEO_ROLES[role]
    files, poses, times, calib, images = {}, {}, {}, {}, {}
    numbers = FrameNumbers()
    for seq in _sequences(root):
        folder = seq / sub
        if not folder.is_dir():
            continue
        stack = read_kitti_poses(seq / "poses.txt")
        clock = read_times(seq / "times.txt") if (seq / "times.txt").is_file() else None
        for f in sorted(folder.iterdir()):
            if not f.is_file() or f.name.startswith(".") or f.suffix.lower() not in suffixes:
                continue
            key = FrameKey(seq.name, file_stem(f))
            files[key] = f
            # a scan or an image brings its calibration (and a scan its image), as KITTI trees do
            if role in ("cloud", "image") and (seq / "calib" / f"{key.frame}.txt").is_file():
                calib[key] = seq / "calib" / f"{key.frame}.txt"
            if role == "cloud":
                if (seq / "image_2" / f"{key.frame}.png").is_file():
                    images[key] = seq / "image_2" / f"{key.frame}.png"
            i = frame_number(key)
            if i is not None:
                numbers.take(seq / "poses.txt", i, key)
            if i is not None and i < len(stack):
                poses[key] = tuple(float(v) for v in stack[i].reshape(-1))
                if clock is not None and i < len(clock):
                    times[key] = float(clock[i])
    if not files:
        raise FormatError(f"{option}: {root}: no <sequence>/{sub}/ files in this video folder")
    return FileIndex(
        root, files, layout="synthetic-video", calib=calib, images=images, poses=poses,
        times=times,
    )  # fmt: skip
