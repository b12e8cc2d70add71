"""Dataset splits: fractions, split files (KITTI Eigen lines), sequence names, assignment.

Splits are assigned to whole sequences. With fractions (``--splits``): sequences are ordered
by SHA-256 of ``"<seed>/<sequence>"`` and the first ones filled into the splits in order
until each split holds its quota (largest-remainder rounding of ``fraction * sequences``;
every split with a non-zero fraction gets at least one sequence when there are enough).
Sequences already in the dataset keep their split when frames are appended; new sequences
fill the remaining quotas. With split files (``--split-file``), see :func:`read_split_file`.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from ...errors import ParameterError
from ...io.dataset import check_relative_path
from ...validate import check_non_negative

__all__ = [
    "DEFAULT_SPLIT",
    "SIDE_CAMERA",
    "SplitList",
    "SplitListReport",
    "SplitListsReport",
    "assign_splits",
    "match_split_lines",
    "parse_split_fractions",
    "parse_split_lines",
    "read_split_file",
    "sequence_resolver",
    "split_file_assignments",
    "split_list_of",
]

DEFAULT_SPLIT = {"train": 0.8, "val": 0.1, "test": 0.1}


# -- parsing -------------------------------------------------------------------------------------
def parse_split_fractions(text: str | Mapping[str, float]) -> dict[str, float]:
    """Parse ``0.8,0.1,0.1`` (train, val, test), ``0.9,0.1`` or ``train=0.7,val=0.3``.

    Fractions must be >= 0 and sum to 1 (within 1e-6).
    """
    if isinstance(text, Mapping):
        fractions = {str(k): float(v) for k, v in text.items()}
    else:
        items = [s.strip() for s in str(text).split(",") if s.strip()]
        fractions = {}
        try:
            if items and all("=" in s for s in items):
                for s in items:
                    k, _, v = s.partition("=")
                    if not k.strip() or k.strip() in fractions:
                        raise ParameterError(f"a split name is empty or given twice: {text!r}")
                    fractions[k.strip()] = float(v)
            elif 2 <= len(items) <= 3 and not any("=" in s for s in items):
                fractions = dict(
                    zip(("train", "val", "test")[: len(items)], map(float, items), strict=True)
                )
            else:
                raise ParameterError(
                    f"expected 2 or 3 fractions (train,val[,test]) or name=fraction pairs, got {text!r}"
                )
        except ValueError as exc:
            if isinstance(exc, ParameterError):
                raise
            raise ParameterError(f"expected split fractions as numbers, got {text!r}") from None
    if not fractions:
        raise ParameterError("no split fractions given")
    for name, f in fractions.items():
        check_relative_path(name, what="split name")
        check_non_negative(f, f"split fraction of '{name}'")
    total = sum(fractions.values())
    if abs(total - 1.0) > 1e-6:
        raise ParameterError(f"split fractions must sum to 1, got {total:g}")
    return fractions


def sequence_resolver(spec: str, default: str) -> Callable[[str], str]:
    """``parent`` (the key's folder; ``default`` for a flat folder) or ``regex:PATTERN``."""
    if spec == "parent":
        return lambda key: key.rpartition("/")[0] or default
    if spec.startswith("regex:"):
        pattern = spec[len("regex:") :]
        try:
            rx = re.compile(pattern)
        except re.error as exc:
            raise ParameterError(
                f"--sequence-from: bad regular expression {pattern!r} ({exc})"
            ) from exc

        def fn(key: str) -> str:
            m = rx.search(key)
            if m is None:
                raise ParameterError(f"--sequence-from: {pattern!r} does not match frame '{key}'")
            if "sequence" in rx.groupindex:
                seq = m.group("sequence")
            elif rx.groups:
                seq = m.group(1)
            else:
                seq = m.group(0)
            if not seq:
                raise ParameterError(f"--sequence-from: empty sequence for frame '{key}'")
            return seq

        return fn
    raise ParameterError(f"expected parent or regex:PATTERN, got {spec!r}", param="sequence_from")


# -- split files -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class SplitList:
    """One split's list of samples, read from a file or shipped with the package.

    Attributes
    ----------
    name : str
        The split its lines go to (``train``, ``val``, ``test``...).
    source : str
        Where the lines came from (a path, or a shipped list's name), for reports.
    lines : tuple of tuples of str
        As :func:`read_split_file` returns them.
    """

    name: str
    source: str
    lines: tuple[tuple[str, ...], ...]


def parse_split_lines(text: str, where: str) -> list[tuple[str, ...]]:
    """The lines of a split list (see :func:`read_split_file`); ``where`` names it in errors."""
    lines = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = tuple(line.split())
        if len(parts) > 3 or (len(parts) == 3 and parts[2] not in ("l", "r")):
            raise ParameterError(
                f"{where}:{n}: expected '<folder> <frame> [l|r]' or an id: {line!r}"
            )
        if len(parts) >= 2 and not parts[1].isdigit():
            raise ParameterError(f"{where}:{n}: frame '{parts[1]}' is not a number")
        lines.append(parts)
    return lines


def read_split_file(path: str | os.PathLike) -> list[tuple[str, ...]]:
    """Read a split list: one sample per line, blank lines and ``#`` comments ignored.

    Each line is either the KITTI Eigen form ``<folder> <frame> [l|r]``
    (``2011_09_26/2011_09_26_drive_0001_sync 0000000005 l``) or a single name: a sample id, or
    a sequence (a nuScenes scene: every sample of it). A list ending in ``.xz`` (as the
    shipped ones are stored) is read xz-compressed, at most :data:`MAX_SPLIT_TEXT` bytes of
    text.
    """
    import lzma

    path = Path(path)
    try:
        if path.suffix == ".xz":
            unpack = lzma.LZMADecompressor()
            data = unpack.decompress(path.read_bytes(), max_length=MAX_SPLIT_TEXT)
            if not unpack.eof:
                raise ValueError(f"more than {MAX_SPLIT_TEXT >> 20} MiB of text, or cut short")
            text = data.decode("utf-8")
        else:
            text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError, ValueError, lzma.LZMAError) as exc:
        raise ParameterError(f"{path}: cannot read split file ({exc})") from exc
    return parse_split_lines(text, str(path))


#: The most text a compressed split list may unpack to (bytes): the largest official list,
#: Eigen's full training split, is 2 MB.
MAX_SPLIT_TEXT = 256 << 20


def _frame_number(stem: str) -> int | None:
    m = re.search(r"(\d+)$", stem)
    return int(m.group(1)) if m else None


#: The camera of an Eigen line's side: ``l`` the left colour camera, ``r`` the right one.
SIDE_CAMERA = {"l": 2, "r": 3}
_CAMERA_FOLDERS = {"image_02": 2, "image_03": 3}


@dataclass(frozen=True)
class _LineMatch:
    """What the lines of a list matched: sample ids by line, and the lines that matched none
    (``absent``) or only frames of the other camera (``other_camera``)."""

    matches: dict[str, list[str]]
    absent: list[tuple[str, ...]]
    other_camera: list[tuple[str, ...]]


def _match_lines(
    lines: Iterable[tuple[str, ...]], samples: Mapping[str, str], camera: int | None
) -> _LineMatch:
    # (folder component, frame number) -> ids: one look-up per line, whatever the tree's size
    by_place: dict[tuple[str, int], list[str]] = defaultdict(list)
    by_sequence: dict[str, list[str]] = defaultdict(list)
    cameras: dict[str, set[int]] = {}
    for sid, seq in samples.items():
        comps = {seq, *sid.split("/")[:-1], *seq.split("/")}
        num = _frame_number(sid.rpartition("/")[2])
        if num is not None:
            for c in comps:
                by_place[(c, num)].append(sid)
        by_sequence[seq].append(sid)
        cams = {_CAMERA_FOLDERS[c] for c in comps & _CAMERA_FOLDERS.keys()}
        cameras[sid] = cams or ({camera} if camera is not None else set())
    out = _LineMatch({}, [], [])
    for parts in lines:
        other = False
        if len(parts) == 1:
            found = [parts[0]] if parts[0] in samples else list(by_sequence.get(parts[0], ()))
        else:
            folder, number = parts[0], int(parts[1])
            drive = folder.rstrip("/").rpartition("/")[2]
            side = SIDE_CAMERA.get(parts[2]) if len(parts) == 3 else None
            found = []
            candidates = by_place.get((drive, number), []) + by_place.get((folder, number), [])
            for sid in dict.fromkeys(candidates):
                cams = cameras[sid]
                if side is not None and cams and side not in cams:
                    other = True
                    continue
                found.append(sid)
        if found:
            out.matches[" ".join(parts)] = found
        elif other:
            out.other_camera.append(parts)
        else:
            out.absent.append(parts)
    return out


def match_split_lines(
    lines: Iterable[tuple[str, ...]], samples: Mapping[str, str], *, camera: int | None = None
) -> tuple[dict[str, list[str]], int]:
    """Match split-file lines to sample ids.

    Parameters
    ----------
    lines : iterable of tuples
        From :func:`read_split_file`.
    samples : mapping id -> sequence
    camera : int, optional
        The KITTI camera the samples' images come from (2: ``image_02``), for samples whose id
        does not name it; None: unknown (the side of a line is then not checked for them).

    Returns
    -------
    matches : dict line -> list of ids
    missing : int
        Lines that match no sample.

    Notes
    -----
    A one-field line matches the sample with exactly that id, else every sample of the
    sequence of that name (a nuScenes scene). An Eigen line ``<folder> <frame> [l|r]``
    matches a sample when (1) the sample's frame number (the trailing digits of its file
    stem) equals ``int(frame)``, (2) the last component of ``folder`` (the drive,
    ``2011_09_26_drive_0001_sync``) is the sample's sequence or one of the folder components
    of its id or sequence, and (3) its side (``l``: ``image_02``, ``r``: ``image_03``) is the
    sample's camera: the ``image_0N`` component of its id, else ``camera``. A line of the
    other camera is no match.
    """
    found = _match_lines(lines, samples, camera)
    return found.matches, len(found.absent) + len(found.other_camera)


def _split_from_file_name(path: Path) -> str:
    stem = path.stem.lower()
    for name in ("train", "val", "test"):
        if name in stem:
            return name
    raise ParameterError(
        f"cannot tell the split of {path.name} from its name: give it as NAME=PATH (e.g. test={path})"
    )


def _line_group(parts: tuple[str, ...]) -> str:
    """The drive of an Eigen line, the sequence (scene) of a one-field line."""
    if len(parts) > 1:
        return parts[0].rstrip("/").rpartition("/")[2]
    return parts[0].rpartition("/")[0] or parts[0]


#: Drives / scenes named in a report's text line; the rest are counted.
SHOWN_GROUPS = 3


@dataclass(frozen=True)
class SplitListReport:
    """What one split list matched.

    Attributes
    ----------
    split, source : str
        The split its lines go to, and where they came from.
    listed : int
        Lines.
    present : int
        Lines that matched a frame of the inputs.
    absent : int
        Lines naming a frame (a scene) that the inputs lack.
    other_camera : int
        Lines of the other camera (``r`` when the dataset is ``image_02``): no match.
    absent_groups : dict of str -> (int, int)
        Drive (scene, sequence) -> its absent lines and its listed lines, for the drives with
        absent lines, by name.
    noun : str
        What a group is: ``drives``, ``scenes`` or ``sequences``.
    """

    split: str
    source: str
    listed: int
    present: int
    absent: int
    other_camera: int
    absent_groups: dict[str, tuple[int, int]]
    noun: str

    def counts(self) -> dict:
        """The counts, without the groups (the manifest's record)."""
        return {"split": self.split, "source": self.source, "listed": self.listed,
                "present": self.present, "absent": self.absent,
                "other_camera": self.other_camera}  # fmt: skip

    def to_dict(self) -> dict:
        """The counts and every drive (scene) with absent lines (the JSON summary)."""
        groups = {g: {"absent": a, "listed": n} for g, (a, n) in self.absent_groups.items()}
        return {**self.counts(), f"absent_{self.noun}": groups}

    def text(self, label: str) -> str:
        """``eigen test: 697 listed, 3 present, 694 absent: drives A (22 of 25), B (25), C
        (25) and 25 more``: a drive's absent lines (of its lines, when some are present); a
        scene's one line is its name only."""
        line = f"{label}: {self.listed} listed, {self.present} present, {self.absent} absent"
        if self.other_camera:
            line += f", {self.other_camera} of the other camera"
        if self.absent_groups:
            shown = [g if n == 1 else f"{g} ({a})" if a == n else f"{g} ({a} of {n})"
                     for g, (a, n) in list(self.absent_groups.items())[:SHOWN_GROUPS]]  # fmt: skip
            rest = len(self.absent_groups) - len(shown)
            line += f": {self.noun} {', '.join(shown)}" + (f" and {rest} more" if rest else "")
        return line


@dataclass(frozen=True)
class SplitListsReport:
    """What the split lists of a build matched (:func:`split_file_assignments`).

    Attributes
    ----------
    lists : tuple of SplitListReport
        One per list, in the order given.
    name : str, optional
        The official split the lists are (``--split eigen``); None for files.
    not_listed : int
        Frames of the inputs in no list: left out of the dataset.
    """

    lists: tuple[SplitListReport, ...]
    name: str | None = None
    not_listed: int = 0

    @property
    def listed(self) -> int:
        return sum(r.listed for r in self.lists)

    @property
    def missing(self) -> int:
        """Lines that matched no frame (absent, or of the other camera)."""
        return sum(r.absent + r.other_camera for r in self.lists)

    def manifest_dict(self) -> dict:
        """What the manifest records: the totals (``listed``, ``missing`` as sparsetools 0.3
        recorded them), and the counts of each list."""
        return {"listed": self.listed, "missing": self.missing, "not_listed": self.not_listed,
                "lists": [r.counts() for r in self.lists]}  # fmt: skip

    def to_dict(self) -> dict:
        """Everything, the absent drives (scenes) of each list included."""
        return {"name": self.name, "listed": self.listed, "missing": self.missing,
                "not_listed": self.not_listed, "lists": [r.to_dict() for r in self.lists]}  # fmt: skip

    def lines(self) -> list[str]:
        """One line per list, then the frames in no list."""
        out = [
            r.text(f"{self.name} {r.split}" if self.name else f"{r.split} ({Path(r.source).name})")
            for r in self.lists
        ]
        which = f"the {self.name} lists" if self.name else "the split files"
        out.append(
            f"{self.not_listed} frame(s) of the inputs are in none of {which}: left out"
            if self.not_listed
            else f"every frame of the inputs is in one of {which}"
        )
        return out


def _report(split_list: SplitList, found: _LineMatch) -> SplitListReport:
    listed: dict[str, int] = defaultdict(int)
    absent: dict[str, int] = defaultdict(int)
    for parts in split_list.lines:
        listed[_line_group(parts)] += 1
    for parts in found.absent:
        absent[_line_group(parts)] += 1
    first = split_list.lines[0] if split_list.lines else ("",)
    noun = "drives" if len(first) > 1 else "sequences" if "/" in first[0] else "scenes"
    return SplitListReport(
        split=split_list.name, source=split_list.source, listed=len(split_list.lines),
        present=len(found.matches), absent=len(found.absent),
        other_camera=len(found.other_camera),
        absent_groups={g: (absent[g], listed[g]) for g in sorted(absent)}, noun=noun,
    )  # fmt: skip


def split_list_of(item: str | os.PathLike | tuple[str, str] | SplitList) -> SplitList:
    """A split list from ``--split-file``'s item: ``NAME=PATH``, ``(name, path)`` or a path
    whose name holds train / val / test."""
    if isinstance(item, SplitList):
        return item
    if isinstance(item, tuple):
        name, path = item
    elif "=" in str(item) and not Path(str(item)).exists():
        name, _, path = str(item).partition("=")
    else:
        path = item
        name = _split_from_file_name(Path(item))
    check_relative_path(name, what="split name")
    return SplitList(name, str(path), tuple(read_split_file(path)))


def split_file_assignments(
    split_files: Iterable[str | tuple[str, str] | SplitList],
    samples: Mapping[str, str],
    *,
    camera: int | None = None,
    name: str | None = None,
) -> tuple[dict[str, str], SplitListsReport]:
    """Each listed sample's split, and what each list matched.

    Parameters
    ----------
    split_files : iterable
        Split lists (:class:`SplitList`) or ``--split-file`` items (see :func:`split_list_of`).
    samples : mapping id -> sequence
    camera : int, optional
        The KITTI camera of samples whose id does not name one (see :func:`match_split_lines`).
    name : str, optional
        The official split the lists are, for the report.

    Returns
    -------
    assignment : dict id -> split
        The listed samples only.
    report : SplitListsReport
        Without ``not_listed`` (the caller knows which frames it had).

    Raises
    ------
    ParameterError
        A sample listed in two splits, an unreadable list.
    """
    assignment: dict[str, str] = {}
    reports = []
    for item in split_files:
        split_list = split_list_of(item)
        found = _match_lines(split_list.lines, samples, camera)
        reports.append(_report(split_list, found))
        for ids in found.matches.values():
            for sid in ids:
                if assignment.get(sid, split_list.name) != split_list.name:
                    raise ParameterError(
                        f"sample '{sid}' is listed in two splits ({assignment[sid]} and "
                        f"{split_list.name})"
                    )
                assignment[sid] = split_list.name
    return assignment, SplitListsReport(tuple(reports), name=name)


# -- split assignment ------------------------------------------------------------------------------
def _quotas(fractions: Mapping[str, float], n: int) -> dict[str, int]:
    """Largest-remainder counts summing to n; non-zero fractions get >= 1 when n allows."""
    names = list(fractions)
    exact = [fractions[k] * n for k in names]
    counts = [math.floor(e) for e in exact]
    order = sorted(range(len(names)), key=lambda i: (-(exact[i] - counts[i]), i))
    for i in order[: n - sum(counts)]:
        counts[i] += 1
    nonzero = [i for i in range(len(names)) if fractions[names[i]] > 0]
    if n >= len(nonzero):
        for i in nonzero:
            if counts[i] == 0:
                donor = max(range(len(names)), key=lambda j: (counts[j], -j))
                counts[donor] -= 1
                counts[i] += 1
    return dict(zip(names, counts, strict=True))


def assign_splits(
    sequences: Iterable[str],
    fractions: Mapping[str, float],
    *,
    seed: int = 0,
    pinned: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """Assign whole sequences to splits, deterministically from ``seed``.

    Parameters
    ----------
    sequences : iterable of str
        Every sequence of the dataset (order does not matter).
    fractions : mapping split -> fraction
        Summing to 1 (see :func:`parse_split_fractions`).
    seed : int
    pinned : mapping sequence -> split, optional
        Sequences whose split is fixed (already in the dataset when appending).

    Returns
    -------
    dict sequence -> split
        The result depends only on the set of sequences, the fractions, the seed and
        ``pinned``: not on input order, worker count or platform (SHA-256 ordering).
    """

    pinned = dict(pinned or {})
    seqs = sorted(set(sequences) | set(pinned))
    quotas = _quotas(fractions, len(seqs))
    out = dict(pinned)
    remaining = dict(quotas)
    for split in pinned.values():
        if split in remaining:
            remaining[split] -= 1

    def key(s: str) -> bytes:
        return hashlib.sha256(f"{int(seed)}/{s}".encode()).digest()

    names = list(fractions)
    for s in sorted((s for s in seqs if s not in out), key=key):
        target = next((k for k in names if remaining[k] > 0), None)
        if target is None:  # quotas used up by pinned sequences: largest fraction
            target = max(names, key=lambda k: fractions[k])
        out[s] = target
        remaining[target] -= 1
    return out
