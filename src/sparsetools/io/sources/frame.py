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
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from ...errors import ParameterError

__all__ = ["PATH_FIELDS", "Frame", "FrameKey", "FrameList", "Sweep", "check_key_part"]

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


@dataclass(frozen=True, order=True, slots=True)
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
    def checked(cls, sequence: str, frame: str) -> FrameKey:
        """A key of parts already checked (by the index that holds them): made without
        checking them again."""
        key = object.__new__(cls)
        object.__setattr__(key, "sequence", sequence)
        object.__setattr__(key, "frame", frame)
        return key

    @classmethod
    def parse(cls, text: str) -> FrameKey:
        """Inverse of ``str(key)``: the last path part is the frame, the rest the sequence."""
        seq, _, frame = str(text).rpartition("/")
        return cls(seq, frame)

    def path(self, root: str | os.PathLike, suffix: str, *, prefix: str = "") -> Path:
        """``root/<prefix>/<sequence>/<frame><suffix>`` (empty parts left out)."""
        # one string, parsed once: the frame runner makes two of these per frame and task
        parts = [os.fspath(root)]
        if prefix:
            parts.append(prefix)
        if self.sequence:
            parts.append(self.sequence)
        parts.append(f"{self.frame}{suffix}")
        return Path(os.path.join(*parts))


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


#: Frame fields holding one input file's path.
PATH_FIELDS = ("cloud", "image", "depth", "gt", "mask", "calib")


class FrameList(Sequence[Frame]):
    """The frames of a batch held compactly: a :class:`Frame` is made when one is asked for.

    A million frames as :class:`Frame` objects with :class:`~pathlib.Path` fields take about
    1 KB each; here a frame is its key's and file's strings in the :class:`FileMap` it came
    from plus what every frame shares (a calibration file given once), about 100 bytes
    (issue 28). Slicing gives a list of frames.

    Parameters
    ----------
    files : FileMap
        Frame key -> file, in key order.
    field : str
        The :class:`Frame` field the files fill (``cloud``, ``image``, ...).
    shared : mapping, optional
        Field -> value every frame has.
    """

    def __init__(self, files, *, field: str = "cloud", shared: Mapping | None = None):
        self.files = files
        self.field = field
        self.shared = dict(shared or {})

    def __len__(self) -> int:
        return len(self.files)

    def _frame(self, i: int) -> Frame:
        key, path = self.files.item_at(i)
        return Frame(key=key, **{self.field: path}, **self.shared)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self._frame(j) for j in range(*i.indices(len(self)))]
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError("frame index out of range")
        return self._frame(i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self._frame(i)

    def with_shared(self, **values) -> FrameList:
        """These frames with ``values`` (field -> value) given to every frame."""
        return FrameList(self.files, field=self.field, shared={**self.shared, **values})
