"""Frame discovery: which point clouds make a batch, and the calibration and image of each.

Layouts understood:

- plain files and folders of clouds, with a calibration that is one file (shared), a KITTI
  raw date folder (shared) or a folder of per-frame files matched by stem
  (``<stem>.txt`` / ``<stem>.json``), and optionally an image (file or folder matched by stem)
  that gives the image size;
- KITTI raw drives: ``<date>/<date>_drive_XXXX_sync/velodyne_points/data/*.bin`` with the
  calibration pair in ``<date>/``;
- KITTI object: ``ROOT/training/{velodyne,calib,image_2}/<stem>.*`` (or the same folders
  directly under ROOT).

Nothing here reads a cloud or a calibration: it only finds files, so a bad frame fails in its
own job (and ``--on-error skip`` can skip it).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import FormatError, ParameterError
from .image import check_pixel_count, image_header_size

__all__ = [
    "CALIB_SUFFIXES",
    "CLOUD_FILE_SUFFIXES",
    "IMAGE_SUFFIXES",
    "SourceFrame",
    "cloud_stem",
    "discover_clouds",
    "find_by_stem",
    "frames_from_paths",
    "image_size_of",
    "is_kitti_raw_calib_dir",
    "kitti_object_frames",
    "kitti_raw_frames",
]

#: Suffixes taken as point clouds when a folder is given (``.pcd.bin`` ends in ``.bin``).
CLOUD_FILE_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")
#: Per-frame calibration files matched by stem, in order of preference.
CALIB_SUFFIXES = (".txt", ".json")
#: Images matched by stem, in order of preference.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class SourceFrame:
    """One frame of a batch before anything is read.

    Attributes
    ----------
    frame_id : str
        Output stem (the cloud's stem).
    cloud : Path
        Point-cloud file.
    calib : Path or None
        Calibration file or KITTI raw calib folder for this frame (None: the caller gives one).
        For a per-frame calib folder without a match this is the expected path, so the frame
        fails with "no such calibration file" in its own job.
    image : Path or None
        Image whose size the depth map takes (None: size from the calibration or the caller).
    """

    frame_id: str
    cloud: Path
    calib: Path | None = None
    image: Path | None = None


def cloud_stem(path: str | os.PathLike) -> str:
    """Frame stem of a cloud file: ``a/000001.bin`` -> ``000001``, ``x.pcd.bin`` -> ``x``."""
    name = Path(path).name
    if name.lower().endswith(".pcd.bin"):
        return name[: -len(".pcd.bin")]
    return Path(name).stem


def _is_cloud(path: Path) -> bool:
    return (
        path.is_file()
        and not path.name.startswith(".")
        and (path.suffix.lower() in CLOUD_FILE_SUFFIXES)
    )


def discover_clouds(paths: list[str | os.PathLike]) -> list[Path]:
    """Expand files and folders into a sorted list of cloud files (folders: not recursive).

    Raises
    ------
    FormatError
        A path does not exist, or nothing that looks like a point cloud was found.
    """
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(c for c in p.iterdir() if _is_cloud(c))
            if not found:
                raise FormatError(
                    f"{p}: no point clouds in this folder (looked for "
                    f"{', '.join('*' + s for s in CLOUD_FILE_SUFFIXES)})"
                )
            out.extend(found)
        elif p.is_file():
            out.append(p)
        else:
            raise FormatError(f"{p}: no such file or folder")
    if not out:
        raise ParameterError("no point clouds given")
    return out


def find_by_stem(folder: Path, stem: str, suffixes: tuple[str, ...]) -> Path | None:
    """``folder/<stem><suffix>`` for the first suffix that exists, else None."""
    for suffix in suffixes:
        candidate = folder / f"{stem}{suffix}"
        if candidate.is_file():
            return candidate
    return None


def is_kitti_raw_calib_dir(path: Path) -> bool:
    """Whether ``path`` is a KITTI raw date folder holding the calibration pair."""
    return path.is_dir() and (path / "calib_cam_to_cam.txt").is_file()


def image_size_of(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of a PNG or JPEG from its header, without decoding the pixels.

    Raises
    ------
    FormatError
        Missing file, or a header that is neither PNG nor JPEG.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
            size = image_header_size(head)
            if size is None and head[:2] == b"\xff\xd8":
                # A JPEG's frame header can follow a large EXIF block.
                size = image_header_size(head + fh.read())
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such image") from exc
    except IsADirectoryError as exc:
        raise FormatError(f"{path}: is a folder, expected an image") from exc
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if size is None or size[0] <= 0 or size[1] <= 0:
        raise FormatError(f"{path}: not a PNG or JPEG image (cannot read its size)")
    check_pixel_count(*size, f"{path}: declared size")
    return size


def frames_from_paths(
    clouds: list[str | os.PathLike],
    *,
    calib: str | os.PathLike | None = None,
    image: str | os.PathLike | None = None,
) -> list[SourceFrame]:
    """Frames for clouds given as files/folders, matching calibration and image by stem.

    Parameters
    ----------
    clouds : list of path-like
        Cloud files and/or folders of clouds.
    calib : path-like, optional
        A calibration file (shared by every frame), a KITTI raw date folder (shared), or a
        folder of per-frame ``<stem>.txt`` / ``<stem>.json`` files.
    image : path-like, optional
        An image (its size is shared) or a folder of per-frame ``<stem>.png``/``.jpg`` images.
    """
    files = discover_clouds(clouds)
    calib_path = Path(calib) if calib is not None else None
    image_path = Path(image) if image is not None else None
    per_frame_calib = (
        calib_path is not None and calib_path.is_dir() and not (is_kitti_raw_calib_dir(calib_path))
    )
    if per_frame_calib and not any(
        c.suffix.lower() in CALIB_SUFFIXES for c in calib_path.iterdir() if c.is_file()
    ):
        raise FormatError(
            f"{calib_path}: folder holds neither per-frame calib files (<stem>.txt / <stem>.json) "
            "nor a KITTI raw calibration pair (calib_cam_to_cam.txt + calib_velo_to_cam.txt)"
        )
    frames = []
    for f in files:
        stem = cloud_stem(f)
        c = calib_path
        if per_frame_calib:
            c = find_by_stem(calib_path, stem, CALIB_SUFFIXES) or calib_path / f"{stem}.txt"
        im = image_path
        if image_path is not None and image_path.is_dir():
            im = find_by_stem(image_path, stem, IMAGE_SUFFIXES) or image_path / f"{stem}.png"
        frames.append(SourceFrame(stem, f, c, im))
    return frames


def kitti_raw_frames(drive_dir: str | os.PathLike) -> list[SourceFrame]:
    """Frames of a KITTI raw drive: ``velodyne_points/data/*.bin`` + the date folder's calib.

    ``drive_dir`` is ``<date>/<date>_drive_XXXX_sync``; the calibration pair is looked for in
    ``<date>/`` (then in the drive folder). The image size comes from ``S_rect_0N``.
    """
    drive = Path(drive_dir)
    data = drive / "velodyne_points" / "data"
    if not data.is_dir():
        raise FormatError(
            f"{drive}: not a KITTI raw drive folder (no velodyne_points/data/; give "
            "<date>/<date>_drive_XXXX_sync)"
        )
    for candidate in (drive.parent, drive):
        if is_kitti_raw_calib_dir(candidate):
            calib_dir = candidate
            break
    else:
        raise FormatError(
            f"{drive}: no calib_cam_to_cam.txt / calib_velo_to_cam.txt in {drive.parent} "
            "(the KITTI raw date folder) nor in the drive folder"
        )
    files = sorted(f for f in data.iterdir() if f.is_file() and f.suffix.lower() == ".bin")
    if not files:
        raise FormatError(f"{data}: no .bin scans")
    return [SourceFrame(cloud_stem(f), f, calib_dir, None) for f in files]


def kitti_object_frames(root: str | os.PathLike, *, camera: int = 2) -> list[SourceFrame]:
    """Frames of a KITTI object split: ``velodyne/``, ``calib/`` and ``image_{camera}/``.

    ``root`` may be the dataset root holding ``training/`` or the split folder itself.
    Image sizes vary (e.g. 1224x370 and 1242x375), so each frame takes its image's size.
    """
    root = Path(root)
    base = root / "training" if (root / "training" / "velodyne").is_dir() else root
    velo = base / "velodyne"
    if not velo.is_dir():
        raise FormatError(f"{root}: not a KITTI object folder (no velodyne/ or training/velodyne/)")
    calib_dir = base / "calib"
    image_dir = base / f"image_{camera}"
    for needed in (calib_dir, image_dir):
        if not needed.is_dir():
            raise FormatError(f"{root}: KITTI object folder has no {needed.name}/")
    files = sorted(f for f in velo.iterdir() if f.is_file() and f.suffix.lower() == ".bin")
    if not files:
        raise FormatError(f"{velo}: no .bin scans")
    frames = []
    for f in files:
        stem = cloud_stem(f)
        frames.append(
            SourceFrame(
                stem,
                f,
                calib_dir / f"{stem}.txt",
                find_by_stem(image_dir, stem, IMAGE_SUFFIXES) or image_dir / f"{stem}.png",
            )
        )
    return frames
