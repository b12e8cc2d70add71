"""Camera images at a map's resolution: resized and cropped, with their adjusted intrinsics.

A depth map projected with ``--resize S --crop TOP,LEFT,H,W`` needs the camera image made the
same way (and its intrinsics, METHODS.md section 0) before a dataset can pair them. Per frame
this job writes ``OUT/<sequence>/<frame>.png`` (OpenCV area interpolation when shrinking,
bilinear when enlarging, then the crop) and ``OUT/calib/<sequence>/<frame>.json``: the
frame's calibration resized and cropped exactly as :mod:`.project` does.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..calibration import Calibration
from ..errors import FormatError, ParameterError
from ..io.sources import Frame
from ..validate import check_positive, parse_crop
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames

__all__ = ["CameraImageInput", "CameraImageJob", "CameraImageSettings", "run_camera_images"]


@dataclass(frozen=True)
class CameraImageSettings:
    """How images are brought to the maps' resolution (as ``project --resize/--crop``)."""

    resize: float | None = None
    crop: tuple[int, int, int, int] | None = None

    def __post_init__(self) -> None:
        check_positive(self.resize, "resize", allow_none=True)
        if self.crop is not None:
            object.__setattr__(self, "crop", parse_crop(self.crop))


@dataclass(frozen=True)
class CameraImageInput:
    image: str
    calibration: Calibration


@dataclass(frozen=True)
class CameraImageJob:
    """Per frame: read, resize, crop, write the image and its calibration (atomically)."""

    settings: CameraImageSettings

    def __call__(self, task: FrameTask[CameraImageInput]) -> dict:
        import cv2

        from ..io.calib import write_json_calib
        from ..io.image import read_image, write_image

        s, inp = self.settings, task.inputs
        rgb = read_image(inp.image)
        calib = inp.calibration
        if calib.width is not None and (calib.width, calib.height) != (rgb.shape[1], rgb.shape[0]):
            raise FormatError(
                f"{inp.image}: the image is {rgb.shape[1]}x{rgb.shape[0]} but its calibration "
                f"says {calib.width}x{calib.height}"
            )
        calib = calib.with_size(rgb.shape[1], rgb.shape[0])
        if s.resize is not None and s.resize != 1.0:
            calib = calib.resized(s.resize)
            interp = cv2.INTER_AREA if s.resize < 1 else cv2.INTER_LINEAR
            rgb = cv2.resize(rgb, (calib.width, calib.height), interpolation=interp)
        if s.crop is not None:
            top, left, h, w = s.crop
            if top + h > rgb.shape[0] or left + w > rgb.shape[1]:
                raise ParameterError(
                    f"crop {s.crop} does not fit the {rgb.shape[1]}x{rgb.shape[0]} image",
                    param="crop",
                )
            calib = calib.cropped(top, left, h, w)
            rgb = rgb[top : top + h, left : left + w]
        write_image(task.outputs["image"], rgb)
        write_json_calib(
            task.outputs["calib"], calib, frame=task.frame_id, image=inp.image,
            resize=s.resize, crop=s.crop,
        )  # fmt: skip
        return {"width": int(rgb.shape[1]), "height": int(rgb.shape[0])}


def run_camera_images(
    frames: list[Frame],
    out_dir: str | os.PathLike,
    settings: CameraImageSettings,
    *,
    batch: Batch | None = None,
) -> RunSummary:
    """Write every frame's camera image at the maps' resolution (frames need ``image`` and
    ``calibration``, as :func:`sparsetools.io.sources.nuscenes_frames` gives them)."""
    batch = batch or Batch()
    out = check_output_dir(out_dir, [])
    tasks = []
    for f in frames:
        if f.image is None or f.calibration is None:
            raise ParameterError(f"frame {f.key} has no camera image or calibration")
        tasks.append(
            FrameTask(
                f.key,
                CameraImageInput(str(f.image), f.calibration),
                {
                    "image": f.key.path(out, ".png"),
                    "calib": f.key.path(out, ".json", prefix="calib"),
                },
                (Path(f.image), *f.extra_inputs),
            )
        )
    spec = RunSpec("camera-images", out, settings, noun="camera images")
    return run_frames(CameraImageJob(settings), tasks, batch=batch, spec=spec, desc="images")
