"""Per-frame files of a folder, keyed by :class:`FrameKey`, and matching between folders.

A folder tree maps to keys by its structure: ``DIR/<frame>.ext`` is ``("", frame)`` and
``DIR/<a>/<b>/<frame>.ext`` is ``("a/b", frame)``, the layout every batch command writes. A
folder written by sparsetools is read through its record (``.sparsetools/``), so its side
files (confidence maps, masks, calibrations) are never taken for frames. Two files that
would be one frame (``x.png`` and ``x.jpg``) are an error naming both.
"""

from __future__ import annotations

import itertools
import logging
import os
import re
from collections import Counter, defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ...errors import FormatError, ParameterError
from ..atomic import TMP_PREFIX
from ..provenance import RECORD_DIR, recorded_outputs
from .frame import FrameKey, check_key_part

__all__ = [
    "CALIB_SUFFIXES",
    "CLOUD_SUFFIXES",
    "DEPTH_SUFFIXES",
    "IMAGE_SUFFIXES",
    "FileIndex",
    "file_stem",
    "index_tree",
    "match_keys",
    "walk_once",
]

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".png", ".npy")
CLOUD_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")
CALIB_SUFFIXES = (".txt", ".json")
#: Companion files named after a frame: ``<frame>_conf`` (jbf-expand confidence) and
#: ``<frame>_sweep<k>`` (single radar sweeps beside their merged frame).
_COMPANION = re.compile(r"^(?P<frame>.+)_(conf|sweep\d+)$")
#: What a file name may hold that a frame name may not (a file's name has no ``/``, and names
#: starting with ``.`` are skipped before).
_BAD_NAME = re.compile(r"[\x00-\x1f\\]")


def file_stem(path: str | os.PathLike) -> str:
    """Frame name of a file: ``a/000001.png`` -> ``000001``, ``x.pcd.bin`` -> ``x``."""
    name = Path(path).name
    if name.lower().endswith(".pcd.bin"):
        return name[: -len(".pcd.bin")]
    return name[: -len(Path(name).suffix)] if Path(name).suffix else name


class FileMap(Mapping[FrameKey, Path]):
    """Frame key -> file, in key order, about 100 bytes per frame (issue 28).

    What an index of a million files holds as ``dict[FrameKey, Path]`` takes about 600 bytes
    per file; here each file is its folder (shared by the folder's files), its sequence
    (shared) and its name: keys and paths are made when asked for. Lookups by key bisect the
    sorted keys.

    Parameters
    ----------
    entries : iterable of (sequence, frame, folder, name)
        Frame parts already checked; no two with one (sequence, frame).
    """

    __slots__ = ("_folders", "_frames", "_names", "_sequences")

    def __init__(self, entries: Iterable[tuple[str, str, str, str]]):
        rows = sorted(entries)
        self._sequences = [r[0] for r in rows]
        self._frames = [r[1] for r in rows]
        self._folders = [r[2] for r in rows]
        self._names = [r[3] for r in rows]

    def __len__(self) -> int:
        return len(self._frames)

    def item_at(self, i: int) -> tuple[FrameKey, Path]:
        """The ``i``-th (key, file) in key order."""
        return (FrameKey.checked(self._sequences[i], self._frames[i]),
                Path(self._folders[i], self._names[i]))  # fmt: skip

    def _find(self, key) -> int:
        if not isinstance(key, FrameKey):
            return -1
        target = (key.sequence, key.frame)
        lo, hi = 0, len(self._frames)
        while lo < hi:
            mid = (lo + hi) // 2
            if (self._sequences[mid], self._frames[mid]) < target:
                lo = mid + 1
            else:
                hi = mid
        if lo < len(self._frames) and (self._sequences[lo], self._frames[lo]) == target:
            return lo
        return -1

    def __getitem__(self, key: FrameKey) -> Path:
        i = self._find(key)
        if i < 0:
            raise KeyError(key)
        return Path(self._folders[i], self._names[i])

    def __contains__(self, key) -> bool:
        return self._find(key) >= 0

    def __iter__(self):
        for seq, frame in zip(self._sequences, self._frames, strict=True):
            yield FrameKey.checked(seq, frame)

    def items(self):
        return (self.item_at(i) for i in range(len(self)))


@dataclass(frozen=True)
class FileIndex:
    """Files of one input, by frame key.

    Attributes
    ----------
    root : Path
        What the user gave.
    files : dict of FrameKey -> Path
        In key order.
    layout : str
        How the keys were derived: ``file``, ``tree``, ``sparsetools``, ``kitti-raw``,
        ``kitti-object``, ``kitti-depth-completion``, ``kitti-val-selection``.
    splits : dict of FrameKey -> str
        Splits the layout assigns (KITTI depth completion), else empty.
    calib : dict of FrameKey -> Path
        Calibration the layout provides per frame (KITTI raw date folder, KITTI object).
    images : dict of FrameKey -> Path
        Camera image the layout provides per frame (KITTI raw, KITTI object).
    poses : dict of FrameKey -> tuple of 16 floats
        Row-major 4x4 ``T_world_from_cam`` the layout provides (synthetic videos).
    times : dict of FrameKey -> float
        Seconds, where the layout provides them.
    """

    root: Path
    files: dict[FrameKey, Path]
    layout: str = "tree"
    splits: dict[FrameKey, str] = field(default_factory=dict)
    calib: dict[FrameKey, Path] = field(default_factory=dict)
    images: dict[FrameKey, Path] = field(default_factory=dict)
    poses: dict[FrameKey, tuple] = field(default_factory=dict)
    times: dict[FrameKey, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.files)

    @property
    def is_single_file(self) -> bool:
        return self.layout == "file"


def _suffix_ok(name: str, suffixes: tuple[str, ...]) -> bool:
    low = name.lower()
    return any(low.endswith(s) for s in suffixes)


def _add(files: dict[FrameKey, Path], key: FrameKey, path: Path, option: str) -> None:
    if key in files:
        raise FormatError(
            f"{option}: {files[key]} and {path} are the same frame '{key}': "
            "keep one of them or give the folders separately"
        )
    files[key] = path


def _drop_companions(files: dict[FrameKey, Path]) -> dict[FrameKey, Path]:
    present = set(files)
    out = {}
    for key, path in files.items():
        m = _COMPANION.match(key.frame)
        if m and FrameKey(key.sequence, m["frame"]) in present:
            continue
        out[key] = path
    return out


def walk_once(root: str | os.PathLike):
    """``os.walk`` that follows folder links but walks every real folder once.

    Dataset trees are often assembled with links (a drive linked into a date folder), so
    links are followed; a link back up the tree (``ln -s . x``) or a second link to a folder
    already walked would repeat its frames (and two such loops walk 2^depth paths): such a
    folder is left out, with a warning naming it. The walk is in the order ``os.walk`` gives;
    callers sort what they keep.
    """
    seen: set[tuple[int, int]] = set()
    try:
        st = os.stat(root)
        seen.add((st.st_dev, st.st_ino))
    except OSError:
        return
    for dirpath, dirnames, filenames in os.walk(root, followlinks=True):
        keep = []
        for d in sorted(dirnames):  # which of two links to one folder is kept: the first by name
            full = os.path.join(dirpath, d)
            try:
                st = os.stat(full)
            except OSError:
                continue  # a dangling link
            ident = (st.st_dev, st.st_ino)
            if ident in seen:
                if not d.startswith(".") and d != RECORD_DIR:
                    log.warning("%s: a link to a folder already read (a loop or a second link): "
                                "left out", full)  # fmt: skip
                continue
            seen.add(ident)
            keep.append(d)
        dirnames[:] = keep
        yield dirpath, dirnames, filenames


def index_tree(
    path: str | os.PathLike,
    suffixes: tuple[str, ...],
    *,
    option: str,
    role: str | None = None,
) -> FileIndex:
    """Files with ``suffixes`` under ``path`` (a file, or a folder searched recursively).

    Parameters
    ----------
    path : path-like
    suffixes : tuple of str
        Lower-case suffixes with the dot (``.pcd.bin`` is matched by ``.bin``).
    option : str
        The option or argument the path came from, for messages (``--rgb``).
    role : str, optional
        In a folder written by sparsetools, the recorded outputs of this role (``depth``,
        ``image``, ``cloud``); default: the folder's only role.

    Raises
    ------
    FormatError
        The path does not exist, holds no such file, or two files are one frame.
    """
    root = Path(path)
    if root.exists() and not root.is_file() and not root.is_dir():
        raise FormatError(f"{option}: {root}: not a regular file (a device or a pipe?)")
    if root.is_file():
        if not _suffix_ok(root.name, suffixes):
            raise FormatError(f"{option}: {root} is not a {'/'.join(suffixes)} file")
        return FileIndex(root, {FrameKey("", file_stem(root)): root}, layout="file")
    if not root.is_dir():
        raise FormatError(f"{option}: {root}: no such file or folder")
    recorded = recorded_outputs(root, role)
    if recorded:
        entries, folders = [], {}
        while recorded:
            k, p = recorded.popitem()
            if _suffix_ok(p.name, suffixes) and p.is_file():
                key = FrameKey.parse(k)
                folder = str(p.parent)
                entries.append(
                    (key.sequence, key.frame, folders.setdefault(folder, folder), p.name)
                )
        if entries:
            return FileIndex(root, FileMap(entries), layout="sparsetools")
    rows: list[tuple[str, str, str, str]] = []
    for dirpath, dirnames, filenames in walk_once(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and d != RECORD_DIR)
        rel = os.path.relpath(dirpath, root).replace(os.sep, "/")
        sequence = "" if rel == "." else rel
        try:
            check_key_part(sequence, "sequence name")
        except ParameterError as exc:
            raise FormatError(f"{option}: {dirpath}: {exc}") from exc
        for name in filenames:
            if name.startswith(".") or name.startswith(TMP_PREFIX):
                continue
            if not _suffix_ok(name, suffixes) or not os.path.isfile(os.path.join(dirpath, name)):
                continue  # a dangling link or a special file is not a frame
            frame = file_stem(name)
            if not frame or _BAD_NAME.search(frame):
                try:
                    FrameKey(sequence, frame)
                except ParameterError as exc:
                    raise FormatError(f"{option}: {Path(dirpath) / name}: {exc}") from exc
            rows.append((sequence, frame, dirpath, name))
    rows = _drop_companion_rows(_unique_rows(rows, option))
    if not rows:
        raise FormatError(f"{option}: no {'/'.join('*' + s for s in suffixes)} files in {root}")
    return FileIndex(root, FileMap(rows), layout="tree")


def _unique_rows(rows: list, option: str) -> list:
    """``rows`` sorted by key; two files of one frame (``x.png`` and ``x.jpg``) refused."""
    rows.sort()
    for a, b in itertools.pairwise(rows):
        if a[:2] == b[:2]:
            key = FrameKey.checked(a[0], a[1])
            raise FormatError(
                f"{option}: {Path(a[2], a[3])} and {Path(b[2], b[3])} are the same frame "
                f"'{key}': keep one of them or give the folders separately"
            )
    return rows


def _drop_companion_rows(rows: list) -> list:
    """Companion files (``<frame>_conf``, ``<frame>_sweep<k>``) of a frame that is present are
    not frames."""
    keys = None
    out = []
    for r in rows:
        m = _COMPANION.match(r[1])
        if m:
            if keys is None:
                keys = {(row[0], row[1]) for row in rows}
            if (r[0], m["frame"]) in keys:
                continue
        out.append(r)
    return out


def match_keys(keys: Iterable[FrameKey], index: Mapping[FrameKey, Path]) -> dict[FrameKey, Path]:
    """The file of each key in ``index``: the same key, else the same frame name when that
    name is unique among ``keys`` and in ``index`` (a flat folder beside a sequence tree)."""
    keys = list(keys)
    names = Counter(k.frame for k in keys)
    by_name: dict[str, list[FrameKey]] = defaultdict(list)
    for k in index:
        by_name[k.frame].append(k)
    out = {}
    for k in keys:
        if k in index:
            out[k] = index[k]
            continue
        cands = by_name.get(k.frame, [])
        if len(cands) == 1 and names[k.frame] == 1:
            out[k] = index[cands[0]]
    return out
