"""The official split lists shipped with sparsetools (``--split NAME``): KITTI's Eigen,
Eigen-Zhou, Eigen benchmark and odometry splits, nuScenes' official and mini scene splits.

The lists are the package's data (``sparsetools/data/splits/``, copied verbatim from
monodepth2 and the nuScenes devkit and stored xz-compressed, ``<list>.txt.xz``: 4.4 MB of
text in 0.4 MB; sources and licences in its ``README.txt``), read with
:mod:`importlib.resources`. A name maps each split of the dataset (train / val / test) to one
list; :func:`official_split_lists` reads them as :class:`~.splits.SplitList` records, which
:func:`~.splits.split_file_assignments` matches to the frames as it does ``--split-file``.

KITTI lines are ``<date>/<drive>_sync <frame> <l|r>`` (``l``: ``image_02``, ``r``:
``image_03``); a line of the camera the dataset is not made of matches nothing (counted as
``other_camera``). The odometry split's lines name odometry sequences (``8 4056 r``): they are
read as the KITTI raw drive and frame the sequence was cut from (:data:`ODOMETRY_DRIVES`).
nuScenes lists hold one scene name per line: every sample of that scene.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from ...errors import ParameterError
from .splits import SplitList, parse_split_lines

__all__ = [
    "ODOMETRY_DRIVES",
    "OFFICIAL_SPLITS",
    "OfficialSplit",
    "check_scene_list",
    "official_split",
    "official_split_lists",
    "official_split_names",
    "shipped_split_file",
    "shipped_split_lines",
]

KITTI, NUSCENES = "kitti", "nuscenes"


@dataclass(frozen=True)
class OfficialSplit:
    """A named split: the shipped list of each of its splits.

    Attributes
    ----------
    name : str
        As ``--split`` takes it (``eigen``).
    dataset : {"kitti", "nuscenes"}
    lists : tuple of (str, str)
        (split, list file under ``data/splits/<dataset>/``), in train, val, test order.
    about : str
        One line: what it is.
    """

    name: str
    dataset: str
    lists: tuple[tuple[str, str], ...]
    about: str


_ZHOU = (("train", "eigen_zhou_train_files.txt"), ("val", "eigen_zhou_val_files.txt"))

#: Every named split, by name (the names of KITTI and nuScenes do not collide).
OFFICIAL_SPLITS: dict[str, OfficialSplit] = {
    s.name: s
    for s in (
        OfficialSplit("eigen", KITTI, (*_ZHOU, ("test", "eigen_test_files.txt")),
                      "Eigen-Zhou train / val (39,810 / 4,424 lines) and the Eigen test split "
                      "(697)"),
        OfficialSplit("eigen_full", KITTI,
                      (("train", "eigen_full_train_files.txt"),
                       ("val", "eigen_full_val_files.txt"), ("test", "eigen_test_files.txt")),
                      "Eigen's train / val with static frames (45,200 / 1,776) and Eigen test "
                      "(697)"),
        OfficialSplit("eigen_benchmark", KITTI,
                      (*_ZHOU, ("test", "eigen_benchmark_test_files.txt")),
                      "Eigen-Zhou train / val and the 652 Eigen test frames with KITTI's "
                      "annotated ground truth"),
        OfficialSplit("odom", KITTI,
                      (("train", "odom_train_files.txt"), ("val", "odom_val_files.txt")),
                      "monodepth2's odometry split (sequences 00-08, as KITTI raw drives)"),
        OfficialSplit("official", NUSCENES,
                      (("train", "train_scenes.txt"), ("val", "val_scenes.txt"),
                       ("test", "test_scenes.txt")),
                      "the nuScenes scene split (700 / 150 / 150 scenes)"),
        OfficialSplit("mini", NUSCENES,
                      (("train", "mini_train_scenes.txt"), ("val", "mini_val_scenes.txt")),
                      "the v1.0-mini scene split (8 / 2 scenes)"),
    )
}  # fmt: skip

#: KITTI odometry sequence -> (KITTI raw drive, its frame that is the sequence's frame 0), from
#: the "Mapping between KITTI raw data and odometry sequences" of the odometry development
#: kit's readme.txt. Sequence 03's drive (2011_09_26_drive_0067) is not among the published
#: raw drives, so its lines are always absent.
ODOMETRY_DRIVES: dict[int, tuple[str, int]] = {
    0: ("2011_10_03/2011_10_03_drive_0027_sync", 0),
    1: ("2011_10_03/2011_10_03_drive_0042_sync", 0),
    2: ("2011_10_03/2011_10_03_drive_0034_sync", 0),
    3: ("2011_09_26/2011_09_26_drive_0067_sync", 0),
    4: ("2011_09_30/2011_09_30_drive_0016_sync", 0),
    5: ("2011_09_30/2011_09_30_drive_0018_sync", 0),
    6: ("2011_09_30/2011_09_30_drive_0020_sync", 0),
    7: ("2011_09_30/2011_09_30_drive_0027_sync", 0),
    8: ("2011_09_30/2011_09_30_drive_0028_sync", 1100),
    9: ("2011_09_30/2011_09_30_drive_0033_sync", 0),
    10: ("2011_09_30/2011_09_30_drive_0034_sync", 0),
}


def official_split_names(dataset: str | None = None) -> tuple[str, ...]:
    """The names ``--split`` takes (of one dataset: ``kitti`` or ``nuscenes``)."""
    return tuple(n for n, s in OFFICIAL_SPLITS.items() if dataset in (None, s.dataset))


def official_split(name: str, dataset: str | None = None) -> OfficialSplit:
    """The named split; a name not shipped (for ``dataset``) is a ParameterError listing the
    names that are."""
    split = OFFICIAL_SPLITS.get(str(name))
    if split is None or dataset not in (None, split.dataset):
        raise ParameterError(
            f"unknown split {name!r}: the official splits are "
            f"{', '.join(official_split_names(dataset))}",
            param="--split",
        )
    return split


def shipped_split_file(spec: str) -> tuple[str, Path]:
    """``NAME:SPLIT`` (``eigen:test``) -> (split, the shipped list's path on disk).

    Raises
    ------
    ParameterError
        Not ``NAME:SPLIT``, an unknown name, or a split the name does not have.
    """
    name, sep, part = str(spec).partition(":")
    if not sep:
        raise ParameterError(f"expected a shipped list as NAME:SPLIT (eigen:test), got {spec!r}")
    split = official_split(name)
    files = dict(split.lists)
    if part not in files:
        raise ParameterError(
            f"the official split {name} has no {part!r} list (it has {', '.join(files)})"
        )
    ref = _shipped(split.dataset, files[part])
    path = Path(str(ref))
    if not path.is_file():  # a zipped installation: no file on disk to hand out
        raise ParameterError(f"the shipped split list {split.dataset}/{files[part]} is not a file")
    return part, path


#: How the shipped lists are stored: ``<list>.txt`` compressed.
SHIPPED_SUFFIX = ".xz"


def _shipped(dataset: str, file: str):
    """The resource of a shipped list (``file``: its name, ``eigen_test_files.txt``)."""
    return resources.files("sparsetools") / "data" / "splits" / dataset / (file + SHIPPED_SUFFIX)


def _shipped_text(dataset: str, file: str) -> str:
    import lzma

    try:
        return lzma.decompress(_shipped(dataset, file).read_bytes()).decode("utf-8")
    except (OSError, lzma.LZMAError, UnicodeDecodeError) as exc:  # a broken installation
        raise ParameterError(
            f"the shipped split list {dataset}/{file} cannot be read ({exc})"
        ) from exc


@functools.lru_cache(maxsize=16)
def shipped_split_lines(dataset: str, file: str) -> tuple[tuple[str, ...], ...]:
    """The lines of one shipped list, as written (``data/splits/<dataset>/<file>.xz``)."""
    where = f"{dataset}/{file}"
    text = _shipped_text(dataset, file)
    lines = _scene_lines(text, where) if dataset == NUSCENES else parse_split_lines(text, where)
    return tuple(lines)


def _odometry_as_raw(line: tuple[str, ...], where: str) -> tuple[str, ...]:
    """``8 4056 r`` -> ``2011_09_30/2011_09_30_drive_0028_sync 5156 r``."""
    if not line[0].isdigit() or int(line[0]) not in ODOMETRY_DRIVES:
        raise ParameterError(f"{where}: {' '.join(line)!r} names no odometry sequence 00-10")
    drive, start = ODOMETRY_DRIVES[int(line[0])]
    return (drive, str(start + int(line[1])), *line[2:])


@functools.lru_cache(maxsize=8)
def official_split_lists(name: str) -> tuple[SplitList, ...]:
    """The named split's lists, one per split, as :func:`~.splits.split_file_assignments`
    takes them (odometry lines as KITTI raw drives and frames)."""
    split = official_split(name)
    out = []
    for split_name, file in split.lists:
        lines = shipped_split_lines(split.dataset, file)
        if name == "odom":
            lines = tuple(_odometry_as_raw(line, f"{split.dataset}/{file}") for line in lines)
        out.append(SplitList(split_name, f"{split.dataset}/{file}", lines))
    return tuple(out)


def _scene_lines(text: str, where: str) -> list[tuple[str, ...]]:
    lines = parse_split_lines(text, where)
    check_scene_list(SplitList("", where, tuple(lines)))
    return lines


def check_scene_list(split_list: SplitList) -> SplitList:
    """``split_list`` if it is a nuScenes scene list (one scene name per line), else a
    ParameterError naming its first other line."""
    bad = next((p for p in split_list.lines if len(p) != 1), None)
    if bad is not None:
        raise ParameterError(
            f"{split_list.source}: expected one scene name per line, got {' '.join(bad)!r}"
        )
    return split_list
