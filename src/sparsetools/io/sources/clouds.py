"""The frames of point-cloud commands (``project``, ``beams``, ``accumulate``): clouds given as
files and folders, KITTI raw drives / date folders, a KITTI object root, or a nuScenes root."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ...errors import FormatError, ParameterError, UsageError
from .frame import Frame, FrameKey, FrameList
from .index import attach, index_input
from .nuscenes import nuscenes_frames
from .tree import FileMap

__all__ = ["CloudSource", "cloud_frames", "cloud_source"]


def cloud_frames(
    paths: list[str | os.PathLike],
    *,
    calib: str | os.PathLike | None = None,
    image: str | os.PathLike | None = None,
    camera: int = 2,
    option: str = "CLOUD",
) -> Sequence[Frame]:
    """Frames of point-cloud inputs (files, folders, KITTI raw / object trees), sorted by key
    (a :class:`FrameList` for one folder of clouds).

    The layout's own calibration and image (KITTI raw date folder, KITTI object
    ``calib/``, ``image_2/``) come with the frames; ``calib`` and ``image`` replace them:
    one file or KITTI raw folder shared by every frame, or a folder matched by frame key.

    Raises
    ------
    FormatError
        Missing paths, no clouds, or two inputs that are the same frame.
    """
    from dataclasses import replace

    if not paths:
        raise ParameterError("no point clouds given")
    if len(paths) == 1:
        index = index_input(paths[0], "cloud", option=option, camera=camera)
        if isinstance(index.files, FileMap) and not (index.calib or index.images or index.splits):
            # a folder of clouds: held compactly (a million frames in ~100 MB less)
            out = FrameList(index.files, field="cloud")
            if calib is not None:
                out, _ = attach(out, calib, "calib", role="calib", option="--calib",
                                camera=camera)  # fmt: skip
            if image is not None:
                out, _ = attach(out, image, "image", role="image", option="--image",
                                camera=camera)  # fmt: skip
            return out
    frames: dict[FrameKey, Frame] = {}
    for path in paths:
        index = index_input(path, "cloud", option=option, camera=camera)
        for key, cloud in index.files.items():
            if key in frames:
                raise FormatError(
                    f"{frames[key].cloud} and {cloud} are the same frame '{key}': give each "
                    "once, or folders whose frames differ"
                )
            frames[key] = Frame(
                key=key,
                cloud=cloud,
                calib=index.calib.get(key),
                image=index.images.get(key),
                split=index.splits.get(key),
            )
    out = [frames[k] for k in sorted(frames)]
    if calib is not None:
        out, _ = attach(out, calib, "calib", role="calib", option="--calib", camera=camera)
    if image is not None:
        out, _ = attach(out, image, "image", role="image", option="--image", camera=camera)
        # an image given explicitly gives the size, not the layout's image of another camera
    return [replace(f) for f in out]


@dataclass(frozen=True)
class CloudSource:
    """The frames of one cloud source and what the run needs to know of it.

    Attributes
    ----------
    frames : sequence of Frame
        Sorted by key, each with a calibration (file, KITTI raw folder, or computed); a
        :class:`FrameList` for one folder of clouds.
    camera : int or str
        The camera the maps are for: a KITTI index, a nuScenes channel, or a camera name of
        JSON calibrations.
    inputs : tuple of Path
        The paths the user gave (the output folder may not be inside one of them).
    """

    frames: Sequence[Frame]
    camera: int | str
    inputs: tuple[Path, ...]


def _camera(camera: str | None, *, nuscenes: bool, clouds: bool) -> int | str:
    if nuscenes:
        return camera or "CAM_FRONT"
    if camera is None:
        return 2
    if str(camera).isdigit():
        return int(camera)
    if clouds:
        return str(camera)  # a camera name, for JSON calibrations holding several cameras
    raise UsageError(f"KITTI camera is an index 0-3, got {camera!r}", param="camera")


def cloud_source(
    *,
    clouds=(),
    kitti_raw=(),
    kitti_object: str | os.PathLike | None = None,
    nuscenes: str | os.PathLike | None = None,
    calib: str | os.PathLike | None = None,
    image: str | os.PathLike | None = None,
    camera: str | None = None,
    nuscenes_version: str = "v1.0-mini",
    sensor: str = "RADAR_FRONT",
    sweeps: int | None = None,
) -> CloudSource:
    """The frames of exactly one cloud source, each with its calibration.

    Parameters
    ----------
    clouds : sequence of path-like
        Cloud files and folders (``calib`` and ``image`` give their calibration and size
        when the layout has none).
    kitti_raw : sequence of path-like
        KITTI raw drives, date folders or roots of dates.
    kitti_object : path-like, optional
        A KITTI object root.
    nuscenes : path-like, optional
        A nuScenes root; ``nuscenes_version``, ``sensor`` and ``sweeps`` (default 5 for
        radar, 1 for LiDAR) select what is projected.
    camera : str, optional
        KITTI camera index (default 2), nuScenes channel (default CAM_FRONT), or the camera
        name of JSON calibrations.

    Raises
    ------
    UsageError
        Not exactly one source, ``calib`` / ``image`` with a layout that brings its own, or a
        frame without a calibration.
    """
    given = [name for name, v in (("CLOUD", clouds), ("--kitti-raw", kitti_raw),
                                  ("--kitti-object", kitti_object), ("--nuscenes", nuscenes))
             if v]  # fmt: skip
    if len(given) != 1:
        raise UsageError(
            "give exactly one source: CLOUD..., --kitti-raw, --kitti-object or --nuscenes"
            + (f" (got {', '.join(given)})" if given else "")
        )
    if not clouds and (calib is not None or image is not None):
        opt = "--calib" if calib is not None else "--image"
        raise UsageError(f"{opt} goes with CLOUD arguments ({given[0]} has its own)")
    cam = _camera(camera, nuscenes=bool(nuscenes), clouds=bool(clouds))
    if nuscenes:
        n = sweeps if sweeps is not None else (5 if sensor.upper().startswith("RADAR") else 1)
        frames = nuscenes_frames(nuscenes, version=nuscenes_version, sensor=sensor, camera=cam,
                                 sweeps=n)  # fmt: skip
        return CloudSource(frames, cam, (Path(nuscenes),))
    sources = [Path(p) for p in (list(clouds) or list(kitti_raw) or [kitti_object])]
    frames = cloud_frames(sources, calib=calib, image=image,
                          camera=cam if isinstance(cam, int) else 2)  # fmt: skip
    missing = [f for f in frames if f.calib is None]
    if missing:
        raise UsageError(
            f"no calibration for {missing[0].cloud}: give --calib (a file, a KITTI raw date "
            "folder or per-frame files), or point CLOUD at a KITTI raw drive / date folder or a "
            "KITTI object root, whose calibration is found in the tree"
        )
    inputs = (*sources, *(Path(p) for p in (calib, image) if p is not None))
    return CloudSource(frames, cam, inputs)
