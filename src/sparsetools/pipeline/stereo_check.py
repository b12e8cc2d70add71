"""Batch job of the stereo consistency check of ground-truth maps (``dataset kitti-raw``).

Per frame: read a sparse ground-truth map (a KITTI depth PNG, e.g. an ``accumulate`` output),
the rectified pair (the map's camera and its stereo partner: KITTI ``image_02`` /
``image_03``) and the pair's focal length and baseline
(:func:`sparsetools.io.calib.read_kitti_stereo_rig`), and drop the points whose depth
disagrees with OpenCV's SGBM disparity (:func:`sparsetools.ops.stereo.stereo_check`).
A frame without a partner image is written unchanged (``checked`` False in its statistics).
With ``resize_to`` (maps made at an exact size, ``dataset kitti-raw --resize-to``) both images
are first resized to the maps' size (area interpolation when shrinking, as the dataset's
images) and fx scaled with the columns: disparities are then in the maps' pixels.

Outputs per frame, the layout of ``project`` / ``accumulate``: ``OUT/<sequence>/<frame>.png``
(the checked map, KITTI uint16) and, when the input map's folder has one,
``OUT/calib/<sequence>/<frame>.json`` (the map's calibration, copied).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..io.atomic import atomic_path
from ..io.sources import Frame
from ..ops.stereo import StereoCheckSettings
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask
from .provenance import settings_dict

__all__ = ["StereoCheckInput", "StereoCheckJob", "StereoCheckStats"]


@dataclass(frozen=True)
class StereoCheckInput:
    """One frame: its map, the map's calibration JSON (or None), the pair (``right`` None:
    no check) and the calibration folder / file giving fx and the baseline."""

    depth: str
    calib_json: str | None
    left: str
    right: str | None
    rig: str | None


@dataclass(frozen=True)
class StereoCheckStats(FrameStats):
    """One frame: whether it was checked, the map's points, those removed, and the pixels
    where SGBM found a disparity."""

    checked: bool
    points: int
    removed: int
    stereo_valid_pixels: int


@dataclass(frozen=True)
class StereoCheckJob(BatchJob[StereoCheckInput]):
    """The stereo check of every frame's map (picklable). Frames carry their map in
    ``Frame.depth``, the left image in ``Frame.image`` and the calibration in ``Frame.calib``;
    ``right`` maps a frame id to its partner image (absent: written unchanged)."""

    command: ClassVar[str] = "stereo-check"
    noun: ClassVar[str] = "stereo-checked depth maps"
    stats_type: ClassVar[type[FrameStats]] = StereoCheckStats

    settings: StereoCheckSettings = field(default_factory=StereoCheckSettings)
    right: tuple[tuple[str, str], ...] = ()
    resize_to: tuple[int, int] | None = None

    def record(self) -> dict:
        flat = {k: v for k, v in settings_dict(self.settings).items() if k != "sgbm"}
        flat.update({f"sgbm_{k}": v for k, v in settings_dict(self.settings.sgbm).items()})
        if self.resize_to is not None:  # only when set: older folders resume
            flat["resize_to"] = list(self.resize_to)
        return flat

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[StereoCheckInput]]:
        right = dict(self.right)
        out, tasks = Path(out_dir), []
        for f in frames:
            cj = _calib_json_of(f.depth, f.key)
            partner = right.get(f.id)
            inp = StereoCheckInput(str(f.depth), None if cj is None else str(cj), str(f.image),
                                   partner, None if f.calib is None else str(f.calib))  # fmt: skip
            sources = [p for p in (f.depth, cj, f.image, partner, f.calib) if p is not None]
            outputs = {"depth": f.key.path(out, ".png")}
            if cj is not None:
                outputs["calib"] = f.key.path(out, ".json", prefix="calib")
            tasks.append(FrameTask(f.key, inp, outputs, tuple(map(Path, sources))))
        return tasks

    def __call__(self, task: FrameTask[StereoCheckInput]) -> StereoCheckStats:
        from ..io.calib import read_kitti_stereo_rig
        from ..io.image import read_depth_png, read_image, write_depth_png
        from ..ops.stereo import stereo_check

        inp = task.inputs
        depth = read_depth_png(inp.depth)
        points = int(np.count_nonzero(depth))
        checked, removed, stereo_valid = False, 0, 0
        if inp.right is not None:
            fx, baseline = read_kitti_stereo_rig(inp.rig)
            # read_image gives RGB; SGBM matches grey levels, the channel order does not matter
            left, right = read_image(inp.left), read_image(inp.right)
            if self.resize_to is not None:
                fx *= self.resize_to[0] / left.shape[1]  # disparities scale with the columns
                left, right = _resized(left, self.resize_to), _resized(right, self.resize_to)
            depth, mask, disparity = stereo_check(depth, left, right, fx=fx, baseline=baseline,
                                                  settings=self.settings)  # fmt: skip
            checked, removed = True, int(np.count_nonzero(mask))
            stereo_valid = int(np.count_nonzero(np.isfinite(disparity)))
        write_depth_png(task.outputs["depth"], depth)
        if inp.calib_json is not None:
            with atomic_path(task.outputs["calib"]) as tmp:
                shutil.copyfile(inp.calib_json, tmp)
        return StereoCheckStats(checked=checked, points=points, removed=removed,
                                stereo_valid_pixels=stereo_valid)  # fmt: skip

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        stats = self.stats(summary)
        return {
            "checked": sum(st.checked for st in stats),
            "points": sum(st.points for st in stats),
            "removed": sum(st.removed for st in stats),
        }


def _resized(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    w, h = size
    if (image.shape[1], image.shape[0]) == (w, h):
        return image
    shrink = w <= image.shape[1] and h <= image.shape[0]
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def _calib_json_of(depth: Path, key) -> Path | None:
    """``<root>/calib/<sequence>/<frame>.json`` beside ``<root>/<sequence>/<frame>.png``."""
    root = depth.parent if not key.sequence else depth.parent.parent
    cand = key.path(root, ".json", prefix="calib")
    return cand if cand.is_file() else None
