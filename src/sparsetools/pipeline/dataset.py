"""``dataset build / info / verify`` and ``stats``: the batch jobs behind the commands.

Build in three stages, so that an interrupted run resumes and appending works:

1. **Plan** (main process): index the input folders, match files by key (relative path
   without suffix, falling back to a unique file stem), derive each frame's sequence,
   drop frames already in the dataset (unless ``overwrite``).
2. **Frames** (:func:`build_frame`, one :class:`FrameTask` each, any executor): copy or
   hard-link the files into the dataset, decode them to check sizes, hash them, and write a
   *staging record* ``DATASET/.staging/<id>.rec`` (manifest row + sparse
   points) last. All writes are atomic, so a frame whose record exists is complete.
3. **Finalize** (main process): merge the existing manifest with every staged record,
   assign splits (by sequence), write the new ``sparse/part-*.parquet`` files, then the
   manifest atomically, then delete parts no longer referenced and the staging folder.

Splits are assigned to whole sequences. With fractions (``--split``): sequences are ordered
by SHA-256 of ``"<seed>/<sequence>"`` and the first ones filled into the splits in order
until each split holds its quota (largest-remainder rounding of ``fraction * sequences``;
every split with a non-zero fraction gets at least one sequence when there are enough).
Sequences already in the dataset keep their split when frames are appended; new sequences
fill the remaining quotas. With split files (``--split-file``), see :func:`read_split_file`.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import statistics
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import FormatError, OutputError, ParameterError
from ..io.atomic import TMP_PREFIX, atomic_path
from ..io.dataset import (
    MANIFEST_NAME,
    MANIFEST_SCHEMA,
    MAX_SIDE,
    PART_SCHEMA,
    SPARSE_DIR,
    _brief,
    bytes_sha256,
    check_relative_path,
    decode_confidence_bytes,
    decode_depth_bytes,
    depth_to_points,
    part_rows,
    points_sha256,
    read_manifest,
    read_sparse_part,
    resolve_in_dataset,
    write_manifest,
    write_sparse_part,
)
from .core import FrameTask, check_output_dir, run_frames

__all__ = [
    "DEFAULT_SPLIT",
    "assign_splits",
    "build_dataset",
    "build_frame",
    "dataset_info",
    "depth_stats_files",
    "match_split_lines",
    "parse_split_fractions",
    "read_split_file",
    "sequence_resolver",
    "verify_dataset",
]

log = logging.getLogger(__name__)

DEFAULT_SPLIT = {"train": 0.8, "val": 0.1, "test": 0.1}
RGB_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".png", ".npy")
CALIB_SUFFIXES = (".txt", ".json")
STAGING = ".staging"
SPARSE_FORMATS = ("png", "parquet", "both")
#: jbf-expand names its confidence maps ``<stem>_conf.png``; they match frame ``<stem>``.
CONF_SUFFIX = "_conf"
_PART_RE = re.compile(r"^part-(\d{5,})\.parquet$")


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
                        raise ParameterError(f"split names must be unique and non-empty: {text!r}")
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
            raise ParameterError(f"split fractions must be numbers, got {text!r}") from None
    if not fractions:
        raise ParameterError("no split fractions given")
    for name, f in fractions.items():
        check_relative_path(name, what="split name")
        if not math.isfinite(f) or f < 0:
            raise ParameterError(f"split fraction of '{name}' must be >= 0, got {f}")
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
    raise ParameterError(f"--sequence-from must be 'parent' or 'regex:PATTERN', got {spec!r}")


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


def _split_file_assignments(
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
    import hashlib

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


# -- input indexing ----------------------------------------------------------------------------------
def _index_inputs(
    path: str | os.PathLike, suffixes: tuple[str, ...], *, what: str, strip: str | None = None
) -> dict[str, Path]:
    """key (relative posix path without suffix) -> file, for files with ``suffixes``."""
    root = Path(path)
    if not root.exists():
        raise ParameterError(f"--{what}: {root} does not exist")
    if root.is_file():
        if root.suffix.lower() not in suffixes:
            raise ParameterError(f"--{what}: {root} is not a {'/'.join(suffixes)} file")
        files = [(root.stem, root)]
    else:
        files = []
        for dirpath, dirnames, filenames in os.walk(root):
            dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
            rel_dir = Path(dirpath).relative_to(root).as_posix()
            for name in sorted(filenames):
                if name.startswith(".") or name.startswith(TMP_PREFIX):
                    continue
                p = Path(name)
                if p.suffix.lower() not in suffixes:
                    continue
                stem = p.name[: -len(p.suffix)]
                key = stem if rel_dir == "." else f"{rel_dir}/{stem}"
                files.append((key, Path(dirpath) / name))
    out: dict[str, Path] = {}
    for key, p in files:
        if strip and key.endswith(strip):
            key = key[: -len(strip)]
        if key in out:
            raise ParameterError(
                f"--{what}: two files for frame '{key}': {out[key].name} and {p.name}"
            )
        out[key] = p
    return out


def _match(keys: Iterable[str], other: Mapping[str, object]) -> dict[str, object]:
    """Match frame keys to another input by key, or by file stem when unique on both sides."""
    keys = list(keys)
    key_stems = Counter(k.rpartition("/")[2] for k in keys)
    other_by_stem: dict[str, list[str]] = defaultdict(list)
    for k in other:
        other_by_stem[k.rpartition("/")[2]].append(k)
    out = {}
    for k in keys:
        if k in other:
            out[k] = other[k]
            continue
        stem = k.rpartition("/")[2]
        cands = other_by_stem.get(stem, [])
        if len(cands) == 1 and key_stems[stem] == 1:
            out[k] = other[cands[0]]
    return out


def _read_points_table(path: Path) -> dict[str, tuple]:
    """A Parquet table of sparse points (one row per frame) -> key -> (u, v, depth, h, w)."""
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except Exception as exc:
        raise FormatError(f"{path}: cannot read the sparse-points table ({_brief(exc)})") from exc
    id_col = next(
        (c for c in ("id", "frame_id", "stem", "frame", "name") if c in table.column_names), None
    )
    if id_col is None or not {"u", "v", "depth"} <= set(table.column_names):
        raise FormatError(f"{path}: a sparse-points table needs an id column and u, v, depth lists")
    ids = [str(x) for x in table.column(id_col).to_pylist()]
    hs = table.column("height").to_pylist() if "height" in table.column_names else [None] * len(ids)
    ws = table.column("width").to_pylist() if "width" in table.column_names else [None] * len(ids)
    cols = {}
    for name in ("u", "v", "depth"):
        arr = table.column(name).combine_chunks()
        cols[name] = (arr.offsets.to_numpy(), arr.values.to_numpy(zero_copy_only=False))
    out = {}
    for i, fid in enumerate(ids):
        key = fid[: -len(Path(fid).suffix)] if Path(fid).suffix.lower() in DEPTH_SUFFIXES else fid
        if key in out:
            raise FormatError(f"{path}: frame '{key}' appears twice")
        u, v, d = (vals[off[i] : off[i + 1]] for off, vals in cols.values())
        out[key] = (np.asarray(u), np.asarray(v), np.asarray(d), hs[i], ws[i])
    return out


def _is_single_calib(path: Path) -> bool:
    return path.is_file() or (
        (path / "calib_cam_to_cam.txt").exists() or (path / "calib_velo_to_cam.txt").exists()
    )


# -- per-frame job -----------------------------------------------------------------------------------
def _read_bytes(path: str, what: str) -> bytes:
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise FormatError(f"{path}: cannot read {what} ({exc.strerror or exc})") from exc
    if not data:
        raise FormatError(f"{path}: empty {what} file")
    return data


def _decode_rgb_size(data: bytes, source: str) -> tuple[int, int]:
    """Decode an 8-bit colour image (to prove it is readable); return (width, height)."""
    from ..io.image import check_pixel_count, image_header_size, imdecode_captured, import_cv2

    cv2 = import_cv2()
    size = image_header_size(data)
    if size is not None:
        check_pixel_count(*size, f"{source}: declared size")
    img, detail = imdecode_captured(data, cv2.IMREAD_UNCHANGED, source=source)
    if img is None:
        why = f": {detail}" if detail else ""
        raise FormatError(f"{source}: cannot decode image (corrupt or unsupported format){why}")
    if img.dtype != np.uint8:
        raise FormatError(f"{source}: {img.dtype} image, expected 8-bit RGB (is this a depth map?)")
    if img.ndim == 3 and img.shape[2] not in (3, 4):
        raise FormatError(f"{source}: {img.shape[2]}-channel image, expected RGB")
    return int(img.shape[1]), int(img.shape[0])


def _store(data: bytes, src: str | None, dst: Path, link: bool) -> bool:
    """Write ``data`` to ``dst`` atomically, as a hard link to ``src`` when asked and possible."""
    with atomic_path(dst) as tmp:
        if link and src is not None:
            try:
                tmp.unlink()
                # link() does not follow a symbolic link: resolve it, or the dataset would hold
                # a link pointing outside it instead of the file.
                os.link(os.path.realpath(src), tmp)
                return True
            except OSError:  # other file system, or links not permitted: copy instead
                pass
        tmp.write_bytes(data)
    return False


def _clean_points(u, v, d, h: int, w: int, source: str) -> np.ndarray:
    u = np.asarray(u)
    v = np.asarray(v)
    d = np.asarray(d, dtype=np.float32)
    if not (u.shape == v.shape == d.shape):
        raise FormatError(f"{source}: u, v, depth lengths differ")
    keep = np.isfinite(d) & (d > 0)
    u, v, d = u[keep], v[keep], d[keep]
    if u.size and (u.min() < 0 or v.min() < 0 or u.max() >= w or v.max() >= h):
        raise FormatError(f"{source}: sparse points outside the {w}x{h} image")
    flat = v.astype(np.int64) * w + u.astype(np.int64)
    if np.unique(flat).size != flat.size:
        raise FormatError(f"{source}: two sparse points in the same pixel")
    depth = np.zeros((h, w), dtype=np.float32)
    depth[v.astype(np.intp), u.astype(np.intp)] = d
    return depth


_RECORD_MAGIC = b"SPTREC1\n"


def _write_record(path: Path, row: dict, points) -> None:
    """Staging record: magic, JSON header (manifest row, point count), then the raw points.

    Layout: ``SPTREC1\n``, uint64 LE header length, UTF-8 JSON, then u (uint16 LE),
    v (uint16 LE), depth (float32 LE). Far cheaper than a one-row Parquet file or an .npz
    (about 0.1 ms vs 3-5 ms to write and read back here).
    """
    n = -1 if points is None else int(len(points[0]))
    header = json.dumps({"row": row, "n_points": n}).encode("utf-8")
    parts = [_RECORD_MAGIC, np.uint64(len(header)).astype("<u8").tobytes(), header]
    if points is not None:
        u, v, d = points
        parts += [
            np.asarray(u, "<u2").tobytes(),
            np.asarray(v, "<u2").tobytes(),
            np.asarray(d, "<f4").tobytes(),
        ]
    with atomic_path(path) as tmp:
        tmp.write_bytes(b"".join(parts))


def _read_record(path: Path) -> tuple[dict, tuple | None]:
    try:
        data = path.read_bytes()
        if not data.startswith(_RECORD_MAGIC):
            raise ValueError("bad magic")
        start = len(_RECORD_MAGIC) + 8
        size = int(np.frombuffer(data[len(_RECORD_MAGIC) : start], "<u8")[0])
        header = json.loads(data[start : start + size].decode("utf-8"))
        n = int(header["n_points"])
        body = memoryview(data)[start + size :]
        if n < 0:
            points = None
        elif len(body) != 8 * n:
            raise ValueError(f"{len(body)} bytes of points, expected {8 * n}")
        else:
            points = (
                np.frombuffer(body[: 2 * n], "<u2").astype(np.uint16),
                np.frombuffer(body[2 * n : 4 * n], "<u2").astype(np.uint16),
                np.frombuffer(body[4 * n :], "<f4").astype(np.float32),
            )
        row = header["row"]
        if not isinstance(row, dict):
            raise ValueError("the record's row is not an object")
    except (OSError, ValueError, KeyError, TypeError, IndexError, OverflowError) as exc:
        raise FormatError(
            f"{path}: corrupt staging record ({_brief(exc)}); delete it and rerun"
        ) from exc
    return row, points


def build_frame(task: FrameTask) -> dict:
    """Copy/convert one frame into the dataset and stage its manifest row (picklable job).

    ``task.inputs`` holds: ``root``, ``id``, ``sequence``, ``frame``, ``rgb`` (path),
    ``sparse`` (path) or ``sparse_points`` ((u, v, depth, h, w)), optional ``gt``,
    ``confidence``, ``calib`` (paths), ``sparse_format``, ``link``, ``source``, ``params``.
    Returns counts and the seconds spent per stage (``t_read``, ``t_decode``, ``t_encode``,
    ``t_hash``, ``t_write``, ``t_stage``).
    """

    x = task.inputs
    root = Path(x["root"])
    fid = x["id"]
    t = defaultdict(float)
    clock = time.perf_counter

    def timed(stage, fn, *args, **kwargs):
        t0 = clock()
        out = fn(*args, **kwargs)
        t[stage] += clock() - t0
        return out

    linked = 0
    row: dict = {f.name: None for f in MANIFEST_SCHEMA}
    row.update(id=fid, sequence=x["sequence"], frame=x["frame"], source=x["source"])

    # RGB: stored byte for byte with its own suffix.
    rgb_src = x["rgb"]
    data = timed("t_read", _read_bytes, rgb_src, "image")
    w, h = timed("t_decode", _decode_rgb_size, data, rgb_src)
    row.update(width=w, height=h)
    row["rgb_sha256"] = timed("t_hash", bytes_sha256, data)
    row["rgb_path"] = f"rgb/{fid}{Path(rgb_src).suffix.lower()}"
    # Files are written only once every input of the frame has been decoded and checked, so
    # a bad frame leaves nothing behind in the dataset.
    writes = [(data, rgb_src, root / row["rgb_path"])]

    # Sparse depth: the float32 map as decoded, then PNG and/or points.
    fmt = x["sparse_format"]
    params = {"sparse_format": fmt, "inputs": dict(x["inputs_desc"])}
    sparse_png = None
    if x.get("sparse") is not None:
        src = x["sparse"]
        sdata = timed("t_read", _read_bytes, src, "sparse depth")
        depth = timed("t_decode", decode_depth_bytes, sdata, Path(src).suffix, source=src)
        if Path(src).suffix.lower() == ".png":
            sparse_png = sdata
    else:
        u, v, d, ph, pw = x["sparse_points"]
        if (ph is not None and ph != h) or (pw is not None and pw != w):
            raise FormatError(f"frame {fid}: sparse points are for {pw}x{ph}, the image is {w}x{h}")
        src = "sparse points table"
        depth = timed("t_decode", _clean_points, u, v, d, h, w, f"frame {fid}")
    if depth.shape != (h, w):
        raise FormatError(
            f"{src}: sparse depth is {depth.shape[1]}x{depth.shape[0]}, the image {rgb_src} is {w}x{h}"
        )
    n_sparse = int(np.count_nonzero(depth))
    row.update(n_sparse=n_sparse, density=n_sparse / float(w * h))
    if fmt in ("png", "both"):
        if sparse_png is None:
            from ..io.image import encode_depth_png

            sparse_png, clipped = timed("t_encode", encode_depth_png, depth)
            params["png_clipped"] = int(clipped)
            png_src = None
        else:
            png_src = src
        row["sparse_path"] = f"{SPARSE_DIR}/{fid}.png"
        row["sparse_sha256"] = timed("t_hash", bytes_sha256, sparse_png)
        writes.append((sparse_png, png_src, root / row["sparse_path"]))
    points = None
    if fmt in ("parquet", "both"):
        if max(w, h) > MAX_SIDE:
            raise FormatError(f"frame {fid}: {w}x{h} is too large for uint16 pixel coordinates")
        points = timed("t_encode", depth_to_points, depth)
        row["sparse_points_sha256"] = timed("t_hash", points_sha256, *points)

    # Ground truth and confidence: stored byte for byte (PNG or .npy), decoded to check.
    for kind, decode in (("gt", decode_depth_bytes), ("confidence", decode_confidence_bytes)):
        src_k = x.get(kind)
        if src_k is None:
            continue
        kdata = timed("t_read", _read_bytes, src_k, kind)
        arr = timed("t_decode", decode, kdata, Path(src_k).suffix, source=src_k)
        if arr.shape != (h, w):
            raise FormatError(
                f"{src_k}: {kind} is {arr.shape[1]}x{arr.shape[0]}, the image {rgb_src} is {w}x{h}"
            )
        if kind == "gt":
            row["n_gt"] = int(np.count_nonzero(arr))
        rel = f"{kind}/{fid}{Path(src_k).suffix.lower()}"
        row[f"{kind}_path"] = rel
        row[f"{kind}_sha256"] = timed("t_hash", bytes_sha256, kdata)
        writes.append((kdata, src_k, root / rel))

    if x.get("calib") is not None:
        from ..errors import CalibrationError
        from ..io.calib import load_calibration

        calib = load_calibration(x["calib"])
        if calib.width is not None and (calib.width, calib.height) != (w, h):
            raise CalibrationError(
                f"{x['calib']}: calibration is for {calib.width}x{calib.height}, "
                f"the image {rgb_src} is {w}x{h}"
            )
        row.update(fx=calib.fx, fy=calib.fy, cx=calib.cx, cy=calib.cy)
        params["calib"] = x["inputs_desc"].get("calib")
    if x.get("params"):
        params["params"] = x["params"]
    row["generation_params"] = json.dumps(params, sort_keys=True)

    for wdata, wsrc, wdst in writes:
        linked += timed("t_write", _store, wdata, wsrc, wdst, x["link"])
    t0 = clock()
    _write_record(root / STAGING / f"{fid}.rec", row, points)
    t["t_stage"] += clock() - t0
    return {"n_sparse": n_sparse, "linked": linked, **t}


# -- build ---------------------------------------------------------------------------------------
def _dataset_state(out: Path) -> str:
    """'new', 'dataset' (has a manifest) or 'partial' (staged frames, no manifest yet)."""
    if (out / MANIFEST_NAME).is_file():
        return "dataset"
    if (out / STAGING).is_dir():
        return "partial"
    if out.exists() and any(
        p for p in out.iterdir() if p.name not in ("rgb", SPARSE_DIR, "gt", "confidence")
    ):
        raise OutputError(
            f"{out} exists and is not a sparsetools dataset (no {MANIFEST_NAME}); "
            "choose a new or empty folder"
        )
    return "new"


def build_dataset(
    out_dir: str | os.PathLike,
    *,
    rgb: str | os.PathLike,
    sparse: str | os.PathLike,
    gt: str | os.PathLike | None = None,
    confidence: str | os.PathLike | None = None,
    calib: str | os.PathLike | None = None,
    sequence_from: str = "parent",
    split: str | Mapping[str, float] | None = None,
    split_files: Iterable[str | tuple[str, str]] | None = None,
    seed: int = 0,
    sparse_format: str = "both",
    link: bool = False,
    source: str = "lidar",
    params: dict | None = None,
    executor=None,
    overwrite: bool = False,
    on_error: str = "stop",
    progress: bool | None = None,
    frames_per_part: int = 1000,
    debug: bool = False,
) -> dict:
    """Build (or extend) a dataset folder from per-frame input files.

    Parameters
    ----------
    out_dir : path-like
        Dataset folder; created, or extended when it already holds a dataset.
    rgb : path-like
        Folder of camera images (.png/.jpg), searched recursively. A frame's key is its
        path relative to this folder without suffix; the key is the sample id.
    sparse : path-like
        Folder of sparse depth maps (KITTI uint16 PNG or float ``.npy`` metres) matched to
        the images by key (or by a file stem unique on both sides), or a Parquet table of
        points with one row per frame (id, u, v, depth lists; optional height, width).
    gt, confidence : path-like, optional
        Folders of ground-truth depth (PNG/.npy) and confidence maps (PNG uint16/65535 or
        uint8/255, or .npy); ``<stem>_conf`` matches frame ``<stem>``.
    calib : path-like, optional
        One calibration for every frame (file, or KITTI raw calib folder), or a folder of
        per-frame ``.txt``/``.json`` calibrations matched by key; gives fx, fy, cx, cy.
    sequence_from : str
        ``parent`` (the key's folder) or ``regex:PATTERN`` (group ``sequence``, else group
        1, else the whole match, searched in the key).
    split : str or mapping, optional
        Fractions per split (default 0.8/0.1/0.1 train/val/test), assigned by sequence.
    split_files : iterable, optional
        Split lists (``NAME=PATH`` or a path whose name contains train/val/test); frames
        not listed are left out. Exclusive with ``split``.
    seed : int
        Split seed.
    sparse_format : {"png", "parquet", "both"}
    link : bool
        Hard-link input files into the dataset instead of copying (falls back to a copy
        across file systems). Converted files (.npy -> PNG) are always written.
    source : str
        Sensor that produced the sparse depth (``lidar``, ``lidar-4beam``, ``radar``...).
    params : dict, optional
        Generation parameters stored (as JSON) in every new row.
    executor, overwrite, on_error, progress, debug
        As :func:`sparsetools.pipeline.run_frames`. Without ``overwrite`` frames already in
        the dataset are kept as they are; with it, frames given again are rebuilt.

    Returns
    -------
    dict
        Summary: frames, processed, skipped_existing, failed, failures, seconds, samples
        (rows in the manifest), sequences, splits (count per split), unmatched inputs,
        linked files, and ``stage_seconds``: ``t_plan`` (indexing and matching the inputs),
        per-frame stages summed over frames (``t_read``, ``t_decode``, ``t_encode``: PNG
        encoding and point extraction, ``t_hash``, ``t_write``: copies / links,
        ``t_stage``: staging records) and ``t_finalize`` (Parquet parts and manifest).
    """
    if sparse_format not in SPARSE_FORMATS:
        raise ParameterError(
            f"sparse format must be one of {', '.join(SPARSE_FORMATS)}, got {sparse_format!r}"
        )
    if split is not None and split_files:
        raise ParameterError("give split fractions or split files, not both")
    if frames_per_part < 1:
        raise ParameterError("frames_per_part must be >= 1")
    fractions = parse_split_fractions(split) if split is not None else dict(DEFAULT_SPLIT)
    if not str(source).strip():
        raise ParameterError("source must not be empty")
    t_start = time.perf_counter()

    rgb_files = _index_inputs(rgb, RGB_SUFFIXES, what="rgb")
    if not rgb_files:
        raise ParameterError(f"--rgb: no .png/.jpg images in {rgb}")
    sparse_path = Path(sparse)
    if sparse_path.is_file() and sparse_path.suffix.lower() == ".parquet":
        sparse_in = _read_points_table(sparse_path)
        sparse_is_table = True
    else:
        sparse_in = _index_inputs(sparse, DEPTH_SUFFIXES, what="sparse")
        sparse_is_table = False
        if not sparse_in and (sparse_path / "sparse.parquet").is_file():
            # the output folder of ``sparsetools project --format parquet``
            sparse_path = sparse_path / "sparse.parquet"
            sparse_in = _read_points_table(sparse_path)
            sparse_is_table = True
    matched_sparse = _match(rgb_files, sparse_in)
    unmatched = {"rgb_without_sparse": len(rgb_files) - len(matched_sparse)}
    keys = sorted(matched_sparse)
    extra = {}
    for kind, folder, strip in (("gt", gt, None), ("confidence", confidence, CONF_SUFFIX)):
        if folder is None:
            continue
        found = _match(keys, _index_inputs(folder, DEPTH_SUFFIXES, what=kind, strip=strip))
        unmatched[f"without_{kind}"] = len(keys) - len(found)
        keys = [k for k in keys if k in found]
        extra[kind] = found
    calib_of: dict[str, str | None] = dict.fromkeys(keys)
    if calib is not None:
        cpath = Path(calib)
        if not cpath.exists():
            raise ParameterError(f"--calib: {cpath} does not exist")
        if _is_single_calib(cpath):
            calib_of = dict.fromkeys(keys, str(cpath))
        else:
            found = _match(keys, _index_inputs(cpath, CALIB_SUFFIXES, what="calib"))
            unmatched["without_calib"] = len(keys) - len(found)
            keys = [k for k in keys if k in found]
            calib_of = {k: str(found[k]) for k in keys}
    if not keys:
        raise ParameterError(
            f"no frame has all its inputs ({', '.join(f'{k}: {v}' for k, v in unmatched.items())}); "
            "files are matched by their path relative to each folder, without suffix"
        )
    for k in keys:
        check_relative_path(k, what="frame id")
        if Path(k).name.startswith(TMP_PREFIX):
            raise ParameterError(f"frame id {k!r} is reserved")
    seq_fn = sequence_resolver(sequence_from, Path(rgb).resolve().name or "sequence")
    sequence = {k: seq_fn(k) for k in keys}

    assignment: dict[str, str] | None = None
    split_report = {}
    if split_files:
        assignment, split_report = _split_file_assignments(split_files, sequence)
        unmatched["not_in_split_files"] = sum(1 for k in keys if k not in assignment)
        keys = [k for k in keys if k in assignment]
        if not keys:
            raise ParameterError("no frame is listed in the split file(s)")

    inputs = [p for p in (rgb, sparse, gt, confidence) if p is not None]
    out = check_output_dir(out_dir, [p for p in inputs if Path(p).is_dir()])
    real_out = out.resolve()
    for p in [*inputs, calib]:
        if p is not None and (
            Path(p).resolve() == real_out or real_out in Path(p).resolve().parents
        ):
            # files would be replaced by copies of themselves (and then hashed and deleted)
            raise OutputError(f"input {p} is inside the dataset folder {out_dir}")
    state = _dataset_state(out)
    existing_ids: set[str] = set()
    if state == "dataset":
        table, _ = read_manifest(out / MANIFEST_NAME)
        existing_ids = set(table.column("id").to_pylist())
    todo = keys if overwrite else [k for k in keys if k not in existing_ids]

    tasks = []
    for k in todo:
        x = {
            "root": str(out),
            "id": k,
            "sequence": sequence[k],
            "frame": k.rpartition("/")[2],
            "rgb": str(rgb_files[k]),
            "sparse_format": sparse_format,
            "link": bool(link),
            "source": str(source),
            "params": params,
            "calib": calib_of.get(k),
            "inputs_desc": {"rgb": _rel_desc(rgb_files[k], rgb)},
        }
        if sparse_is_table:
            x["sparse_points"] = matched_sparse[k]
            x["inputs_desc"]["sparse"] = sparse_path.name
        else:
            x["sparse"] = str(matched_sparse[k])
            x["inputs_desc"]["sparse"] = _rel_desc(matched_sparse[k], sparse)
        for kind, found in extra.items():
            x[kind] = str(found[k])
            x["inputs_desc"][kind] = _rel_desc(found[k], gt if kind == "gt" else confidence)
        if calib_of.get(k) is not None:
            x["inputs_desc"]["calib"] = _rel_desc(Path(calib_of[k]), calib)
        outputs = [out / f"rgb/{k}{rgb_files[k].suffix.lower()}"]
        if sparse_format in ("png", "both"):
            outputs.append(out / f"{SPARSE_DIR}/{k}.png")
        for kind, found in extra.items():
            outputs.append(out / f"{kind}/{k}{found[k].suffix.lower()}")
        outputs.append(out / STAGING / f"{k}.rec")  # written last: marks the frame complete
        tasks.append(FrameTask(k, x, tuple(outputs)))

    t_plan = time.perf_counter() - t_start
    summary = run_frames(
        build_frame,
        tasks,
        executor=executor,
        overwrite=overwrite,
        on_error=on_error,
        progress=progress,
        desc="dataset",
        debug=debug,
    )
    result = summary.as_dict()
    result["frames"] = len(keys)
    result["skipped_existing"] += len(keys) - len(todo)
    stage_totals = {"t_plan": round(t_plan, 4)}
    stage_totals.update(
        {
            s: round(summary.total(s), 4)
            for s in ("t_read", "t_decode", "t_encode", "t_hash", "t_write", "t_stage")
        }
    )
    info = {
        "created_by": f"sparsetools {__version__}",
        "sparse_format": sparse_format,
        "split": {"method": "split-file", **split_report}
        if assignment is not None
        else {"method": "sequence", "fractions": fractions, "seed": int(seed)},
    }
    t0 = time.perf_counter()
    final = _finalize(
        out,
        fractions=fractions,
        seed=seed,
        assignment=assignment,
        info=info,
        frames_per_part=frames_per_part,
    )
    stage_totals["t_finalize"] = round(time.perf_counter() - t0, 4)
    result.update(final)
    result.update(
        unmatched=unmatched, linked=int(summary.total("linked")), stage_seconds=stage_totals
    )
    result["seconds"] = round(time.perf_counter() - t_start, 3)
    return result


def _rel_desc(path: Path, folder) -> str:
    folder = Path(folder)
    try:
        return Path(path).relative_to(folder).as_posix() if folder.is_dir() else folder.name
    except ValueError:
        return Path(path).name


def _part_index(name: str) -> int | None:
    m = _PART_RE.match(name)
    return int(m.group(1)) if m else None


def _finalize(out: Path, *, fractions, seed, assignment, info, frames_per_part) -> dict:
    """Merge staged frames into the manifest and parts (see the module docstring)."""
    import pyarrow as pa

    staging = out / STAGING
    staged_files = (
        sorted(p for p in staging.rglob("*.rec") if not p.name.startswith(TMP_PREFIX))
        if staging.is_dir()
        else []
    )
    manifest_path = out / MANIFEST_NAME
    old_rows: list[dict] = []
    old_info: dict = {}
    if manifest_path.is_file():
        table, old_info = read_manifest(manifest_path)
        old_rows = table.select(MANIFEST_SCHEMA.names).to_pylist()
    if not staged_files:
        return _counts(old_rows)

    new_rows = []
    points_of: dict[str, tuple] = {}
    for p in staged_files:
        row, points = _read_record(p)
        new_rows.append({name: row.get(name) for name in MANIFEST_SCHEMA.names})
        if points is not None:
            points_of[row["id"]] = points
    staged_ids = {r["id"] for r in new_rows}
    kept = [r for r in old_rows if r["id"] not in staged_ids]

    if assignment is not None:
        unknown = [r["id"] for r in new_rows if r["id"] not in assignment]
        if unknown:
            log.warning(
                "%d staged frame(s) are not in the split files and are left out: %s",
                len(unknown),
                ", ".join(unknown[:5]),
            )
        for r in new_rows:
            r["split"] = assignment.get(r["id"])
        new_rows = [r for r in new_rows if r["split"] is not None]
    else:
        pinned: dict[str, str] = {}
        for r in sorted(kept, key=lambda r: r["id"]):
            if r["split"] is not None:
                pinned.setdefault(r["sequence"], r["split"])
        seq_split = assign_splits(
            {r["sequence"] for r in new_rows}, fractions, seed=seed, pinned=pinned
        )
        for r in new_rows:
            r["split"] = seq_split[r["sequence"]]
    keep_new = {r["id"] for r in new_rows}

    sparse_dir = out / SPARSE_DIR
    on_disk = sorted(sparse_dir.glob("part-*.parquet")) if sparse_dir.is_dir() else []
    # Parts no manifest row refers to were written by a finalize that was interrupted before
    # its manifest: drop them, so the resumed build numbers its parts as an uninterrupted one.
    referenced_old = {r["sparse_parquet"] for r in old_rows if r["sparse_parquet"] is not None}
    for p in on_disk:
        if f"{SPARSE_DIR}/{p.name}" not in referenced_old:
            p.unlink()
    on_disk = [p for p in on_disk if p.exists()]
    next_part = 1 + max((i for p in on_disk if (i := _part_index(p.name)) is not None), default=-1)
    written = []

    def new_part(table: pa.Table) -> str:
        nonlocal next_part
        rel = f"{SPARSE_DIR}/part-{next_part:05d}.parquet"
        next_part += 1
        write_sparse_part(out / rel, table)
        written.append(rel)
        return rel

    # Old parts that lose rows (overwritten frames) are rewritten with the rows kept.
    kept_by_part: dict[str, list[dict]] = defaultdict(list)
    for r in kept:
        if r["sparse_parquet"] is not None:
            kept_by_part[r["sparse_parquet"]].append(r)
    removed_parts = {
        r["sparse_parquet"]
        for r in old_rows
        if r["id"] in staged_ids and r["sparse_parquet"] is not None
    }
    for rel in sorted(removed_parts & set(kept_by_part)):
        rows = sorted(kept_by_part[rel], key=lambda r: r["id"])
        table = read_sparse_part(resolve_in_dataset(out, rel))
        sub = table.take(pa.array([r["sparse_row"] for r in rows], type=pa.int64()))
        if sub.column("id").to_pylist() != [r["id"] for r in rows]:
            raise FormatError(f"{rel}: rows do not match the manifest; run 'dataset verify'")
        new_rel = new_part(sub)
        for i, r in enumerate(rows):
            r["sparse_parquet"], r["sparse_row"] = new_rel, i

    by_id = {r["id"]: r for r in new_rows}
    with_points = sorted(fid for fid in points_of if fid in keep_new)
    for start in range(0, len(with_points), frames_per_part):
        ids = with_points[start : start + frames_per_part]
        rel = new_part(
            _points_table(
                ids,
                [points_of[i] for i in ids],
                [(by_id[i]["height"], by_id[i]["width"]) for i in ids],
            )
        )
        for i, fid in enumerate(ids):
            by_id[fid]["sparse_parquet"], by_id[fid]["sparse_row"] = rel, i

    rows = sorted(kept + new_rows, key=lambda r: r["id"])
    merged_info = {**old_info, **info}
    merged_info.pop("schema_version", None)
    write_manifest(
        manifest_path, pa.Table.from_pylist(rows, schema=MANIFEST_SCHEMA), info=merged_info
    )

    referenced = {r["sparse_parquet"] for r in rows if r["sparse_parquet"] is not None}
    for p in sorted(sparse_dir.glob("part-*.parquet")) if sparse_dir.is_dir() else []:
        if f"{SPARSE_DIR}/{p.name}" not in referenced:
            p.unlink()
    shutil.rmtree(staging, ignore_errors=True)
    result = _counts(rows)
    result["new_parts"] = len(written)
    return result


def _points_table(ids: list[str], points: list[tuple], sizes: list[tuple[int, int]]):
    """A :data:`PART_SCHEMA` table from per-frame (u, v, depth) arrays (no per-point Python)."""
    import pyarrow as pa

    lengths = np.array([len(p[0]) for p in points], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    if offsets[-1] > np.iinfo(np.int32).max:
        raise ParameterError("too many points for one part: lower frames_per_part")
    offsets = pa.array(offsets.astype(np.int32))

    def column(i, dtype, type_):
        values = (
            np.concatenate([np.asarray(p[i], dtype) for p in points])
            if points
            else np.zeros(0, dtype)
        )
        return pa.ListArray.from_arrays(offsets, pa.array(values, type=type_))

    return pa.table(
        {
            "id": pa.array(ids, pa.string()),
            "u": column(0, np.uint16, pa.uint16()),
            "v": column(1, np.uint16, pa.uint16()),
            "depth": column(2, np.float32, pa.float32()),
            "height": pa.array([h for h, _ in sizes], pa.int32()),
            "width": pa.array([w for _, w in sizes], pa.int32()),
        },
        schema=PART_SCHEMA,
    )


def _counts(rows: list[dict]) -> dict:
    splits = Counter(r["split"] for r in rows)
    return {
        "samples": len(rows),
        "sequences": len({r["sequence"] for r in rows}),
        "splits": {k: splits[k] for k in sorted(splits, key=str)},
    }


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
        from ..io.image import check_pixel_count, image_header_size, imdecode_captured, import_cv2

        cv2 = import_cv2()
        size = image_header_size(data)
        if size is not None:
            check_pixel_count(*size, "declared size")
        img, _ = imdecode_captured(data, cv2.IMREAD_UNCHANGED, source=rel)
        if img is None or img.dtype != np.uint8:
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
    return {
        "dataset": str(root),
        "schema_version": info["schema_version"],
        "samples": len(rows),
        "problems": problems,
        "warnings": warnings,
    }


# -- stats over files ---------------------------------------------------------------------------
def _depth_files(path: str | os.PathLike, what: str) -> dict[str, Path]:
    p = Path(path)
    if p.is_file():
        return {p.stem: p}
    files = _index_inputs(p, DEPTH_SUFFIXES, what=what)
    if not files:
        raise ParameterError(f"{p}: no depth maps (.png or .npy)")
    return files


def depth_stats_files(
    depth: str | os.PathLike,
    *,
    reference: str | os.PathLike | None = None,
    max_depth: float = 80.0,
) -> dict:
    """Statistics of one depth map or a folder of them, optionally against a reference.

    Parameters
    ----------
    depth : path-like
        A depth map (KITTI PNG or .npy) or a folder of them.
    reference : path-like, optional
        A reference map (e.g. LiDAR) or folder, matched by key/stem: adds the intrinsic-error
        metrics of each map against it.
    max_depth : float, metres
        Reference depths above this are ignored by the intrinsic error.

    Returns
    -------
    dict
        ``frames``: per-frame dicts (id, points, pixels, density_percent, min, median, mean,
        max, and with a reference :func:`sparsetools.ops.intrinsic.intrinsic_error`'s
        delta1, delta2, rmse, density (%), evaluated); ``aggregate``: per-frame values
        averaged over frames (min / max: over all frames) plus ``frames`` and
        ``total_points``; ``unmatched``: maps without a reference (left out).
    """
    from ..io.dataset import read_depth_file
    from ..ops.intrinsic import intrinsic_error
    from ..ops.stats import depth_stats

    files = _depth_files(depth, "depth")
    refs = None
    if reference is not None:
        refs = _match(files, _depth_files(reference, "reference"))
        if not refs:
            raise ParameterError(
                f"no depth map in {depth} has a reference in {reference} with the same name"
            )
    frames = []
    for key in sorted(files):
        d = read_depth_file(files[key])
        rec = {"id": key, **depth_stats(d)}
        if refs is not None:
            if key not in refs:
                continue
            ref = read_depth_file(refs[key])
            if ref.shape != d.shape:
                raise FormatError(
                    f"{files[key]} is {d.shape[1]}x{d.shape[0]} but its reference {refs[key]} is "
                    f"{ref.shape[1]}x{ref.shape[0]}"
                )
            rec.update(intrinsic_error(d, ref, max_depth=max_depth))
        frames.append(rec)
    agg: dict = {"frames": len(frames), "total_points": int(sum(f["points"] for f in frames))}
    numeric = [k for k in (frames[0] if frames else {}) if k not in ("id", "pixels")]
    for k in numeric:
        vals = [f[k] for f in frames if isinstance(f.get(k), (int, float)) and math.isfinite(f[k])]
        if not vals:
            agg[k] = None
        elif k == "min":
            agg[k] = min(vals)
        elif k == "max":
            agg[k] = max(vals)
        else:  # per-frame values averaged over frames (the papers' tables do the same)
            agg[k] = float(np.mean(vals))
    result = {"frames": frames, "aggregate": agg}
    if refs is not None:
        result["unmatched"] = len(files) - len(frames)
    return result
