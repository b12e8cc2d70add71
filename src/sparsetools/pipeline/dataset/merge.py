"""The last step of ``dataset build``: merge the staged frames into the dataset.

The existing manifest and every staging record (:mod:`.staging`) become one manifest: splits
assigned (given per frame, or by sequence: :func:`.splits.assign_splits`), the points written
as new ``sparse/part-*.parquet`` files, then the manifest atomically, then the parts no longer
referenced and the staging folder deleted. Interrupted anywhere, the next build redoes it.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import shutil
from collections import Counter, defaultdict
from collections.abc import Mapping
from pathlib import Path

from ...errors import FormatError
from ...io.atomic import TMP_PREFIX
from ...io.containment import ContainedPaths, remove_output
from ...io.dataset import (
    MANIFEST_NAME,
    POINTS_DIR,
    SPARSE_DIR,
    ManifestRow,
    read_manifest,
    resolve_in_dataset,
    write_manifest,
)
from ...io.dataset_parts import (
    points_part_table,
    read_points_part,
    read_sparse_part,
    write_points_part,
    write_sparse_part,
)
from ...io.points_table import sparse_part_table
from .splits import assign_splits
from .staging import POINTS_SUFFIX, STAGING, read_staged

__all__ = ["merge_staged"]

log = logging.getLogger(__name__)

#: Samples per points part at most (about 0.5 MB each for a KITTI scan's image points).
POINTS_PER_PART = 100
_PART_RE = re.compile(r"^part-(\d{5,})\.parquet$")


# -- merging the staged frames -------------------------------------------------------------------------
def _part_index(name: str) -> int | None:
    m = _PART_RE.match(name)
    return int(m.group(1)) if m else None


def _frame_indices(rows: list[ManifestRow]) -> dict[str, int]:
    """``frame_index`` by sample id: each frame's rank in its sequence, frames in natural order
    (numbers compared as numbers: ``2`` before ``10``); the cameras of one frame share it."""
    by_seq: dict[str, set[str]] = defaultdict(set)
    for r in rows:
        by_seq[r.sequence].add(r.frame)
    rank = {
        (seq, frame): i
        for seq, frames in by_seq.items()
        for i, frame in enumerate(sorted(frames, key=_natural))
    }
    return {r.id: rank[r.sequence, r.frame] for r in rows}


def _natural(text: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", text))


def merge_staged(
    out: Path, *, fractions, seed, assignment, info, frames_per_part, only: set[str] | None = None
) -> dict:
    """Merge staged frames into the manifest and parts (see the module docstring).

    ``assignment``: sample id -> split (split files, the tree), else splits by sequence from
    ``fractions``. ``only``: keep only these sample ids (``--overwrite``: the dataset holds
    this run only).
    """
    import pyarrow as pa

    # Everything written or deleted below is inside the dataset and reached through no link
    # (a ds/sparse that links to another folder is refused, its parts are never touched).
    contained = ContainedPaths(out)
    for folder in (out / STAGING, out / SPARSE_DIR):
        contained.check(folder, what="folder")
    contained.check(out / MANIFEST_NAME)
    staging = out / STAGING
    staged_files = (
        sorted(p for p in staging.rglob("*.rec") if not p.name.startswith(TMP_PREFIX))
        if staging.is_dir()
        else []
    )
    manifest_path = out / MANIFEST_NAME
    old_rows: list[ManifestRow] = []
    old_info: dict = {}
    if manifest_path.is_file():
        table, old_info = read_manifest(manifest_path)
        old_rows = ManifestRow.from_table(table)
    dropped = [] if only is None else [r for r in old_rows if r.id not in only]
    if not staged_files and not dropped:
        return _counts(old_rows)

    new_rows: list[ManifestRow] = []
    # where each frame's points are: read again a part at a time (a build of a million frames
    # never holds every frame's points)
    points_of: dict[str, Path] = {}
    for p in staged_files:
        row, points = read_staged(p)
        new_rows.append(row)
        if points is not None:
            points_of[row.id] = p
        del points
    gone = {r.id for r in new_rows} | {r.id for r in dropped}
    kept = [r for r in old_rows if r.id not in gone]
    # What changes in a row (its split, its part and row there, its frame_index), by id.
    changes: dict[str, dict] = defaultdict(dict)

    if assignment is not None:
        unknown = [r.id for r in new_rows if r.id not in assignment]
        if unknown:
            log.warning(
                "%d staged frame(s) are not in the split files and are left out: %s",
                len(unknown),
                ", ".join(unknown[:5]),
            )
        new_rows = [r for r in new_rows if r.id in assignment]
        for r in new_rows:
            changes[r.id]["split"] = assignment[r.id]
    else:
        pinned: dict[str, str] = {}
        for r in sorted(kept, key=lambda r: r.id):
            if r.split is not None:
                pinned.setdefault(r.sequence, r.split)
        seq_split = assign_splits(
            {r.sequence for r in new_rows}, fractions, seed=seed, pinned=pinned
        )
        for r in new_rows:
            changes[r.id]["split"] = seq_split[r.sequence]

    sparse_dir = out / SPARSE_DIR
    on_disk = sorted(sparse_dir.glob("part-*.parquet")) if sparse_dir.is_dir() else []
    # Parts no manifest row refers to were written by a finalize that was interrupted before
    # its manifest: drop them, so the resumed build numbers its parts as an uninterrupted one.
    referenced_old = {r.sparse_parquet for r in old_rows if r.sparse_parquet is not None}
    for p in on_disk:
        if f"{SPARSE_DIR}/{p.name}" not in referenced_old:
            remove_output(out, p)
    on_disk = [p for p in on_disk if p.exists()]
    next_part = 1 + max((i for p in on_disk if (i := _part_index(p.name)) is not None), default=-1)
    written = []

    def new_part(table: pa.Table, ids: list[str]) -> None:
        nonlocal next_part
        rel = f"{SPARSE_DIR}/part-{next_part:05d}.parquet"
        next_part += 1
        write_sparse_part(contained.check(out / rel), table)
        written.append(rel)
        for i, fid in enumerate(ids):
            changes[fid].update(sparse_parquet=rel, sparse_row=i)

    # Old parts that lose rows (overwritten frames) are rewritten with the rows kept.
    kept_by_part: dict[str, list[ManifestRow]] = defaultdict(list)
    for r in kept:
        if r.sparse_parquet is not None:
            kept_by_part[r.sparse_parquet].append(r)
    removed_parts = {
        r.sparse_parquet for r in old_rows if r.id in gone and r.sparse_parquet is not None
    }
    for rel in sorted(removed_parts & set(kept_by_part)):
        rows = sorted(kept_by_part[rel], key=lambda r: r.id)
        table = read_sparse_part(resolve_in_dataset(out, rel))
        sub = table.take(pa.array([r.sparse_row for r in rows], type=pa.int64()))
        if sub.column("id").to_pylist() != [r.id for r in rows]:
            raise FormatError(f"{rel}: rows do not match the manifest; run 'dataset verify'")
        new_part(sub, [r.id for r in rows])

    size_of = {r.id: (r.height, r.width) for r in new_rows}
    with_points = sorted(fid for fid in points_of if fid in size_of)
    for start in range(0, len(with_points), frames_per_part):
        ids = with_points[start : start + frames_per_part]
        points = [read_staged(points_of[i])[1] for i in ids]
        new_part(sparse_part_table(ids, points, [size_of[i] for i in ids]), ids)
        del points

    drop_stale_points = _merge_points(
        out, contained, old_rows, kept, new_rows, gone, changes, frames_per_part
    )
    rows = sorted(kept + new_rows, key=lambda r: r.id)
    for fid, i in _frame_indices(rows).items():
        changes[fid]["frame_index"] = i
    rows = [_changed(r, changes.get(r.id)) for r in rows]
    merged_info = {**old_info, **info}
    merged_info.pop("schema_version", None)
    # Roots of referenced images (--store reference): the newest path of each name that a
    # row still names.
    roots = {**old_info.get("roots", {}), **info.get("roots", {})}
    used = {r.rgb_root for r in rows if r.rgb_root is not None}
    merged_info.pop("roots", None)
    if used:
        merged_info["roots"] = {k: v for k, v in sorted(roots.items()) if k in used}
    write_manifest(manifest_path, ManifestRow.to_table(rows), info=merged_info)

    referenced = {r.sparse_parquet for r in rows if r.sparse_parquet is not None}
    for p in sorted(sparse_dir.glob("part-*.parquet")) if sparse_dir.is_dir() else []:
        if f"{SPARSE_DIR}/{p.name}" not in referenced:
            remove_output(out, p)
    drop_stale_points(rows)
    shutil.rmtree(staging, ignore_errors=True)  # a real folder (checked): links in it not followed
    result = _counts(rows)
    result["new_parts"] = len(written)
    return result


def _merge_points(out, contained, old_rows, kept, new_rows, gone, changes, frames_per_part):
    """The points parts (``--store-points``), as the sparse parts above: parts of an
    interrupted finalize dropped, old parts that lose rows rewritten with the rows kept, the
    staged points of the new frames written in new parts (``points_parquet`` /
    ``points_row`` in ``changes``). Returns the clean-up to run after the manifest: delete
    the parts no row refers to."""
    import numpy as np
    import pyarrow as pa

    folder = out / POINTS_DIR
    contained.check(folder, what="folder")
    staged = {r.id: out / STAGING / f"{r.id}{POINTS_SUFFIX}" for r in new_rows}
    staged = {fid: p for fid, p in staged.items() if p.is_file()}
    referenced_old = {r.points_parquet for r in old_rows if r.points_parquet is not None}
    if not staged and not referenced_old and not folder.is_dir():
        return lambda rows: None
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
            changes[fid].update(points_parquet=rel, points_row=i)

    kept_by_part = defaultdict(list)
    for r in kept:
        if r.points_parquet is not None:
            kept_by_part[r.points_parquet].append(r)
    removed = {r.points_parquet for r in old_rows if r.id in gone and r.points_parquet}
    for rel in sorted(removed & set(kept_by_part)):
        rows = sorted(kept_by_part[rel], key=lambda r: r.id)
        table = read_points_part(resolve_in_dataset(out, rel))
        sub = table.take(pa.array([r.points_row for r in rows], type=pa.int64()))
        if sub.column("id").to_pylist() != [r.id for r in rows]:
            raise FormatError(f"{rel}: rows do not match the manifest; run 'dataset verify'")
        new_part(sub, [r.id for r in rows])
    size_of = {r.id: (r.height, r.width) for r in new_rows}
    ids = sorted(staged)
    per_part = min(frames_per_part, POINTS_PER_PART)
    for start in range(0, len(ids), per_part):
        chunk = ids[start : start + per_part]
        clouds = []
        for fid in chunk:
            arr = np.load(staged[fid], allow_pickle=False)
            ring = arr[:, 3].astype(np.int16)
            clouds.append((arr[:, :3], None if (ring < 0).all() and len(ring) else ring))
        new_part(points_part_table(chunk, clouds, [size_of[i] for i in chunk]), chunk)

    def clean(rows) -> None:
        referenced = {r.points_parquet for r in rows if r.points_parquet is not None}
        for p in sorted(folder.glob("part-*.parquet")) if folder.is_dir() else []:
            if f"{POINTS_DIR}/{p.name}" not in referenced:
                remove_output(out, p)

    return clean


def _changed(row: ManifestRow, changes: Mapping | None) -> ManifestRow:
    """``row`` with ``changes`` (fields that hold other values now), itself when none does."""
    if changes and any(getattr(row, k) != v for k, v in changes.items()):
        return dataclasses.replace(row, **changes)
    return row


def _counts(rows: list[ManifestRow]) -> dict:
    splits = Counter(r.split for r in rows)
    return {
        "samples": len(rows),
        "sequences": len({r.sequence for r in rows}),
        "splits": {k: splits[k] for k in sorted(splits, key=str)},
    }
