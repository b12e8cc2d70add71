"""``dataset info`` and ``dataset verify``: what a dataset holds, and whether it is intact."""

from __future__ import annotations

import math
import os
import statistics
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from ...errors import FormatError
from ...io.dataset import (
    MANIFEST_NAME,
    SPARSE_DIR,
    _brief,
    bytes_sha256,
    decode_confidence_bytes,
    decode_depth_bytes,
    part_rows,
    points_sha256,
    read_manifest,
    read_sparse_part,
    resolve_in_dataset,
)
from .staging import STAGING

__all__ = ["dataset_info", "verify_dataset"]


# -- info ----------------------------------------------------------------------------------------
def _describe(values: list[float]) -> dict:
    if not values:
        return {"min": None, "median": None, "mean": None, "max": None}
    return {
        "min": min(values),
        "median": statistics.median(values),
        "mean": statistics.fmean(values),
        "max": max(values),
    }


def dataset_info(path: str | os.PathLike) -> dict:
    """Counts per split, image sizes, density statistics, file sizes and the schema version."""
    root = Path(path)
    table, info = read_manifest(root / MANIFEST_NAME)
    rows = table.to_pylist()
    per_split: dict[str, dict] = {}
    for name in sorted({r["split"] for r in rows}, key=str):
        sub = [r for r in rows if r["split"] == name]
        per_split[str(name)] = {
            "samples": len(sub),
            "sequences": len({r["sequence"] for r in sub}),
            "with_gt": sum(r["gt_path"] is not None for r in sub),
        }
    sizes = Counter(f"{r['width']}x{r['height']}" for r in rows)
    bytes_by_kind: dict[str, int] = defaultdict(int)
    missing = 0
    for r in rows:
        for kind, col in (
            ("rgb", "rgb_path"),
            ("sparse_png", "sparse_path"),
            ("gt", "gt_path"),
            ("confidence", "confidence_path"),
        ):
            if r[col] is None:
                continue
            try:
                bytes_by_kind[kind] += resolve_in_dataset(root, r[col]).stat().st_size
            except OSError:
                missing += 1
    for rel in sorted({r["sparse_parquet"] for r in rows if r["sparse_parquet"] is not None}):
        try:
            bytes_by_kind["sparse_parquet"] += resolve_in_dataset(root, rel).stat().st_size
        except OSError:
            missing += 1
    bytes_by_kind["manifest"] = (root / MANIFEST_NAME).stat().st_size
    density = [100.0 * r["density"] for r in rows]
    return {
        "dataset": str(root),
        "schema_version": info.get("schema_version"),
        "created_by": info.get("created_by"),
        "samples": len(rows),
        "sequences": len({r["sequence"] for r in rows}),
        "splits": per_split,
        "image_sizes": dict(sizes.most_common()),
        "sources": dict(Counter(r["source"] for r in rows).most_common()),
        "with_gt": sum(r["gt_path"] is not None for r in rows),
        "with_confidence": sum(r["confidence_path"] is not None for r in rows),
        "with_intrinsics": sum(r["fx"] is not None for r in rows),
        "n_sparse": _describe([float(r["n_sparse"]) for r in rows]),
        "density_percent": _describe(density),
        "bytes": dict(bytes_by_kind),
        "total_bytes": int(sum(bytes_by_kind.values())),
        "missing_files": missing,
        "split_method": info.get("split"),
    }


# -- verify ----------------------------------------------------------------------------------------
def _verify_row(root: Path, r: dict, check_hashes: bool) -> tuple[list[str], np.ndarray | None]:
    problems = []
    fid = r["id"]
    shape = (r["height"], r["width"])
    sparse_png = None

    def load(col: str) -> bytes | None:
        try:
            p = resolve_in_dataset(root, r[col], what=col)
        except FormatError as exc:
            problems.append(f"{fid}: {exc}")
            return None
        try:
            return p.read_bytes()
        except FileNotFoundError:
            problems.append(f"{fid}: {r[col]} is missing")
        except OSError as exc:
            problems.append(f"{fid}: {r[col]} cannot be read ({exc.strerror or exc})")
        return None

    def check(col: str, sha_col: str, decode) -> np.ndarray | None:
        if r[col] is None:
            return None
        data = load(col)
        if data is None:
            return None
        if check_hashes and bytes_sha256(data) != r[sha_col]:
            problems.append(f"{fid}: {r[col]} has changed (sha256 differs from the manifest)")
        try:
            arr = decode(data, r[col])
        except FormatError as exc:
            problems.append(f"{fid}: {r[col]} cannot be decoded ({_brief(exc)})")
            return None
        if arr.shape[:2] != shape:
            problems.append(
                f"{fid}: {r[col]} is {arr.shape[1]}x{arr.shape[0]}, the manifest says "
                f"{shape[1]}x{shape[0]}"
            )
            return None
        return arr

    def rgb_decode(data, rel):
        from ...io.image import decode_image_bytes

        img = decode_image_bytes(data, source=rel)
        if img.dtype != np.uint8:
            raise FormatError("not an 8-bit image")
        return img

    check("rgb_path", "rgb_sha256", rgb_decode)
    sparse_png = check(
        "sparse_path",
        "sparse_sha256",
        lambda d, rel: decode_depth_bytes(d, Path(rel).suffix, source=rel),
    )
    if sparse_png is not None and r["sparse_parquet"] is None:
        n = int(np.count_nonzero(sparse_png))
        if n != r["n_sparse"]:
            problems.append(
                f"{fid}: {r['sparse_path']} holds {n} points, the manifest says {r['n_sparse']}"
            )
    gt = check(
        "gt_path", "gt_sha256", lambda d, rel: decode_depth_bytes(d, Path(rel).suffix, source=rel)
    )
    if gt is not None and r["n_gt"] is not None and int(np.count_nonzero(gt)) != r["n_gt"]:
        problems.append(
            f"{fid}: {r['gt_path']} holds {np.count_nonzero(gt)} points, the manifest says {r['n_gt']}"
        )
    check(
        "confidence_path",
        "confidence_sha256",
        lambda d, rel: decode_confidence_bytes(d, Path(rel).suffix, source=rel),
    )
    if r["sparse_path"] is None and r["sparse_parquet"] is None:
        problems.append(f"{fid}: no sparse depth (neither PNG nor Parquet)")
    if r["width"] > 0 and r["height"] > 0:
        expected = r["n_sparse"] / float(r["width"] * r["height"])
        if not math.isclose(r["density"], expected, rel_tol=1e-9, abs_tol=1e-12):
            problems.append(f"{fid}: density {r['density']} does not match n_sparse / pixels")
    else:
        problems.append(f"{fid}: bad image size {r['width']}x{r['height']}")
    return problems, sparse_png


def _verify_part(
    root: Path, rel: str, rows: list[dict], pngs: dict, check_hashes: bool
) -> list[str]:
    problems = []
    try:
        table = read_sparse_part(resolve_in_dataset(root, rel, what="sparse_parquet"))
    except FormatError as exc:
        return [f"{rel}: {exc}"]
    entries = list(part_rows(table))
    for r in rows:
        fid = r["id"]
        i = r["sparse_row"]
        if i is None or not 0 <= i < len(entries):
            problems.append(f"{fid}: {rel} has no row {i}")
            continue
        pid, u, v, d, h, w = entries[i]
        if pid != fid:
            problems.append(f"{fid}: {rel} row {i} holds '{pid}'")
            continue
        if (h, w) != (r["height"], r["width"]):
            problems.append(
                f"{fid}: {rel} row {i} is {w}x{h}, the manifest says {r['width']}x{r['height']}"
            )
            continue
        if u.size != r["n_sparse"]:
            problems.append(
                f"{fid}: {rel} holds {u.size} points, the manifest says {r['n_sparse']}"
            )
        if check_hashes and points_sha256(u, v, d) != r["sparse_points_sha256"]:
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
            ok_mask = np.array_equal(np.flatnonzero(png), np.sort(flat))
            # The PNG holds round(depth * 256) / 256, clipped to [1, 65535] / 256.
            stored = png[v.astype(np.intp), u.astype(np.intp)].astype(np.float64)
            err = np.abs(stored - np.clip(d.astype(np.float64), 1 / 256, 65535 / 256))
            if not ok_mask or (err.size and float(err.max()) > 1 / 512 + 1e-6):
                problems.append(f"{fid}: {r['sparse_path']} and {rel} disagree")
    return problems


def verify_dataset(path: str | os.PathLike, *, check_hashes: bool = True, workers: int = 1) -> dict:
    """Check a dataset: every file present, decodable, of the manifest's size, hash matching.

    Parameters
    ----------
    path : path-like
        Dataset folder.
    check_hashes : bool
        Compare SHA-256 of every file (and of every frame's sparse points).
    workers : int
        Threads reading and decoding files (hashing and decoding release the GIL).

    Returns
    -------
    dict
        ``samples``, ``problems`` (list of one-line messages; empty = valid),
        ``warnings`` (sequences in several splits, unreferenced part files).
        A manifest that cannot be read at all raises :class:`FormatError`.
    """
    from concurrent.futures import ThreadPoolExecutor

    root = Path(path)
    table, info = read_manifest(root / MANIFEST_NAME)
    rows = table.to_pylist()
    problems: list[str] = []
    warnings: list[str] = []

    def one(r):
        return _verify_row(root, r, check_hashes)

    if workers > 1:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            results = list(pool.map(one, rows))
    else:
        results = [one(r) for r in rows]
    pngs = {}
    for r, (probs, png) in zip(rows, results, strict=True):
        problems.extend(probs)
        if png is not None:
            pngs[r["id"]] = png
    by_part: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        if r["sparse_parquet"] is not None:
            by_part[r["sparse_parquet"]].append(r)
    for rel in sorted(by_part):
        problems.extend(_verify_part(root, rel, by_part[rel], pngs, check_hashes))
    seq_splits: dict[str, set] = defaultdict(set)
    for r in rows:
        seq_splits[r["sequence"]].add(r["split"])
    for seq in sorted(seq_splits):
        if len(seq_splits[seq]) > 1:
            warnings.append(
                f"sequence '{seq}' is in several splits: {', '.join(sorted(map(str, seq_splits[seq])))}"
            )
    sparse_dir = root / SPARSE_DIR
    if sparse_dir.is_dir():
        for p in sorted(sparse_dir.glob("part-*.parquet")):
            if f"{SPARSE_DIR}/{p.name}" not in by_part:
                warnings.append(f"{SPARSE_DIR}/{p.name} is not referenced by the manifest")
    if (root / STAGING).is_dir():
        warnings.append(
            f"{STAGING}/ holds frames of an unfinished build (rerun the build to add them)"
        )
    changed, moved = _changed_inputs(root, {r["id"] for r in rows})
    for sid, path in changed:
        problems.append(
            f"{sid}: input {path} changed since the build (rerun 'dataset build' to update)"
        )
    if moved:
        warnings.append(
            f"{len(moved)} input file(s) of the build are gone (moved or deleted), e.g. "
            f"{moved[0][1]} of {moved[0][0]}: the dataset itself is unaffected"
        )
    return {
        "dataset": str(root),
        "schema_version": info["schema_version"],
        "samples": len(rows),
        "inputs_changed": len(changed),
        "problems": problems,
        "warnings": warnings,
    }


def _changed_inputs(root: Path, ids: set[str]) -> tuple[list, list]:
    """(sample, input) pairs whose input file differs from the build's record, and those
    whose input is gone. A dataset without a record (older sparsetools) reports none."""
    from ...io.provenance import file_identity, read_frame_records

    changed, gone = [], []
    try:
        records = read_frame_records(root)
    except FormatError:
        return changed, gone
    cache: dict[str, object] = {}
    for sid in sorted(records):
        if sid not in ids:
            continue
        for old in records[sid].inputs:
            now = cache.get(old.path)
            if now is None:
                now = cache[old.path] = file_identity(old.path)
            if now.size < 0:
                gone.append((sid, old.path))
            elif not old.same_file(now):
                changed.append((sid, old.path))
    return changed, gone
