"""The last step of ``dataset build``: merge the staged frames into the dataset.

The existing manifest and every staged frame (:mod:`.staged`: pack entries, and the record
files of earlier versions) become one manifest: splits assigned (given per frame, or by
sequence: :func:`.splits.assign_splits`), the points written as new ``sparse/part-*.parquet``
files, then the manifest atomically, then the parts no longer referenced and the staging
folder deleted. Interrupted anywhere, the next build redoes it.
"""

from __future__ import annotations

import bisect
import dataclasses
import heapq
import itertools
import logging
import re
import shutil
from collections import Counter, defaultdict
from collections.abc import Collection, Iterable
from pathlib import Path

import numpy as np

from ...errors import FormatError
from ...io.atomic import TMP_PREFIX
from ...io.containment import ContainedPaths, remove_output
from ...io.dataset import (
    FULL_SCHEMA,
    MANIFEST_NAME,
    MANIFEST_ROW_GROUP,
    OPTIONAL_SCHEMA,
    POINTS_DIR,
    SPARSE_DIR,
    ManifestRow,
    read_manifest,
    resolve_in_dataset,
)
from ...io.dataset_parts import (
    points_part_table,
    read_points_part,
    read_sparse_part,
    write_points_part,
    write_sparse_part,
)
from ...io.manifest_writer import ManifestWriter
from ...io.points_table import sparse_part_table
from .splits import assign_splits
from .staged import StagedAt, latest_entries, read_staged, read_staged_entry, staged_row
from .staging import POINTS_SUFFIX, STAGING

__all__ = ["merge_staged"]

log = logging.getLogger(__name__)

#: Samples per points part at most (about 0.5 MB each for a KITTI scan's image points).
POINTS_PER_PART = 100
_PART_RE = re.compile(r"^part-(\d{5,})\.parquet$")


# -- merging the staged frames -------------------------------------------------------------------------
def _part_name(index: int) -> str:
    """A sparse part's path in the dataset."""
    return f"{SPARSE_DIR}/part-{index:05d}.parquet"


def _part_index(name: str) -> int | None:
    m = _PART_RE.match(name)
    return int(m.group(1)) if m else None


def _natural(text: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", text))


def _frame_ranks(sequence: Iterable[str], frame: Iterable[str]) -> dict[tuple[str, str], int]:
    """``frame_index`` by (sequence, frame): each frame's rank in its sequence, frames in
    natural order (numbers compared as numbers: ``2`` before ``10``); the cameras of one
    frame share it."""
    by_seq: dict[str, set[str]] = defaultdict(set)
    for seq, name in zip(sequence, frame, strict=True):
        by_seq[seq].add(name)
    return {
        (seq, name): i
        for seq, names in by_seq.items()
        for i, name in enumerate(sorted(names, key=_natural))
    }


_OPTIONAL = tuple(OPTIONAL_SCHEMA.names)


@dataclasses.dataclass
class _Staged:
    """The staged frames, in sample-id order, as the few columns the merge decides on (a
    record's whole row is read again when it is written: nothing per frame is held but these)."""

    folder: Path
    ids: list[str]
    sequence: list[str]
    frame: list[str]
    rgb_root: list[str | None]
    optional: list[int]  # bit k: the row fills OPTIONAL_SCHEMA's k-th column
    points: list[bool]  # the record holds the frame's sparse points
    where: list[StagedAt | None]  # its pack entry; None: a file of its own (earlier versions)

    @classmethod
    def scan(cls, staging: Path) -> _Staged:
        """Read every staged record once: each sample's latest pack entry, and the record
        files of earlier versions (a sample with both has its entry). A record is untrusted
        input: one naming another sample than its entry's id or its file name is refused
        (it must not stand for another frame)."""
        found: dict[str, tuple[StagedAt | None, _Brief, bool]] = {}
        for fid, at in latest_entries(staging).items():
            source = f"{staging / at.pack} (byte {at.offset})"
            row, points = staged_row(read_staged_entry(staging, at), source)
            if row.id != fid:
                raise FormatError(
                    f"{source}: corrupt staging record (it names sample {row.id!r}, its "
                    f"entry {fid!r}); delete {staging} and rerun"
                )
            found[fid] = (at, _Brief.of(row), points is not None)
        if staging.is_dir():
            for p in staging.rglob("*.rec"):
                fid = p.relative_to(staging).as_posix()[: -len(".rec")]
                if p.name.startswith(TMP_PREFIX) or fid in found:
                    continue
                row, points = read_staged(p)
                if row.id != fid:
                    raise FormatError(
                        f"{p}: corrupt staging record (it names sample {row.id!r}, not "
                        f"{fid!r}); delete it and rerun"
                    )
                found[fid] = (None, _Brief.of(row), points is not None)
        s = cls(staging, [], [], [], [], [], [], [])
        sequences: dict[str, str] = {}
        for fid in sorted(found):
            at, row, has_points = found.pop(fid)
            s.ids.append(fid)
            s.sequence.append(sequences.setdefault(row.sequence, row.sequence))  # shared
            s.frame.append(row.frame)
            s.rgb_root.append(row.rgb_root)
            s.optional.append(row.optional)
            s.points.append(has_points)
            s.where.append(at)
        return s

    def read(self, i: int) -> tuple[ManifestRow, tuple | None]:
        """The ``i``-th record's row and points."""
        at = self.where[i]
        if at is None:
            return read_staged(self.folder / f"{self.ids[i]}.rec")
        return staged_row(
            read_staged_entry(self.folder, at), f"{self.folder / at.pack} (byte {at.offset})"
        )

    def row(self, fid: str) -> ManifestRow:
        """The row of sample ``fid`` (staged)."""
        i = bisect.bisect_left(self.ids, fid)
        if i == len(self.ids) or self.ids[i] != fid:
            raise KeyError(fid)
        return self.read(i)[0]


@dataclasses.dataclass(frozen=True, slots=True)
class _Brief:
    """What the merge keeps of a staged row until it writes it."""

    sequence: str
    frame: str
    rgb_root: str | None
    optional: int

    @classmethod
    def of(cls, row: ManifestRow) -> _Brief:
        bits = sum(1 << k for k, name in enumerate(_OPTIONAL) if getattr(row, name) is not None)
        return cls(row.sequence, row.frame, row.rgb_root, bits)


def merge_staged(
    out: Path,
    *,
    fractions,
    seed,
    assignment,
    info,
    frames_per_part,
    only: set[str] | None = None,
    failed: Collection[str] = (),
) -> dict:
    """Merge staged frames into the manifest and parts (see the module docstring).

    ``assignment``: sample id -> split (split files, the tree), else splits by sequence from
    ``fractions``. ``only``: keep only these sample ids (``--overwrite``: the dataset holds
    this run only). ``failed``: the frames that failed in this run; neither their row of an
    earlier build nor an entry an earlier, interrupted run staged for them stands in the
    manifest: a rerun holds what a fresh run would (``--on-error skip`` leaves them out).

    Memory: the earlier manifest as an Arrow table (when there is one), and per new frame its
    id, sequence and frame name; rows are read again and written a row group at a time.
    """
    import pyarrow as pa

    # Everything written or deleted below is inside the dataset and reached through no link
    # (a ds/sparse that links to another folder is refused, its parts are never touched).
    contained = ContainedPaths(out)
    for folder in (out / STAGING, out / SPARSE_DIR):
        contained.check(folder, what="folder")
    contained.check(out / MANIFEST_NAME)
    staging = out / STAGING
    staged = _Staged.scan(staging)
    manifest_path = out / MANIFEST_NAME
    old = ManifestRow.to_table([], every_column=True)
    old_info: dict = {}
    if manifest_path.is_file():
        table, old_info = read_manifest(manifest_path)
        old = table.select(FULL_SCHEMA.names).cast(FULL_SCHEMA)  # later columns: not kept
        del table
    old_ids = old.column("id").to_pylist()
    dropped = np.zeros(len(old_ids), dtype=bool)  # --overwrite: rows of frames not given
    if only is not None:
        dropped = np.array([fid not in only for fid in old_ids], dtype=bool)
    failed = set(failed)
    if failed:
        dropped |= np.array([fid in failed for fid in old_ids], dtype=bool)
    if not staged.ids and not dropped.any():
        return _counts(old)

    restaged = set(staged.ids)
    gone = dropped | np.array([fid in restaged for fid in old_ids], dtype=bool)
    del restaged
    kept = sorted(np.flatnonzero(~gone).tolist(), key=old_ids.__getitem__)
    lost = old.filter(pa.array(gone))
    referenced_old = _values(old.column("sparse_parquet"))
    removed_parts = _values(lost.column("sparse_parquet"))
    referenced_points = _values(old.column("points_parquet"))
    removed_points = _values(lost.column("points_parquet"))
    del lost
    old_seq, old_frame = old.column("sequence").to_pylist(), old.column("frame").to_pylist()
    old_split = old.column("split").to_pylist()
    pinned: dict[str, str] = {}
    for i in kept:  # the earlier build's rows, in id order: the first split wins
        if old_split[i] is not None:
            pinned.setdefault(old_seq[i], old_split[i])

    # The new rows: the staged ones the split lists name (all without lists), their splits;
    # with ``only``, of those frames alone; never a frame that failed in this run.
    new = range(len(staged.ids))
    if failed:
        new = [i for i in new if staged.ids[i] not in failed]
    if only is not None:
        new = [i for i in new if staged.ids[i] in only]
    if assignment is not None:
        unknown = [staged.ids[i] for i in new if staged.ids[i] not in assignment]
        if unknown:
            log.warning(
                "%d staged frame(s) are not in the split files and are left out: %s",
                len(unknown),
                ", ".join(unknown[:5]),
            )
        new = [i for i in new if staged.ids[i] in assignment]
        new_split = [assignment.get(fid) for fid in staged.ids]
    else:
        seq_split = assign_splits(
            {staged.sequence[i] for i in new}, fractions, seed=seed, pinned=pinned
        )
        new_split = [seq_split.get(seq) for seq in staged.sequence]

    sparse_dir = out / SPARSE_DIR
    on_disk = sorted(sparse_dir.glob("part-*.parquet")) if sparse_dir.is_dir() else []
    # Parts no manifest row refers to were written by a finalize that was interrupted before
    # its manifest: drop them, so the resumed build numbers its parts as an uninterrupted one.
    for p in on_disk:
        if f"{SPARSE_DIR}/{p.name}" not in referenced_old:
            remove_output(out, p)
    on_disk = [p for p in on_disk if p.exists()]
    next_part = 1 + max((i for p in on_disk if (i := _part_index(p.name)) is not None), default=-1)
    moved: dict[str, tuple[str, int]] = {}  # id -> (sparse part, row) of kept rows that move
    written = []

    def new_part(table: pa.Table, ids: list[str] | None) -> None:
        nonlocal next_part
        rel = _part_name(next_part)
        next_part += 1
        write_sparse_part(contained.check(out / rel), table)
        written.append(rel)
        for i, fid in enumerate(ids or ()):
            moved[fid] = (rel, i)

    # Old parts that lose rows (overwritten frames) are rewritten with the rows kept.
    for sub, ids in _kept_rows(out, old, kept, "sparse", removed_parts, read_sparse_part):
        new_part(sub, ids)

    # The new frames' points, in id order, frames_per_part to a part, written as the manifest
    # pass below reads their records (each staged record is read there once): the j-th new
    # frame with points is row j % frames_per_part of part first_new + j // frames_per_part.
    first_new = next_part
    pending: list[tuple[str, tuple, tuple[int, int]]] = []

    def flush_points() -> None:
        if pending:
            ids, points, sizes = zip(*pending, strict=True)
            new_part(sparse_part_table(list(ids), list(points), list(sizes)), None)
            pending.clear()
            pa.default_memory_pool().release_unused()

    points_of, drop_stale_points = _merge_points(
        out, contained, old, kept, [staged.ids[i] for i in new], referenced_points,
        removed_points, frames_per_part, staged.row,
    )  # fmt: skip

    # The manifest, a row group at a time: kept rows and new rows merged in id order.
    order = heapq.merge(
        ((old_ids[i], False, i) for i in kept), ((staged.ids[i], True, i) for i in new)
    )
    ranks = _frame_ranks(
        [*(old_seq[i] for i in kept), *(staged.sequence[i] for i in new)],
        [*(old_frame[i] for i in kept), *(staged.frame[i] for i in new)],
    )
    # The optional columns some row fills, and the image roots some row names (kept rows:
    # one column at a time, never a copy of the earlier manifest).
    kept_at = pa.array(kept, pa.int64())
    filled = {name for k, name in enumerate(_OPTIONAL)
              if any(staged.optional[i] >> k & 1 for i in new)
              or old.column(name).take(kept_at).null_count < len(kept)}  # fmt: skip
    if points_of:
        filled |= {"points_parquet", "points_row"}
    used = {staged.rgb_root[i] for i in new} | _values(old.column("rgb_root").take(kept_at))
    used.discard(None)
    merged_info = {**old_info, **info}
    merged_info.pop("schema_version", None)
    # Roots of referenced images (--store reference): the newest path of each name that a
    # row still names.
    roots = {**old_info.get("roots", {}), **info.get("roots", {})}
    merged_info.pop("roots", None)
    if used:
        merged_info["roots"] = {k: v for k, v in sorted(roots.items()) if k in used}

    def rows_of(entries: list[tuple[str, bool, int]]) -> pa.Table:
        """The manifest rows of ``entries`` (id order), their merged values filled in."""
        old_at = [i for _, is_new, i in entries if not is_new]
        new_at = [i for _, is_new, i in entries if is_new]
        new_rows = []
        for i in new_at:
            row, pts = staged.read(i)
            if row.id != staged.ids[i] or (pts is not None) != staged.points[i]:
                raise FormatError(
                    f"{staging}: the staging record of {staged.ids[i]} changed during the "
                    "merge; rerun"
                )
            new_rows.append(row)
            if pts is not None:
                pending.append((row.id, pts, (row.height, row.width)))
                if len(pending) == frames_per_part:
                    flush_points()
        table = pa.concat_tables([
            old.take(pa.array(old_at, pa.int64())),
            ManifestRow.to_table(new_rows, every_column=True),
        ])  # fmt: skip
        del new_rows
        rank_old, rank_new = iter(range(len(old_at))), iter(range(len(old_at), table.num_rows))
        table = table.take(pa.array(
            [next(rank_new) if is_new else next(rank_old) for _, is_new, _ in entries],
            pa.int64(),
        ))  # fmt: skip
        values = {name: table.column(name).to_pylist() for name in _CHANGING}
        for k, (fid, is_new, i) in enumerate(entries):
            if is_new:
                values["split"][k] = new_split[i]
                values["sparse_parquet"][k] = values["sparse_row"][k] = None
                if staged.points[i]:
                    j = next(nth_with_points)
                    values["sparse_parquet"][k] = _part_name(first_new + j // frames_per_part)
                    values["sparse_row"][k] = j % frames_per_part
                values["points_parquet"][k], values["points_row"][k] = points_of.get(
                    fid, (None, None)
                )
            else:
                if fid in moved:
                    values["sparse_parquet"][k], values["sparse_row"][k] = moved[fid]
                if fid in points_of:
                    values["points_parquet"][k], values["points_row"][k] = points_of[fid]
        seq, frame = table.column("sequence").to_pylist(), table.column("frame").to_pylist()
        values["frame_index"] = [ranks[s, f] for s, f in zip(seq, frame, strict=True)]
        for name, column in values.items():
            f = FULL_SCHEMA.field(name)
            table = table.set_column(
                table.schema.get_field_index(name), f, pa.array(column, type=f.type)
            )
        return table

    nth_with_points = itertools.count()
    counts = Counter()
    sequences = set()
    with ManifestWriter(manifest_path, optional=filled, referenced=bool(used),
                        info=merged_info) as writer:  # fmt: skip
        while entries := list(itertools.islice(order, MANIFEST_ROW_GROUP)):
            table = rows_of(entries)
            writer.write(table)
            counts.update(table.column("split").to_pylist())
            sequences.update(table.column("sequence").unique().to_pylist())
            del table
            pa.default_memory_pool().release_unused()  # mimalloc keeps freed pages otherwise
        flush_points()

    referenced = set(written) | _kept_parts(manifest_path)
    for p in sorted(sparse_dir.glob("part-*.parquet")) if sparse_dir.is_dir() else []:
        if f"{SPARSE_DIR}/{p.name}" not in referenced:
            remove_output(out, p)
    drop_stale_points(manifest_path)
    shutil.rmtree(staging, ignore_errors=True)  # a real folder (checked): links in it not followed
    return {
        "samples": writer.rows,
        "sequences": len(sequences),
        "splits": {k: counts[k] for k in sorted(counts, key=str)},
        "new_parts": len(written),
    }


#: Columns the merge decides (``frame_index`` too, from every row's sequence and frame).
_CHANGING = ("split", "sparse_parquet", "sparse_row", "points_parquet", "points_row")


def _kept_parts(manifest: Path, column: str = "sparse_parquet") -> set[str]:
    """The parts the manifest just written refers to (one column read back)."""
    import pyarrow.parquet as pq

    if column not in pq.read_schema(manifest).names:
        return set()
    return _values(pq.read_table(manifest, columns=[column]).column(column))


def _merge_points(
    out, contained, old, kept, new_ids, referenced_old, removed, frames_per_part, staged_row_of
):
    """The points parts (``--store-points``), as the sparse parts above: parts of an
    interrupted finalize dropped, old parts that lose rows rewritten with the rows kept (in
    ``old``'s rows ``kept``), the staged points of the frames ``new_ids`` written in new
    parts. Returns (part, row) by sample id of the rows written, and the clean-up to run
    after the manifest: delete the parts it no longer refers to."""

    folder = out / POINTS_DIR
    contained.check(folder, what="folder")
    staged = {fid: out / STAGING / f"{fid}{POINTS_SUFFIX}" for fid in new_ids}
    staged = {fid: p for fid, p in staged.items() if p.is_file()}
    where: dict[str, tuple[str, int]] = {}
    if not staged and not referenced_old and not folder.is_dir():
        return where, lambda manifest: None
    on_disk = sorted(folder.glob("part-*.parquet")) if folder.is_dir() else []
    for p in on_disk:
        if f"{POINTS_DIR}/{p.name}" not in referenced_old:
            remove_output(out, p)
    on_disk = [p for p in on_disk if p.exists()]
    next_part = 1 + max((i for p in on_disk if (i := _part_index(p.name)) is not None), default=-1)

    def new_part(table, ids) -> None:
        nonlocal next_part
        rel = f"{POINTS_DIR}/part-{next_part:05d}.parquet"
        next_part += 1
        write_points_part(contained.check(out / rel), table)
        for i, fid in enumerate(ids):
            where[fid] = (rel, i)

    for sub, ids in _kept_rows(out, old, kept, "points", removed, read_points_part):
        new_part(sub, ids)
    ids = sorted(staged)
    per_part = min(frames_per_part, POINTS_PER_PART)
    for start in range(0, len(ids), per_part):
        chunk = ids[start : start + per_part]
        clouds, sizes = [], []
        for fid in chunk:
            arr = np.load(staged[fid], allow_pickle=False)
            ring = arr[:, 3].astype(np.int16)
            clouds.append((arr[:, :3], None if (ring < 0).all() and len(ring) else ring))
            row = staged_row_of(fid)
            sizes.append((row.height, row.width))
        new_part(points_part_table(chunk, clouds, sizes), chunk)

    def clean(manifest: Path) -> None:
        referenced = _kept_parts(manifest, "points_parquet")
        for p in sorted(folder.glob("part-*.parquet")) if folder.is_dir() else []:
            if f"{POINTS_DIR}/{p.name}" not in referenced:
                remove_output(out, p)

    return where, clean


def _kept_rows(out: Path, old, kept: list[int], kind: str, parts: set[str], read):
    """For each part of ``parts`` (``kind``: ``sparse`` or ``points``) that rows ``kept`` of the
    earlier manifest ``old`` are in, in name order: the table of those rows read from the part
    (``read``) and their ids, checked against the manifest."""
    import pyarrow as pa

    ids = old.column("id").to_pylist()
    part = old.column(f"{kind}_parquet").to_pylist()
    row = old.column(f"{kind}_row").to_pylist()
    by_part: dict[str, list[int]] = defaultdict(list)
    for i in kept:
        if part[i] in parts:
            by_part[part[i]].append(i)
    for rel in sorted(by_part):
        at = by_part[rel]
        sub = read(resolve_in_dataset(out, rel)).take(pa.array([row[i] for i in at], pa.int64()))
        if sub.column("id").to_pylist() != [ids[i] for i in at]:
            raise FormatError(f"{rel}: rows do not match the manifest; run 'dataset verify'")
        yield sub, [ids[i] for i in at]


def _values(column) -> set[str]:
    """The distinct non-empty values of an Arrow string column."""
    return {v for v in column.unique().to_pylist() if v is not None}


def _counts(table) -> dict:
    splits = Counter(table.column("split").to_pylist())
    return {
        "samples": table.num_rows,
        "sequences": len(table.column("sequence").unique()),
        "splits": {k: splits[k] for k in sorted(splits, key=str)},
    }
