"""The cameras of a rig in one dataset (``--cameras``): one sample per (frame, camera).

Every camera's inputs are found as for a one-camera build (:func:`.build.find_build_inputs`),
then each frame gets the camera in its id, ``<sequence>/<camera>/<frame>`` (the KITTI raw
layout's order, ``<drive>/image_03/0000000005``: a split-file line names its camera by that
``image_0N`` folder, and every id keeps its sequence first, so ids of two cameras never collide
and the sample's files sit under ``rgb/<sequence>/<camera>/``). A sample's cameras share its
sequence, so splits by sequence keep them together; split lists (whose lines name one camera:
KITTI ``l`` / ``r``) give a frame the split of its first camera listed, in ``--cameras``
order, and every camera of the frame follows it. A frame that some camera lacks keeps the
cameras it has; the summary counts the missing (frame, camera) pairs (``unmatched``'s
``missing_camera``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from ...errors import ParameterError
from .build import BuildInputs, find_build_inputs
from .official_splits import official_split_lists
from .settings import BuildSettings
from .splits import split_file_assignments
from .staging import DatasetFrameInput

__all__ = ["CameraInputs", "camera_id", "find_rig_inputs", "parse_cameras"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraInputs:
    """One camera's inputs of a rig build (the arguments of :func:`.build.find_build_inputs`).

    Attributes
    ----------
    name : str
        The camera as ids and the ``camera`` column name it (``image_03``, ``CAM_BACK``).
    rgb, sparse : path-like
    gt, calib : path-like, optional
    index : int
        KITTI camera index (the ``image_0N`` folder and the calibration's ``P_rect_0N``).
    extra : tuple of (name, value)
        Per-frame fields of :class:`~.staging.DatasetFrameInput` by frame id (e.g. the
        nuScenes ``T_ego_cam``), as ``(field, {id: value})`` pairs.
    """

    name: str
    rgb: str | os.PathLike
    sparse: str | os.PathLike
    gt: str | os.PathLike | None = None
    calib: str | os.PathLike | None = None
    confidence: str | os.PathLike | None = None
    index: int = 2
    extra: tuple = ()


def parse_cameras(text: str | Sequence[str] | None, known: Sequence[str], *, option: str) -> tuple:
    """``--cameras A,B`` (or ``all``: every one of ``known``) as a tuple of names, in the
    order given; duplicates and unknown names are refused naming ``known``."""
    if text is None:
        return ()
    items = [c.strip() for c in text.split(",")] if isinstance(text, str) else list(text)
    if items == ["all"]:
        return tuple(known)
    if not items or any(not c for c in items):
        raise ParameterError(f"give camera names separated by commas, got {text!r}", param=option)
    unknown = [c for c in items if c not in known]
    if unknown:
        raise ParameterError(
            f"unknown camera {unknown[0]!r} (known: {', '.join(known)})", param=option
        )
    if len(set(items)) != len(items):
        raise ParameterError(f"camera {items[0]!r} given twice", param=option)
    return tuple(items)


def camera_id(frame_id: str, camera: str) -> str:
    """``<sequence>/<camera>/<frame>``: the camera inserted before the frame's last part."""
    head, sep, tail = frame_id.rpartition("/")
    return f"{head}/{camera}/{tail}" if sep else f"{camera}/{tail}"


def find_rig_inputs(settings: BuildSettings, cameras: Sequence[CameraInputs]) -> BuildInputs:
    """The frames of every camera, ids ``<sequence>/<camera>/<frame>``, the cameras of one
    frame in one split (see the module docstring).

    Raises
    ------
    ParameterError
        Two cameras of one name, no frame listed in the split lists, or the tree split
        (``--splits tree``: one-camera builds only).
    """
    if len({c.name for c in cameras}) != len(cameras):
        raise ParameterError("a camera is given twice", param="--cameras")
    lists = None
    if settings.official_split:
        lists = official_split_lists(settings.official_split)
    elif settings.split_files:
        lists = settings.split_files
    elif settings.split_from_tree:
        raise ParameterError("--splits tree takes one camera", param="--cameras")
    # every frame of every camera first (no list drops any), the lists are applied below
    plain = replace(settings, split={"train": 1.0}, split_files=None, official_split=None)
    frames: list[DatasetFrameInput] = []
    unmatched: dict[str, int] = {}
    roots: list[Path] = []
    seconds = 0.0
    for cam in cameras:
        found = find_build_inputs(
            plain, rgb=cam.rgb, sparse=cam.sparse, gt=cam.gt, confidence=cam.confidence,
            calib=cam.calib, camera=cam.index,
        )  # fmt: skip
        extra = dict(cam.extra)
        for x in found.frames:
            fields = {name: values[x.id] for name, values in extra.items() if x.id in values}
            frames.append(
                replace(x, id=camera_id(x.id, cam.name), camera=cam.name,
                        calib_camera=cam.index, split=None, **fields)
            )  # fmt: skip
        for k, v in found.unmatched.items():
            unmatched[k] = unmatched.get(k, 0) + v
        roots += [r for r in found.roots if r not in roots]
        seconds += found.seconds
    # a frame some camera lacks (no image, no map) is kept with the cameras it has: counted
    have: dict[tuple[str, str], int] = {}
    for x in frames:
        have[x.sequence, x.frame] = have.get((x.sequence, x.frame), 0) + 1
    unmatched["missing_camera"] = sum(len(cameras) - n for n in have.values())
    split_lists = None
    if lists is not None:
        assignment, split_lists = split_file_assignments(
            lists, {x.id: x.sequence for x in frames}, camera=cameras[0].index,
            name=settings.official_split,
        )  # fmt: skip
        frames, unmatched["not_in_split_files"] = _frame_splits(frames, assignment, cameras)
        split_lists = replace(split_lists, not_listed=unmatched["not_in_split_files"])
        if not frames:
            raise ParameterError(
                f"no frame is listed in the split lists: {split_lists.listed} line(s), none "
                "matched a frame of the inputs"
            )
    order = {c.name: i for i, c in enumerate(cameras)}
    frames.sort(key=lambda x: (x.sequence, x.frame, order[x.camera]))
    return BuildInputs(frames, tuple(roots), unmatched, split_lists, seconds)


def _frame_splits(frames, assignment, cameras) -> tuple[list[DatasetFrameInput], int]:
    """Every camera of a frame in the split of its first camera listed (``cameras`` order);
    frames of no list left out (their count: the second value, in samples)."""
    order = {c.name: i for i, c in enumerate(cameras)}
    split_of: dict[tuple[str, str], tuple[int, str]] = {}
    conflicts = set()
    for x in frames:
        s = assignment.get(x.id)
        if s is None:
            continue
        key = (x.sequence, x.frame)
        rank = order[x.camera]
        have = split_of.get(key)
        if have is not None and have[1] != s:
            conflicts.add(key)
        if have is None or rank < have[0]:
            split_of[key] = (rank, s)
    if conflicts:
        log.warning(
            "%d frame(s) are listed in different splits for different cameras: all their "
            "cameras go to the split of the first camera listed (%s order)",
            len(conflicts), ",".join(c.name for c in cameras),
        )  # fmt: skip
    kept = [replace(x, split=split_of[x.sequence, x.frame][1]) for x in frames
            if (x.sequence, x.frame) in split_of]  # fmt: skip
    return kept, len(frames) - len(kept)
