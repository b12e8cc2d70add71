"""KITTI raw trees for the tests, cut from the real 11-frame sequence of ../shared/data/real
(2011_09_26, frames 0000000000-0000000010: image_02, velodyne_points, the calibration pair)."""

from __future__ import annotations

import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

DATE = "2011_09_26"
CALIB_FILES = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt")


def make_raw_tree(
    real_dir: Path,
    root: Path,
    drives: Mapping[str, Sequence[int | tuple[int, int]]],
    *,
    cameras: Sequence[str] = ("image_02",),
) -> Path:
    """``root/2011_09_26/{calib files, <drive>/{velodyne_points, <camera>...}/data/}``.

    ``drives`` maps a drive folder name to its frames: a real frame number (kept as its name),
    or ``(real frame, name)`` to rename it. Every camera's images are copies of the real
    ``image_02`` (the sequence has no other camera). Returns ``root``.
    """
    seq = Path(real_dir) / "kitti-raw-sequence-2011_09_26"
    date = Path(root) / DATE
    date.mkdir(parents=True, exist_ok=True)
    for name in CALIB_FILES:
        shutil.copy(seq / name, date / name)
    for drive, frames in drives.items():
        for frame in frames:
            src, dst = frame if isinstance(frame, tuple) else (frame, frame)
            sources = [("velodyne_points", "velodyne_points", ".bin")]
            sources += [(cam, "image_02", ".png") for cam in cameras]
            for sub, real_sub, ext in sources:
                folder = date / drive / sub / "data"
                folder.mkdir(parents=True, exist_ok=True)
                shutil.copy(
                    seq / real_sub / "data" / f"{src:010d}{ext}", folder / f"{dst:010d}{ext}"
                )
    return Path(root)
