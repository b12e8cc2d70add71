"""``dataset verify``: whether a dataset is intact (every file present, decodable, of the
manifest's size and hash; Parquet parts and PNGs in agreement; the build's inputs unchanged)."""

from __future__ import annotations

import dataclasses
import math
import os
from array import array
from collections import Counter, defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import FormatError
from ...io.dataset import (
    MANIFEST_NAME,
    SPARSE_DIR,
    ManifestRow,
    brief_error,
    bytes_sha256,
    points_sha256,
    resolve_in_dataset,
)
from ...io.dataset_parts import part_rows, read_sparse_part
from ...io.depth_files import decode_confidence_bytes, decode_depth_bytes
from ...io.frame_index import key_hash
from ...io.manifest_stream import ManifestBatches
from ...validate import check_int_range
from .references import decode_rgb as _decode_rgb
from .references import verify_reference as _verify_reference
from .staging import STAGING

__all__ = ["VerifyReport", "verify_dataset"]


@dataclass(frozen=True)
class VerifyReport:
    """What ``dataset verify`` found: problems (the dataset is not intact) and warnings.

    ``str(report)`` is the text report, :meth:`to_dict` the JSON one.

    Attributes
    ----------
    dataset : str
    schema_version : int
    samples : int
    inputs_changed : int
        Samples whose input files changed since the build (each also a problem).
    problems : tuple of str
        One line each; empty: the dataset is intact.
    warnings : tuple of str
        Sequences in several splits, unreferenced part files, an unfinished build, inputs
        gone since the build.
    references : int
        Camera images referenced in place (``--store reference``).
    references_missing, references_changed : int
        Of them: not found (root unknown or moved, file gone), and changed since the build
        (size, modification time or hash differ: each also a problem).
    """

    dataset: str
    schema_version: int
    samples: int
    inputs_changed: int
    problems: tuple[str, ...]
    warnings: tuple[str, ...]
    references: int = 0
    references_missing: int = 0
    references_changed: int = 0

    @property
    def ok(self) -> bool:
        return not self.problems

    def to_dict(self) -> dict:
        """The report as JSON values (``dataset verify --json``)."""
        d = dataclasses.asdict(self)
        d.update(problems=list(self.problems), warnings=list(self.warnings))
        return d

    def format(self) -> str:
        """Warnings, then problems, one per line; or the line saying all is well."""
        lines = [f"warning: {w}" for w in self.warnings]
        lines += [f"problem: {p}" for p in self.problems]
        if self.ok:
            lines.append(f"{self.dataset}: {self.samples} sample(s) verified, no problem")
        return "\n".join(lines)

    __str__ = format


def _verify_row(
    root: Path, r: ManifestRow, check_hashes: bool, roots: Mapping[str, Path] | None = None
) -> tuple[list[str], np.ndarray | None, list[str], str | None]:
    """(problems, the sparse PNG decoded, warnings, reference status or None)."""
    problems = []
    fid = r.id
    shape = (r.height, r.width)

    def load(rel: str, col: str) -> bytes | None:
        try:
            p = resolve_in_dataset(root, rel, what=col)
        except FormatError as exc:
            problems.append(f"{fid}: {exc}")
            return None
        try:
            return p.read_bytes()
        except FileNotFoundError:
            problems.append(f"{fid}: {rel} is missing")
        except OSError as exc:
            problems.append(f"{fid}: {rel} cannot be read ({exc.strerror or exc})")
        return None

    def check(col: str, sha: str | None, decode) -> np.ndarray | None:
        rel = getattr(r, col)
        if rel is None:
            return None
        data = load(rel, col)
        if data is None:
            return None
        if check_hashes and bytes_sha256(data) != sha:
            problems.append(f"{fid}: {rel} has changed (sha256 differs from the manifest)")
        try:
            arr = decode(data, rel)
        except FormatError as exc:
            problems.append(f"{fid}: {rel} cannot be decoded ({brief_error(exc)})")
            return None
        if arr.shape[:2] != shape:
            problems.append(
                f"{fid}: {rel} is {arr.shape[1]}x{arr.shape[0]}, the manifest says "
                f"{shape[1]}x{shape[0]}"
            )
            return None
        return arr

    def depth_decode(data, rel):
        return decode_depth_bytes(data, Path(rel).suffix, source=rel)

    warnings, status = [], None
    if r.rgb_root is None:
        check("rgb_path", r.rgb_sha256, _decode_rgb)
    else:
        probs, warnings, status = _verify_reference(root, r, check_hashes, roots or {})
        problems.extend(probs)
    sparse_png = check("sparse_path", r.sparse_sha256, depth_decode)
    if sparse_png is not None and r.sparse_parquet is None:
        n = int(np.count_nonzero(sparse_png))
        if n != r.n_sparse:
            problems.append(
                f"{fid}: {r.sparse_path} holds {n} points, the manifest says {r.n_sparse}"
            )
    gt = check("gt_path", r.gt_sha256, depth_decode)
    if gt is not None and r.n_gt is not None and int(np.count_nonzero(gt)) != r.n_gt:
        problems.append(
            f"{fid}: {r.gt_path} holds {np.count_nonzero(gt)} points, the manifest says {r.n_gt}"
        )
    check(
        "confidence_path",
        r.confidence_sha256,
        lambda d, rel: decode_confidence_bytes(d, Path(rel).suffix, source=rel),
    )
    if r.sparse_path is None and r.sparse_parquet is None:
        problems.append(f"{fid}: no sparse depth (neither PNG nor Parquet)")
    if r.width > 0 and r.height > 0:
        expected = r.n_sparse / float(r.width * r.height)
        if not math.isclose(r.density, expected, rel_tol=1e-9, abs_tol=1e-12):
            problems.append(f"{fid}: density {r.density} does not match n_sparse / pixels")
    else:
        problems.append(f"{fid}: bad image size {r.width}x{r.height}")
    return problems, sparse_png, warnings, status


def _verify_part(
    root: Path, rel: str, rows: list[ManifestRow], pngs: dict, check_hashes: bool
) -> list[str]:
    problems = []
    try:
        table = read_sparse_part(resolve_in_dataset(root, rel, what="sparse_parquet"))
    except FormatError as exc:
        return [f"{rel}: {exc}"]
    entries = list(part_rows(table))
    for r in rows:
        fid = r.id
        i = r.sparse_row
        if i is None or not 0 <= i < len(entries):
            problems.append(f"{fid}: {rel} has no row {i}")
            continue
        pid, u, v, d, h, w = entries[i]
        if pid != fid:
            problems.append(f"{fid}: {rel} row {i} holds '{pid}'")
            continue
        if (h, w) != (r.height, r.width):
            problems.append(
                f"{fid}: {rel} row {i} is {w}x{h}, the manifest says {r.width}x{r.height}"
            )
            continue
        if u.size != r.n_sparse:
            problems.append(f"{fid}: {rel} holds {u.size} points, the manifest says {r.n_sparse}")
        if check_hashes and points_sha256(u, v, d) != r.sparse_points_sha256:
            problems.append(f"{fid}: {rel} row {i} has changed (points sha256 differs)")
        if u.size and (int(u.max()) >= w or int(v.max()) >= h):
            problems.append(f"{fid}: {rel} row {i} has points outside the image")
            continue
        if u.size and not np.all(np.isfinite(d) & (d > 0)):
            problems.append(f"{fid}: {rel} row {i} has non-positive or non-finite depths")
        flat = v.astype(np.int64) * w + u.astype(np.int64)
        if np.unique(flat).size != flat.size:
            problems.append(f"{fid}: {rel} row {i} has two points in one pixel")
            continue
        png = pngs.get(fid)
        if png is not None:
            at, counts = png  # the PNG's valid pixels (flat, ascending) and depth x 256
            disagree = not np.array_equal(at, np.sort(flat))
            if not disagree and flat.size:
                # The PNG holds round(depth * 256) / 256, clipped to [1, 65535] / 256.
                stored = counts[np.searchsorted(at, flat)] / 256.0
                err = np.abs(stored - np.clip(d.astype(np.float64), 1 / 256, 65535 / 256))
                disagree = float(err.max()) > 1 / 512 + 1e-6
            if disagree:
                problems.append(f"{fid}: {r.sparse_path} and {rel} disagree")
    return problems


def _valid_pixels(png: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A decoded KITTI depth PNG (metres, k / 256) as its valid pixels: flat indices (int32,
    ascending) and the PNG's uint16 counts k, 6 bytes per valid pixel instead of 4 per pixel."""
    flat = png.reshape(-1)
    at = np.flatnonzero(flat)
    counts = np.rint(flat[at].astype(np.float64) * 256.0).astype(np.uint16)
    return at.astype(np.int32 if flat.size < 2**31 else np.int64), counts


#: Manifest rows read and verified per chunk (memory: one chunk's rows at a time).
_VERIFY_CHUNK = 1024


def verify_dataset(
    path: str | os.PathLike,
    *,
    check_hashes: bool = True,
    threads: int = 1,
    roots: Mapping[str, str | os.PathLike] | None = None,
) -> VerifyReport:
    """Check a dataset: every file present, decodable, of the manifest's size, hash matching.

    Parameters
    ----------
    path : path-like
        Dataset folder.
    check_hashes : bool
        Compare SHA-256 of every file (and of every frame's sparse points).
    threads : int
        Threads reading and decoding files (hashing and decoding release the GIL).
    roots : mapping of str -> path-like, optional
        Where the roots of referenced images are now (default: the paths the build
        recorded); a referenced image missing or changed since the build is a problem.

    Returns
    -------
    VerifyReport
        Its ``problems`` empty when the dataset is intact.

    Raises
    ------
    FormatError
        A manifest that cannot be read or that :func:`~sparsetools.io.dataset.read_manifest`
        would refuse. The manifest is read a chunk of rows at a time
        (:class:`~sparsetools.io.manifest_stream.ManifestBatches`): a refusal found in a later chunk,
        or duplicate sample ids (known only at the end), raise after the earlier rows' files
        were checked.
    """
    from concurrent.futures import ThreadPoolExecutor

    from ...io.dataset_reader import sample_roots

    threads = check_int_range(threads, "threads", low=1)
    root = Path(path)
    manifest = ManifestBatches(root / MANIFEST_NAME, batch_rows=_VERIFY_CHUNK)
    info = manifest.info
    where = sample_roots(info, roots)
    recorded = sample_roots(info, None)
    problems: list[str] = []
    warnings: list[str] = []
    # The manifest is read in chunks and each row's result folded at once: what is kept per
    # sample is its id and sequence, and only for samples with a Parquet part the row and the
    # valid pixels of its PNG (to compare the two), not every row object and decoded map.
    ids = array("q")  # key hashes of the samples, for the journal (8 bytes each)
    pngs: dict = {}
    ref_status: Counter = Counter()
    # a part is compared as soon as its last sample is seen (a build writes a part's samples
    # together): only the parts in progress hold rows and valid pixels
    remaining = _rows_per_part(manifest)
    by_part: dict[str, list[ManifestRow]] = defaultdict(list)
    part_problems: dict[str, list[str]] = {}
    seq_splits: dict[str, set] = defaultdict(set)
    referenced: set[str] = set()  # reference-stored images: checked where they are now

    def one(r):
        return _verify_row(root, r, check_hashes, where)

    def part_done(rel: str) -> None:
        rows = by_part.pop(rel)
        own = {r.id: pngs.pop(r.id) for r in rows if r.id in pngs}
        part_problems[rel] = _verify_part(root, rel, rows, own, check_hashes)

    pool = ThreadPoolExecutor(max_workers=threads) if threads > 1 else None
    try:
        for chunk in manifest:
            rows = ManifestRow.from_table(chunk)
            results = pool.map(one, rows) if pool is not None else map(one, rows)
            for r, (probs, png, warns, status) in zip(rows, results, strict=True):
                problems.extend(probs)
                warnings.extend(warns)
                if status is not None:
                    ref_status[status] += 1
                ids.append(key_hash(r.id))
                seq_splits[r.sequence].add(r.split)
                if r.sparse_parquet is not None:
                    rel = r.sparse_parquet
                    by_part[rel].append(r)
                    if png is not None:
                        pngs[r.id] = _valid_pixels(png)
                    remaining[rel] -= 1
                    if remaining[rel] == 0:
                        part_done(rel)
                if r.rgb_root is not None and r.rgb_root in recorded:
                    referenced.add(os.path.realpath(Path(recorded[r.rgb_root], r.rgb_path)))
    finally:
        if pool is not None:
            pool.shutdown()
    for rel in list(by_part):
        part_done(rel)
    for rel in sorted(part_problems):
        problems.extend(part_problems[rel])
    for seq in sorted(seq_splits):
        if len(seq_splits[seq]) > 1:
            warnings.append(
                f"sequence '{seq}' is in several splits: {', '.join(sorted(map(str, seq_splits[seq])))}"
            )
    sparse_dir = root / SPARSE_DIR
    if sparse_dir.is_dir():
        for p in sorted(sparse_dir.glob("part-*.parquet")):
            if f"{SPARSE_DIR}/{p.name}" not in part_problems:
                warnings.append(f"{SPARSE_DIR}/{p.name} is not referenced by the manifest")
    if (root / STAGING).is_dir():
        warnings.append(
            f"{STAGING}/ holds frames of an unfinished build (rerun the build to add them)"
        )
    changed, moved = _changed_inputs(root, ids, skip=referenced)
    for sid, path in changed:
        problems.append(
            f"{sid}: input {path} changed since the build (rerun 'dataset build' to update)"
        )
    if moved:
        warnings.append(
            f"{len(moved)} input file(s) of the build are gone (moved or deleted), e.g. "
            f"{moved[0][1]} of {moved[0][0]}: the dataset itself is unaffected"
        )
    return VerifyReport(
        dataset=str(root),
        schema_version=info["schema_version"],
        samples=manifest.num_rows,
        inputs_changed=len(changed),
        problems=tuple(problems),
        warnings=tuple(warnings),
        references=sum(ref_status.values()),
        references_missing=ref_status["missing"],
        references_changed=ref_status["changed"],
    )


def _rows_per_part(manifest: ManifestBatches) -> Counter:
    """Manifest rows per ``sparse_parquet`` part (rows without one are not counted), from
    that column alone, a row group at a time. A column that cannot be read counts nothing
    (every part is then compared at the end): reading the manifest refuses it."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    counts = Counter()
    try:
        with pq.ParquetFile(manifest.path) as pf:
            if "sparse_parquet" not in pf.schema_arrow.names:
                return counts
            for batch in pf.iter_batches(
                batch_size=manifest.batch_rows, columns=["sparse_parquet"]
            ):
                column = batch.column(0).cast(pa.string())
                for item in pc.value_counts(column).to_pylist():
                    if item["values"] is not None:
                        counts[item["values"]] += item["counts"]
    except (pa.ArrowException, OSError):
        return Counter()
    return counts


def _changed_inputs(root: Path, ids, skip: set[str] = frozenset()) -> tuple[list, list]:
    """(sample, input) pairs whose input file differs from the build's record, and those
    whose input is gone (inputs at the paths ``skip`` left out), by sample. A dataset without
    a record (older sparsetools) reports none.

    ``ids`` holds the samples' key hashes (:func:`~sparsetools.io.frame_index.key_hash`). The
    journal is read through its index (the last valid line of a key wins; 16 bytes per
    sample); inputs shared by many samples (a calibration) are looked at once (a bounded
    cache)."""
    from functools import lru_cache

    from ...io.frame_index import FrameIndex
    from ...io.provenance import file_identity

    changed, gone = [], []
    try:
        index = FrameIndex(root)
        try:
            identity = lru_cache(maxsize=4096)(file_identity)
            for rec in index.records_in(np.frombuffer(ids, dtype=np.int64)):
                for old in rec.inputs:
                    if old.path in skip:
                        continue
                    now = identity(old.path)
                    if now.size < 0:
                        gone.append((rec.key, old.path))
                    elif not old.same_file(now):
                        changed.append((rec.key, old.path))
        finally:
            index.close()
    except (FormatError, OSError):
        return [], []
    # by sample, as before (a stable sort: a sample's inputs keep their order)
    changed.sort(key=lambda pair: pair[0])
    gone.sort(key=lambda pair: pair[0])
    return changed, gone
