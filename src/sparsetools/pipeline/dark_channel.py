"""Batch job of ``sparsetools dark-channel``: dark channel, LDDCV map and mask of every image.

Per frame (key ``<sequence>/<frame>``), under one prefix per role:

- ``OUT/dark/<sequence>/<frame>.png``: the dark channel, 8-bit grey (``round(DC * 255)``;
  for an 8-bit input this is exactly one of the input's levels, so nothing is lost);
- ``OUT/lddcv/<sequence>/<frame>.npy``: the two-channel LDDCV map, (H, W, 2) float32 in
  [0, 1] (channel 0: intensity variation, 1: dark-channel variation); with
  ``--lddcv-format png`` instead two 16-bit grey PNGs ``<frame>_y.png`` and
  ``<frame>_dc.png`` holding ``round(v * 65535)``;
- ``OUT/mask/<sequence>/<frame>.png``: the mask ``|LDDCV| > T``, 8-bit 0 / 255; with
  ``--mask-mode separate`` one per channel, ``<frame>_y.png`` and ``<frame>_dc.png``;
- with ``--save-pictures``, ``OUT/pictures/<sequence>/<frame>.png``: the image, the dark
  channel, both LDDCV channels (0-0.2 shown as black to white) and the mask, stacked and
  labelled.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import FormatError
from ..io.atomic import atomic_path
from ..io.sources import Frame
from ..validate import check_choice, check_non_negative, check_odd
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask

__all__ = [
    "LDDCV_FORMATS",
    "LDDCV_PNG_SCALE",
    "DarkChannelInput",
    "DarkChannelJob",
    "DarkChannelSettings",
    "DarkChannelStats",
]

LDDCV_FORMATS = ("npy", "png")
#: A 16-bit LDDCV PNG stores ``round(v * 65535)``.
LDDCV_PNG_SCALE = 65535.0
#: Variation shown as white in the pictures (the docs' pictures use the same range).
PICTURE_VARIATION_MAX = 0.2
#: Suffixes of the two channels when they are written as separate files.
CHANNELS = ("y", "dc")


@dataclass(frozen=True)
class DarkChannelSettings:
    """What the dark-channel outputs depend on.

    Attributes
    ----------
    window : int, pixels
        Odd side ``N`` of the dark channel's square patch (paper: 15; ``--patch-size``).
    threshold : float
        Mask threshold ``T`` in the units of an image in [0, 1] (paper: 0.05).
    intensity : {"mean", "luma"}
        Image intensity of the LDDCV's first channel.
    mask_mode : {"norm", "any", "separate"}
        How the two channels make the mask (:func:`sparsetools.ops.dark_channel.lddcv_mask`).
    lddcv_format : {"npy", "png"}
    pictures : bool
        Also write a labelled picture per frame.
    """

    window: int = field(default=15, metadata={"option": "--patch-size"})
    threshold: float = field(default=0.05, metadata={"option": "--mask-threshold"})
    intensity: str = "mean"
    mask_mode: str = "norm"
    lddcv_format: str = "npy"
    pictures: bool = field(default=False, metadata={"option": "--save-pictures"})

    def __post_init__(self) -> None:
        from ..ops.dark_channel import COMBINE_MODES, INTENSITY_MODES

        object.__setattr__(self, "window", check_odd(self.window, "patch_size"))
        object.__setattr__(self, "threshold", check_non_negative(self.threshold, "mask_threshold"))
        check_choice(self.intensity, "intensity", INTENSITY_MODES)
        check_choice(self.mask_mode, "mask_mode", COMBINE_MODES)
        check_choice(self.lddcv_format, "lddcv_format", LDDCV_FORMATS)


@dataclass(frozen=True)
class DarkChannelInput:
    image: str


def _channel_paths(key, out: Path, prefix: str, suffix: str, role: str) -> dict[str, Path]:
    """``role_y`` / ``role_dc`` -> ``OUT/<prefix>/<sequence>/<frame>_y<suffix>`` ..."""
    from ..io.sources import FrameKey

    return {
        f"{role}_{c}": FrameKey(key.sequence, f"{key.frame}_{c}").path(out, suffix, prefix=prefix)
        for c in CHANNELS
    }


def _write_png(path: Path, array: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(array))
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 / uint16 PNG
        raise FormatError(f"{path}: OpenCV cannot encode PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


def _to_uint16(v: np.ndarray) -> np.ndarray:
    return np.rint(np.clip(v.astype(np.float64), 0.0, 1.0) * LDDCV_PNG_SCALE).astype(np.uint16)


def _grey_rgb(v: np.ndarray, top: float) -> np.ndarray:
    g = np.rint(np.clip(v.astype(np.float64) / top, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.repeat(g[:, :, None], 3, axis=2)


def _picture(image: np.ndarray, features) -> np.ndarray:
    from ..ops.colormap import side_by_side
    from ..ops.viz import label_panel

    masks = features.mask if features.mask.ndim == 3 else features.mask[:, :, None]
    names = {
        "norm": ("mask: |LDDCV|",),
        "any": ("mask: either channel",),
        "separate": ("mask: intensity channel", "mask: dark-channel channel"),
    }
    names = names[features.combine]
    share = [f"{100 * masks[:, :, k].mean():.1f} %" for k in range(masks.shape[2])]
    panels = [
        label_panel(image, "image"),
        label_panel(_grey_rgb(features.dark, 1.0), f"dark channel ({features.window}x"
                    f"{features.window})"),
        label_panel(_grey_rgb(features.lddcv[:, :, 0], PICTURE_VARIATION_MAX),
                    f"LDDCV intensity (0-{PICTURE_VARIATION_MAX:g})"),
        label_panel(_grey_rgb(features.lddcv[:, :, 1], PICTURE_VARIATION_MAX),
                    f"LDDCV dark channel (0-{PICTURE_VARIATION_MAX:g})"),
        *(label_panel(_grey_rgb(masks[:, :, k], 1.0),
                      f"{names[k]} > {features.threshold:g} ({share[k]})")
          for k in range(masks.shape[2])),
    ]  # fmt: skip
    return side_by_side(panels, vertical=True)


@dataclass(frozen=True)
class DarkChannelStats(FrameStats):
    """One image: the fraction of its pixels in the mask (with separate masks, of either
    channel's pixels counted apart), mean dark channel, mean LDDCV of each channel."""

    mask_fraction: float
    dark_mean: float
    lddcv_mean_y: float
    lddcv_mean_dc: float


@dataclass(frozen=True)
class DarkChannelJob(BatchJob[DarkChannelInput]):
    """``sparsetools dark-channel`` (picklable): per image read, compute, write every role."""

    command: ClassVar[str] = "dark-channel"
    noun: ClassVar[str] = "dark-channel maps"
    stats_type: ClassVar[type[FrameStats]] = DarkChannelStats

    settings: DarkChannelSettings = field(default_factory=DarkChannelSettings)

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[DarkChannelInput]]:
        """One task per image; roles ``dark``, ``lddcv`` (or ``lddcv_y``, ``lddcv_dc``),
        ``mask`` (or ``mask_y``, ``mask_dc``) and, with pictures, ``picture``."""
        s, out = self.settings, out_dir
        tasks = []
        for f in frames:
            outputs = {"dark": f.key.path(out, ".png", prefix="dark")}
            if s.lddcv_format == "npy":
                outputs["lddcv"] = f.key.path(out, ".npy", prefix="lddcv")
            else:
                outputs.update(_channel_paths(f.key, out, "lddcv", ".png", "lddcv"))
            if s.mask_mode == "separate":
                outputs.update(_channel_paths(f.key, out, "mask", ".png", "mask"))
            else:
                outputs["mask"] = f.key.path(out, ".png", prefix="mask")
            if s.pictures:
                outputs["picture"] = f.key.path(out, ".png", prefix="pictures")
            tasks.append(FrameTask(f.key, DarkChannelInput(str(f.image)), outputs, (f.image,)))
        return tasks

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Totals: ``mask_fraction``, the mean over the frames."""
        stats = self.stats(summary)
        return {"mask_fraction": sum(st.mask_fraction for st in stats) / len(stats) if stats
                else 0.0}  # fmt: skip

    def __call__(self, task: FrameTask[DarkChannelInput]) -> dict:
        from ..io.image import read_image, write_image
        from ..ops.dark_channel import dark_channel_features

        s, outputs = self.settings, task.outputs
        image = read_image(task.inputs.image)  # grey -> RGB; 16-bit refused
        f = dark_channel_features(
            image, window=s.window, threshold=s.threshold, intensity=s.intensity,
            combine=s.mask_mode,
        )  # fmt: skip
        _write_png(outputs["dark"], np.rint(f.dark.astype(np.float64) * 255.0).astype(np.uint8))
        if "lddcv" in outputs:
            with atomic_path(outputs["lddcv"]) as tmp, open(tmp, "wb") as fh:
                np.save(fh, f.lddcv.astype(np.float32))
        else:
            for k, c in enumerate(CHANNELS):
                _write_png(outputs[f"lddcv_{c}"], _to_uint16(f.lddcv[:, :, k]))
        if "mask" in outputs:
            _write_png(outputs["mask"], f.mask.astype(np.uint8) * 255)
        else:
            for k, c in enumerate(CHANNELS):
                _write_png(outputs[f"mask_{c}"], f.mask[:, :, k].astype(np.uint8) * 255)
        if "picture" in outputs:
            write_image(outputs["picture"], _picture(image, f))
        return DarkChannelStats(
            mask_fraction=float(f.mask.mean()),
            dark_mean=float(f.dark.mean(dtype=np.float64)),
            lddcv_mean_y=float(f.lddcv[:, :, 0].mean(dtype=np.float64)),
            lddcv_mean_dc=float(f.lddcv[:, :, 1].mean(dtype=np.float64)),
        )
