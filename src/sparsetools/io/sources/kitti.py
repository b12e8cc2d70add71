"""KITTI layouts: raw drives (one drive, a date folder, a root of dates), object, depth completion.

- **KITTI raw**: ``<date>/<date>_drive_XXXX_sync/{velodyne_points,image_0N}/data/<frame>.*``
  with the calibration pair (``calib_cam_to_cam.txt``, ``calib_velo_to_cam.txt``) in
  ``<date>/`` (or in the drive folder itself). Sequence = the drive folder's name, frame = the
  10-digit file stem, so frame names repeat across drives without colliding.
- **KITTI object**: ``ROOT/training/{velodyne,calib,image_2}/<stem>.*`` (or the same folders
  directly under ROOT). Sequence ``""``.
- **KITTI depth completion**: ``[data_depth_velodyne|data_depth_annotated/]{train,val}/<drive>/
  proj_depth/<name>/image_0N/<frame>.png`` with ``<name>`` ``velodyne_raw`` (sparse input),
  ``groundtruth`` (annotated maps) or any map set laid out the same way; the split comes from
  the tree. Sequence = drive, so the maps match the raw images of the same drive.
- **KITTI val_selection_cropped**: ``{image,velodyne_raw,groundtruth_depth,intrinsics}/
  <drive>_<kind>_<frame>_image_0N.<ext>``; sequence = drive, split ``val_selection``. A flat
  folder of depth maps named that way (a depth-completion submission, ``predict --layout
  kitti-dc``) is keyed the same way (:func:`kitti_selection_maps_index`).

Nothing here reads a cloud or an image: only paths are found (timestamps excepted).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ...errors import FormatError
from .frame import FrameKey
from .tree import IMAGE_SUFFIXES, FileIndex, file_stem

__all__ = [
    "DC_NAMES",
    "drive_splits",
    "is_kitti_depth_completion",
    "is_kitti_object",
    "is_kitti_raw",
    "is_kitti_raw_calib_dir",
    "is_kitti_raw_drive",
    "is_kitti_selection_maps",
    "is_kitti_val_selection",
    "kitti_depth_completion_index",
    "kitti_object_index",
    "kitti_raw_drives",
    "kitti_raw_index",
    "kitti_raw_partner_image",
    "kitti_selection_maps_index",
    "kitti_val_selection_index",
    "read_kitti_timestamps",
]

#: ``proj_depth`` map set a role takes by default in a depth-completion tree.
DC_NAMES = {"sparse": "velodyne_raw", "gt": "groundtruth"}
_SPLITS = ("train", "val")
_SELECTION = re.compile(
    r"^(?P<drive>.+_sync)_(?P<kind>image|velodyne_raw|groundtruth_depth)_"
    r"(?P<frame>\d+)_image_0(?P<camera>\d)$"
)
_SELECTION_DIRS = {
    "image": "image",
    "sparse": "velodyne_raw",
    "gt": "groundtruth_depth",
    "calib": "intrinsics",
}


# -- KITTI raw ---------------------------------------------------------------------------------


def is_kitti_raw_calib_dir(path: Path) -> bool:
    """Whether ``path`` is a folder holding the KITTI raw calibration pair."""
    return path.is_dir() and (path / "calib_cam_to_cam.txt").is_file()


def is_kitti_raw_drive(path: Path) -> bool:
    """A drive folder: ``velodyne_points/data`` or ``image_0N/data`` inside."""
    if not path.is_dir():
        return False
    if (path / "velodyne_points" / "data").is_dir():
        return True
    return any((path / f"image_0{i}" / "data").is_dir() for i in range(4))


def _drives_in(date_dir: Path) -> list[Path]:
    return sorted(
        d for d in date_dir.iterdir() if not d.name.startswith(".") and is_kitti_raw_drive(d)
    )


def kitti_raw_drives(path: str | os.PathLike) -> list[tuple[Path, Path | None]]:
    """``(drive folder, calibration folder)`` of a drive, a date folder or a root of dates.

    Returns an empty list when ``path`` is not a KITTI raw tree. The calibration folder is
    the drive's date folder (or the drive folder itself) when it holds the pair, else None.
    """
    p = Path(path)
    if not p.is_dir():
        return []
    if is_kitti_raw_drive(p):
        for cand in (p.parent, p):
            if is_kitti_raw_calib_dir(cand):
                return [(p, cand)]
        return [(p, None)]
    if is_kitti_raw_calib_dir(p):
        return [(d, p) for d in _drives_in(p)]
    out = []
    for date in sorted(c for c in p.iterdir() if c.is_dir() and not c.name.startswith(".")):
        if is_kitti_raw_calib_dir(date):
            out.extend((d, date) for d in _drives_in(date))
    return out


def is_kitti_raw(path: str | os.PathLike) -> bool:
    return bool(kitti_raw_drives(path))


def read_kitti_timestamps(path: Path) -> list[float] | None:
    """Seconds since midnight of each line of a KITTI raw ``timestamps.txt`` (None if absent)."""
    try:
        lines = path.read_text(encoding="utf-8").split("\n")
    except (OSError, UnicodeDecodeError):
        return None
    out = []
    for line in lines:
        line = line.strip()
        if not line:
            continue
        try:
            clock = line.split(" ")[1]
            h, m, s = clock.split(":")
            out.append(int(h) * 3600 + int(m) * 60 + float(s))
        except (IndexError, ValueError):
            return None
    return out


def kitti_raw_partner_image(image: str | os.PathLike, *, camera: int = 3) -> Path | None:
    """The same frame's image of another camera of a KITTI raw drive, or None when absent:
    ``<drive>/image_02/data/<frame>.png`` -> ``<drive>/image_0{camera}/data/<frame>.png``."""
    p = Path(image)
    if p.parent.name != "data" or not re.fullmatch(r"image_0\d", p.parent.parent.name):
        return None
    cand = p.parents[2] / f"image_{camera:02d}" / "data" / p.name
    return cand if cand.is_file() else None


def kitti_raw_index(
    path: str | os.PathLike, *, what: str = "cloud", camera: int = 2, option: str = "CLOUD"
) -> FileIndex:
    """Scans (``what="cloud"``) or camera images (``"image"``) of KITTI raw drives.

    Every frame gets its drive's calibration folder and (for scans) its camera image.

    Raises
    ------
    FormatError
        Not a KITTI raw tree, a drive without calibration, or no files.
    """
    drives = kitti_raw_drives(path)
    if not drives:
        raise FormatError(
            f"{option}: {path} is not a KITTI raw drive, date folder or root (no "
            "<drive>/velodyne_points/data/ or image_0N/data/)"
        )
    files: dict[FrameKey, Path] = {}
    calib: dict[FrameKey, Path] = {}
    images: dict[FrameKey, Path] = {}
    sub = "velodyne_points" if what == "cloud" else f"image_{camera:02d}"
    suffixes = (".bin",) if what == "cloud" else IMAGE_SUFFIXES
    for drive, calib_dir in drives:
        data = drive / sub / "data"
        if not data.is_dir():
            continue
        if calib_dir is None:
            raise FormatError(
                f"{drive}: no calib_cam_to_cam.txt / calib_velo_to_cam.txt in {drive.parent} "
                "(the KITTI raw date folder) nor in the drive folder"
            )
        image_dir = drive / f"image_{camera:02d}" / "data"
        for f in sorted(data.iterdir()):
            if not f.is_file() or f.name.startswith(".") or f.suffix.lower() not in suffixes:
                continue
            key = FrameKey(drive.name, file_stem(f))
            files[key] = f
            calib[key] = calib_dir
            if what == "cloud":
                for s in IMAGE_SUFFIXES:
                    if (image_dir / f"{key.frame}{s}").is_file():
                        images[key] = image_dir / f"{key.frame}{s}"
                        break
    if not files:
        raise FormatError(f"{option}: {path}: no {sub}/data/*{suffixes[0]} files in its drives")
    return FileIndex(Path(path), files, layout="kitti-raw", calib=calib, images=images)


# -- KITTI object ------------------------------------------------------------------------------


def _object_base(root: Path) -> Path | None:
    if (root / "training" / "velodyne").is_dir():
        return root / "training"
    if (root / "velodyne").is_dir() and (root / "calib").is_dir():
        return root
    return None


def is_kitti_object(path: str | os.PathLike) -> bool:
    return Path(path).is_dir() and _object_base(Path(path)) is not None


def kitti_object_index(path: str | os.PathLike, *, camera: int = 2) -> FileIndex:
    """Scans of a KITTI object split with their per-frame calibration and image.

    Image sizes vary (1224x370, 1242x375), so each frame takes its own image's size.
    """
    root = Path(path)
    base = _object_base(root)
    if base is None:
        raise FormatError(f"{root}: not a KITTI object folder (no velodyne/ or training/velodyne/)")
    calib_dir, image_dir = base / "calib", base / f"image_{camera}"
    for needed in (calib_dir, image_dir):
        if not needed.is_dir():
            raise FormatError(f"{root}: KITTI object folder has no {needed.name}/")
    files, calib, images = {}, {}, {}
    for f in sorted((base / "velodyne").iterdir()):
        if not f.is_file() or f.suffix.lower() != ".bin" or f.name.startswith("."):
            continue
        key = FrameKey("", file_stem(f))
        files[key] = f
        calib[key] = calib_dir / f"{key.frame}.txt"
        images[key] = next(
            (
                image_dir / f"{key.frame}{s}"
                for s in IMAGE_SUFFIXES
                if (image_dir / f"{key.frame}{s}").is_file()
            ),
            image_dir / f"{key.frame}.png",
        )
    if not files:
        raise FormatError(f"{base / 'velodyne'}: no .bin scans")
    return FileIndex(root, files, layout="kitti-object", calib=calib, images=images)


# -- KITTI depth completion --------------------------------------------------------------------


def proj_depth_drives(root: Path) -> list[tuple[Path, str | None]]:
    """(drive folder, split) of every ``<drive>/proj_depth`` within three levels of ``root``."""
    out = []
    for pattern in ("proj_depth", "*/proj_depth", "*/*/proj_depth", "*/*/*/proj_depth"):
        for pd in sorted(root.glob(pattern)):
            if not pd.is_dir():
                continue
            drive = pd.parent
            split = drive.parent.name if drive.parent.name in _SPLITS else None
            out.append((drive, split))
        if out:
            break
    return out


def is_kitti_depth_completion(path: str | os.PathLike) -> bool:
    p = Path(path)
    return p.is_dir() and bool(proj_depth_drives(p))


def kitti_depth_completion_index(
    path: str | os.PathLike,
    *,
    role: str,
    name: str | None = None,
    camera: int = 2,
    option: str = "--sparse",
) -> FileIndex:
    """Depth maps of a KITTI depth-completion tree: ``proj_depth/<name>/image_0N/*.png``.

    Parameters
    ----------
    role : {"sparse", "gt", ...}
        Picks the default map set (``velodyne_raw`` / ``groundtruth``) when the tree holds
        several and ``name`` is not given.
    name : str, optional
        The ``proj_depth`` map set (e.g. ``velodyne_raw_4beam``).
    """
    root = Path(path)
    drives = proj_depth_drives(root)
    if not drives:
        raise FormatError(
            f"{option}: {root} is not a KITTI depth-completion tree (no <drive>/proj_depth/)"
        )
    names = sorted({p.name for d, _ in drives for p in (d / "proj_depth").iterdir() if p.is_dir()})
    if name is None:
        name = names[0] if len(names) == 1 else DC_NAMES.get(role)
        if name not in names:
            raise FormatError(
                f"{option}: {root} holds the map sets {', '.join(names)}: say which one "
                "(e.g. give the path down to proj_depth/<name>'s drive tree or the name option)"
            )
    elif name not in names:
        raise FormatError(f"{option}: {root} has no proj_depth/{name} (it has {', '.join(names)})")
    files, splits = {}, {}
    for drive, split in drives:
        folder = drive / "proj_depth" / name / f"image_{camera:02d}"
        if not folder.is_dir():
            continue
        for f in sorted(folder.iterdir()):
            if f.is_file() and f.suffix.lower() == ".png" and not f.name.startswith("."):
                key = FrameKey(drive.name, file_stem(f))
                if key in files:
                    raise FormatError(
                        f"{option}: {files[key]} and {f} are the same frame '{key}' "
                        "(the drive is in two splits?)"
                    )
                files[key] = f
                if split is not None:
                    splits[key] = split
    if not files:
        raise FormatError(f"{option}: {root}: no proj_depth/{name}/image_{camera:02d}/*.png maps")
    return FileIndex(
        root, dict(sorted(files.items())), layout="kitti-depth-completion", splits=splits
    )


def is_kitti_val_selection(path: str | os.PathLike) -> bool:
    p = Path(path)
    return (
        p.is_dir()
        and (p / "image").is_dir()
        and ((p / "velodyne_raw").is_dir() or (p / "groundtruth_depth").is_dir())
    )


def kitti_val_selection_index(
    path: str | os.PathLike, *, role: str, camera: int = 2, option: str = "--rgb"
) -> FileIndex:
    """Files of one role of a ``val_selection_cropped`` folder (``image``, ``sparse``, ``gt``,
    ``calib`` = ``intrinsics/*.txt``), keyed (drive, frame), split ``val_selection``."""
    root = Path(path)
    sub = _SELECTION_DIRS.get(role)
    if sub is None or not (root / sub).is_dir():
        raise FormatError(f"{option}: {root} has no {sub or role}/ folder")
    files = {}
    for f in sorted((root / sub).iterdir()):
        if not f.is_file() or f.name.startswith("."):
            continue
        m = _SELECTION.match(file_stem(f))
        if m is None or int(m["camera"]) != camera:
            continue
        key = FrameKey(m["drive"], m["frame"])
        files[key] = f
    if not files:
        raise FormatError(f"{option}: {root / sub}: no files named <drive>_{sub}_<frame>_image_0N")
    return FileIndex(
        root, files, layout="kitti-val-selection", splits=dict.fromkeys(files, "val_selection")
    )


def _selection_maps(path: Path) -> list[Path] | None:
    """The PNGs of a flat folder when every one is named ``<drive>_<kind>_<frame>_image_0N``
    (and there is no subfolder but hidden ones); None otherwise."""
    if not path.is_dir():
        return None
    pngs = []
    for f in path.iterdir():
        if f.name.startswith("."):
            continue
        if not f.is_file() or f.suffix.lower() != ".png" or not _SELECTION.match(file_stem(f)):
            return None
        pngs.append(f)
    return sorted(pngs) or None


def is_kitti_selection_maps(path: str | os.PathLike) -> bool:
    """A flat folder of depth PNGs named as ``val_selection_cropped`` names its maps (a KITTI
    depth-completion submission: ``<drive>_groundtruth_depth_<frame>_image_02.png``)."""
    return _selection_maps(Path(path)) is not None


def kitti_selection_maps_index(
    path: str | os.PathLike, *, camera: int = 2, option: str = "--pred"
) -> FileIndex:
    """The maps of a flat folder named as ``val_selection_cropped`` names them, keyed
    (drive, frame) like :func:`kitti_val_selection_index`, so that they match its ground
    truth."""
    root = Path(path)
    files = {}
    for f in _selection_maps(root) or ():
        m = _SELECTION.match(file_stem(f))
        if int(m["camera"]) != camera:
            continue
        key = FrameKey(m["drive"], m["frame"])
        if key in files:
            raise FormatError(f"{option}: {files[key]} and {f} are the same frame '{key}'")
        files[key] = f
    if not files:
        raise FormatError(f"{option}: {root}: no <drive>_<kind>_<frame>_image_0{camera}.png maps")
    return FileIndex(root, dict(sorted(files.items())), layout="kitti-val-selection")


def drive_splits(tree: str | os.PathLike) -> dict[str, str]:
    """``drive -> split`` of a KITTI depth-completion tree (``{train,val}/<drive>/``)."""
    out = {}
    for drive, split in proj_depth_drives(Path(tree)):
        if split is not None:
            out[drive.name] = split
    if not out:
        raise FormatError(
            f"{tree}: no {{train,val}}/<drive>/proj_depth/ folders to take splits from"
        )
    return out
