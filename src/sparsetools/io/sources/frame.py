"""The frame record every batch command works on: ``(sequence, frame)`` plus its files.

A frame is identified by a :class:`FrameKey`: the sequence it belongs to (a KITTI raw drive
``2011_09_26_drive_0001_sync``, a nuScenes scene ``scene-0061``, a sub-folder of a folder
tree; ``""`` for a flat folder) and its name within the sequence (``0000000005``, a sample
token, a file stem). Outputs mirror the key: ``OUT/<sequence>/<frame>.png``, or
``OUT/<frame>.png`` for a flat input, so frames of different sequences never collide.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from ...errors import ParameterError

__all__ = ["Frame", "FrameKey", "Sweep", "check_key_part"]

_BAD_PART = re.compile(r"[\x00-\x1f\\]")


def check_key_part(text: str, what: str) -> str:
    """``text`` when it is a safe relative path (no ``..``, no absolute path, no hidden part)."""
    if not isinstance(text, str):
        raise ParameterError(f"{what} must be a string, got {type(text).__name__}")
    if text == "":
        return text
    parts = PurePosixPath(text).parts
    if (
        text.startswith("/")
        or _BAD_PART.search(text)
        or any(p in ("", ".", "..") or p.startswith(".") for p in parts)
        or text != "/".join(parts)
    ):
        raise ParameterError(f"{what} {text!r} is not a safe relative name")
    return text


@dataclass(frozen=True, order=True)
class FrameKey:
    """Identity of one frame: ``sequence`` (``""`` for flat inputs) and ``frame``.

    ``str(key)`` is ``"<sequence>/<frame>"`` (or ``"<frame>"``): the id used in messages,
    dataset manifests and per-frame random seeds.
    """

    sequence: str
    frame: str

    def __post_init__(self) -> None:
        check_key_part(self.sequence, "sequence name")
        check_key_part(self.frame, "frame name")
        if not self.frame or "/" in self.frame:
            raise ParameterError(f"frame name {self.frame!r} must be one non-empty path part")

    def __str__(self) -> str:
        return f"{self.sequence}/{self.frame}" if self.sequence else self.frame

    @classmethod
    def parse(cls, text: str) -> FrameKey:
        """Inverse of ``str(key)``: the last path part is the frame, the rest the sequence."""
        seq, _, frame = str(text).rpartition("/")
        return cls(seq, frame)

    def path(self, root: str | os.PathLike, suffix: str, *, prefix: str = "") -> Path:
        """``root/<prefix>/<sequence>/<frame><suffix>`` (empty parts left out)."""
        p = Path(root)
        if prefix:
            p = p / prefix
        if self.sequence:
            p = p / self.sequence
        return p / f"{self.frame}{suffix}"


@dataclass(frozen=True)
class Sweep:
    """An earlier sweep accumulated into a key frame's cloud (nuScenes multi-sweep radar).

    Attributes
    ----------
    path : Path
    T_key_from_sweep : tuple of 16 floats or None
        Row-major 4x4 transform from this sweep's sensor frame to the key sweep's sensor
        frame (None: identity).
    """

    path: Path
    T_key_from_sweep: tuple[float, ...] | None = None


@dataclass(frozen=True)
class Frame:
    """One frame of a batch, before anything is read.

    Attributes
    ----------
    key : FrameKey
    cloud : Path, optional
        LiDAR or radar point cloud.
    sweeps : tuple of Sweep
        Earlier sweeps merged into ``cloud`` (empty for one sweep).
    image : Path, optional
        Camera image (also what gives a depth map its size).
    depth : Path, optional
        A depth-like map of the frame (sparse LiDAR/radar depth, a dense depth map).
    gt : Path, optional
        A reference depth map of the frame (ground truth, the LiDAR map radar is compared
        with).
    mask : Path, optional
        Moving-object mask of the frame (PNG, non-zero = moving).
    calib : Path, optional
        Calibration file, or a KITTI raw date folder holding the calibration pair.
    calibration : Calibration, optional
        A calibration the source computed itself (nuScenes: the chain of poses).
    pose : tuple of 16 floats, optional
        Row-major 4x4 ``T_world_from_sensor`` where the source knows it.
    timestamp : float, optional
        Seconds.
    split : str, optional
        Split the dataset tree assigns (KITTI depth completion ``train`` / ``val``).
    extra_inputs : tuple of Path
        Other files the frame depends on (nuScenes tables): their identity decides resume.
    """

    key: FrameKey
    cloud: Path | None = None
    sweeps: tuple[Sweep, ...] = ()
    image: Path | None = None
    depth: Path | None = None
    gt: Path | None = None
    mask: Path | None = None
    calib: Path | None = None
    calibration: object | None = field(default=None, compare=False, repr=False)
    pose: tuple[float, ...] | None = field(default=None, compare=False, repr=False)
    timestamp: float | None = None
    split: str | None = None
    extra_inputs: tuple[Path, ...] = ()

    @property
    def id(self) -> str:
        return str(self.key)

    def files(self) -> tuple[Path, ...]:
        """Every input file of the frame (for resume identity and input-vs-output checks)."""
        out = [
            p
            for p in (self.cloud, self.image, self.depth, self.gt, self.mask, self.calib)
            if p is not None
        ]
        out.extend(s.path for s in self.sweeps)
        out.extend(self.extra_inputs)
        return tuple(out)
