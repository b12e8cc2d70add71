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
from pathlib import Path

from ...errors import ParameterError
from ...io.dataset import check_relative_path
from ...validate import check_non_negative

__all__ = [
    "DEFAULT_SPLIT",
    "assign_splits",
    "match_split_lines",
    "parse_split_fractions",
    "read_split_file",
    "sequence_resolver",
    "split_file_assignments",
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
def read_split_file(path: str | os.PathLike) -> list[tuple[str, ...]]:
    """Read a split list: one sample per line, blank lines and ``#`` comments ignored.

    Each line is either the KITTI Eigen form ``<folder> <frame> [l|r]``
    (``2011_09_26/2011_09_26_drive_0001_sync 0000000005 l``) or a single sample id.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ParameterError(f"{path}: cannot read split file ({exc})") from exc
    lines = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = tuple(line.split())
        if len(parts) > 3 or (len(parts) == 3 and parts[2] not in ("l", "r")):
            raise ParameterError(
                f"{path}:{n}: expected '<folder> <frame> [l|r]' or an id: {line!r}"
            )
        if len(parts) >= 2 and not parts[1].isdigit():
            raise ParameterError(f"{path}:{n}: frame '{parts[1]}' is not a number")
        lines.append(parts)
    return lines


def _frame_number(stem: str) -> int | None:
    m = re.search(r"(\d+)$", stem)
    return int(m.group(1)) if m else None


def match_split_lines(
    lines: Iterable[tuple[str, ...]], samples: Mapping[str, str]
) -> tuple[dict[str, list[str]], int]:
    """Match split-file lines to sample ids.

    Parameters
    ----------
    lines : iterable of tuples
        From :func:`read_split_file`.
    samples : mapping id -> sequence

    Returns
    -------
    matches : dict line -> list of ids
    missing : int
        Lines that match no sample.

    Notes
    -----
    A one-field line matches the sample with exactly that id. An Eigen line
    ``<folder> <frame> [l|r]`` matches a sample when (1) the sample's frame number (the
    trailing digits of its file stem) equals ``int(frame)``, (2) the last component of
    ``folder`` (the drive, ``2011_09_26_drive_0001_sync``) is the sample's sequence or one
    of the folder components of its id or sequence, and (3) when the sample's id has an
    ``image_02`` / ``image_03`` component, it agrees with ``l`` / ``r``.
    """
    by_number: dict[int, list[str]] = defaultdict(list)
    components: dict[str, set[str]] = {}
    for sid, seq in samples.items():
        stem = sid.rpartition("/")[2]
        num = _frame_number(stem)
        if num is not None:
            by_number[num].append(sid)
        components[sid] = {seq, *sid.split("/")[:-1], *seq.split("/")}
    matches: dict[str, list[str]] = {}
    missing = 0
    for parts in lines:
        key = " ".join(parts)
        if len(parts) == 1:
            found = [parts[0]] if parts[0] in samples else []
        else:
            folder, number = parts[0], int(parts[1])
            drive = folder.rstrip("/").rpartition("/")[2]
            side = {"l": "image_02", "r": "image_03"}.get(parts[2]) if len(parts) == 3 else None
            found = []
            for sid in by_number.get(number, []):
                comps = components[sid]
                if drive not in comps and folder not in comps:
                    continue
                cams = comps & {"image_02", "image_03"}
                if side is not None and cams and side not in cams:
                    continue
                found.append(sid)
        if found:
            matches[key] = found
        else:
            missing += 1
    return matches, missing


def _split_from_file_name(path: Path) -> str:
    stem = path.stem.lower()
    for name in ("train", "val", "test"):
        if name in stem:
            return name
    raise ParameterError(
        f"cannot tell the split of {path.name} from its name: give it as NAME=PATH (e.g. test={path})"
    )


def split_file_assignments(
    split_files: Iterable[str | tuple[str, str]], samples: Mapping[str, str]
) -> tuple[dict[str, str], dict]:
    assignment: dict[str, str] = {}
    report = {"listed": 0, "missing": 0}
    for item in split_files:
        if isinstance(item, tuple):
            name, path = item
        elif "=" in str(item) and not Path(str(item)).exists():
            name, _, path = str(item).partition("=")
        else:
            path = item
            name = _split_from_file_name(Path(item))
        check_relative_path(name, what="split name")
        lines = read_split_file(path)
        matches, missing = match_split_lines(lines, samples)
        report["listed"] += len(lines)
        report["missing"] += missing
        for ids in matches.values():
            for sid in ids:
                if assignment.get(sid, name) != name:
                    raise ParameterError(
                        f"sample '{sid}' is listed in two splits ({assignment[sid]} and {name})"
                    )
                assignment[sid] = name
    return assignment, report


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
