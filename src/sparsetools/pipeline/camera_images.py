"""Camera images at a map's resolution: resized and cropped, with their adjusted intrinsics.

A depth map projected with ``--resize S --crop WxH+LEFT+TOP`` needs the camera image made the
same way (and its intrinsics, METHODS.md section 0) before a dataset can pair them. Per frame
this job writes ``OUT/<sequence>/<frame>.png`` (OpenCV area interpolation when shrinking,
bilinear when enlarging, then the crop) and ``OUT/calib/<sequence>/<frame>.json``: the
frame's calibration resized and cropped exactly as :mod:`.project` does. ``resize_to`` brings
every image to one exact size instead (``dataset kitti-raw --resize-to``: KITTI's drives differ
in size), each axis scaled by its own factor.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from ..calibration import Calibration
from ..errors import FormatError, ParameterError
from ..io.sources import Frame
from ..validate import check_positive, parse_crop, parse_size
from .core import BatchJob, FrameStats, FrameTask

__all__ = ["CameraImageInput", "CameraImageJob", "CameraImageSettings", "CameraImageStats"]


@dataclass(frozen=True)
class CameraImageSettings:
    """How images are brought to the maps' resolution (as ``project --resize/--crop``);
    ``resize_to``: instead of ``resize``, exactly this (width, height) (``dataset kitti-raw
    --resize-to``, each axis scaled by its own factor)."""

    resize: float | None = None
    crop: tuple[int, int, int, int] | None = None
    resize_to: tuple[int, int] | None = field(
        default=None, metadata={"option": "--resize-to", "omit_default": True}
    )

    def __post_init__(self) -> None:
        check_positive(self.resize, "resize", allow_none=True)
        if self.crop is not None:
            object.__setattr__(self, "crop", parse_crop(self.crop))
        if self.resize_to is not None:
            object.__setattr__(self, "resize_to", parse_size(self.resize_to, "--resize-to"))
            if self.resize is not None:
                raise ParameterError("--resize and --resize-to exclude each other",
                                     param="resize_to")  # fmt: skip


@dataclass(frozen=True)
class CameraImageInput:
    image: str
    calibration: Calibration


@dataclass(frozen=True)
class CameraImageStats(FrameStats):
    """One image: its size after resize and crop, pixels."""

    width: int
    height: int


@dataclass(frozen=True)
class CameraImageJob(BatchJob[CameraImageInput]):
    """Per frame: read, resize, crop, write the image and its calibration (atomically)."""

    command: ClassVar[str] = "camera-images"
    noun: ClassVar[str] = "camera images"
    stats_type: ClassVar[type[FrameStats]] = CameraImageStats

    settings: CameraImageSettings = field(default_factory=CameraImageSettings)

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[CameraImageInput]]:
        """One task per frame (frames need ``image`` and ``calibration``, as
        :func:`sparsetools.io.sources.nuscenes_frames` gives them)."""
        tasks = []
        for f in frames:
            if f.image is None or f.calibration is None:
                raise ParameterError(f"frame {f.key} has no camera image or calibration")
            outputs = {"image": f.key.path(out_dir, ".png"),
                       "calib": f.key.path(out_dir, ".json", prefix="calib")}  # fmt: skip
            calib_file = () if f.calib is None else (Path(f.calib),)  # where it was read from
            tasks.append(FrameTask(f.key, CameraImageInput(str(f.image), f.calibration), outputs,
                                   (Path(f.image), *calib_file, *f.extra_inputs)))  # fmt: skip
        return tasks

    def __call__(self, task: FrameTask[CameraImageInput]) -> CameraImageStats:
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
        if s.resize_to is not None and s.resize_to != calib.size:
            w, h = s.resize_to
            # area interpolation averages the pixels each output pixel covers (no aliasing)
            # when shrinking; it would repeat pixels when enlarging, where bilinear is used
            shrink = w <= calib.width and h <= calib.height
            calib = calib.resized_to(w, h)
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if shrink
                             else cv2.INTER_LINEAR)  # fmt: skip
        if s.crop is not None:
            top, left, h, w = s.crop
            calib = calib.cropped(top, left, h, w)  # refuses a crop that does not fit
            rgb = rgb[top : top + h, left : left + w]
        write_image(task.outputs["image"], rgb)
        write_json_calib(
            task.outputs["calib"], calib, frame=task.frame_id, image=inp.image,
            resize=s.resize, crop=s.crop,
            **({"resize_to": list(s.resize_to)} if s.resize_to is not None else {}),
        )  # fmt: skip
        return CameraImageStats(width=int(rgb.shape[1]), height=int(rgb.shape[0]))
