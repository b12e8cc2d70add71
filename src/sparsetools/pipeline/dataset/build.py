"""``dataset build``: index the inputs, stage every frame, merge into the manifest.

Build in three stages, so that an interrupted run resumes and appending works:

1. **Plan** (main process): index the input folders, match files by frame key, derive each
   frame's sequence, drop frames already in the dataset (unless ``overwrite``).
2. **Frames** (:mod:`.staging`, one :class:`FrameTask` each, any executor).
3. **Finalize** (main process): merge the existing manifest with every staged record,
   assign splits (by sequence), write the new ``sparse/part-*.parquet`` files, then the
   manifest atomically, then delete parts no longer referenced and the staging folder.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import time
from collections import Counter, defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ..._version import __version__
from ...errors import FormatError, OutputError, ParameterError
from ...io.atomic import TMP_PREFIX
from ...io.dataset import (
    MANIFEST_NAME,
    MANIFEST_SCHEMA,
    SPARSE_DIR,
    read_manifest,
    read_sparse_part,
    resolve_in_dataset,
    write_manifest,
    write_sparse_part,
)
from ...io.points_table import read_points_table, sparse_part_table
from ...io.provenance import RECORD_DIR
from ...io.sources import FrameKey, index_input, is_shared_calibration, match_keys
from ..batch import Batch, RunSummary
from ..core import FrameTask, RunSpec, check_output_dir, run_frames
from .splits import DEFAULT_SPLIT, assign_splits, parse_split_fractions, sequence_resolver
from .splits import split_file_assignments as _split_file_assignments
from .staging import STAGING, DatasetFrameInput, DatasetJob
from .staging import read_record as _read_record

__all__ = ["SPARSE_FORMATS", "BuildSettings", "build_dataset"]

log = logging.getLogger(__name__)

RGB_SUFFIXES = (".png", ".jpg", ".jpeg")
CALIB_SUFFIXES = (".txt", ".json")
SPARSE_FORMATS = ("png", "parquet", "both")
#: jbf-expand names its confidence maps ``<stem>_conf.png``; they match frame ``<stem>``.
CONF_SUFFIX = "_conf"
#: Where the one-command routes (``dataset nuscenes`` / ``kitti-raw``) keep what they prepare
#: (camera images, projected maps): each a sparsetools output folder with its own record.
SOURCES_DIR = ".sources"
_PART_RE = re.compile(r"^part-(\d{5,})\.parquet$")


# -- input indexing ----------------------------------------------------------------------------------
def _confidence_index(path, option: str) -> dict[FrameKey, Path]:
    """Confidence maps by frame: ``<frame>_conf.*`` (jbf-expand's naming) matches ``<frame>``."""
    index = index_input(path, "confidence", option=option).files
    out: dict[FrameKey, Path] = {}
    for key, f in index.items():
        if key.frame.endswith(CONF_SUFFIX) and len(key.frame) > len(CONF_SUFFIX):
            key = FrameKey(key.sequence, key.frame[: -len(CONF_SUFFIX)])
        if key in out:
            raise ParameterError(
                f"{option}: two files for frame '{key}': {out[key].name} and {f.name}"
            )
        out[key] = f
    return out


@dataclass(frozen=True)
class BuildSettings:
    """What a dataset's samples depend on: compared on every run that adds to it."""

    sparse_format: str = "both"
    sparse_name: str | None = None
    gt_name: str | None = None
    link: bool = False
    source: str = "lidar"
    params: dict | None = None
    sequence_from: str = "parent"
    split: dict | None = field(default=None, metadata={"option": "--split"})
    split_files: tuple | None = field(default=None, metadata={"option": "--split-file"})
    seed: int = 0


@dataclass(frozen=True)
class _Inputs:
    """The matched inputs of a build: per frame key, each input's file (or points)."""

    keys: list[FrameKey]
    rgb: dict[FrameKey, Path]
    sparse: dict[FrameKey, object]
    sparse_is_table: bool
    sparse_path: Path
    extra: dict[str, dict[FrameKey, Path]]
    calib: dict[FrameKey, str | None]
    unmatched: dict[str, int]
    splits: dict[FrameKey, str]
    poses: dict[FrameKey, tuple] = field(default_factory=dict)
    times: dict[FrameKey, float] = field(default_factory=dict)


def _index(rgb, sparse, gt, confidence, calib, *, names=(None, None), camera=2) -> _Inputs:
    sparse_name, gt_name = names
    rgb_index = index_input(rgb, "image", option="--rgb", camera=camera)
    rgb_files = rgb_index.files
    sparse_path = Path(sparse)
    if not sparse_path.exists():
        raise ParameterError(f"{sparse_path} does not exist", param="--sparse")
    sparse_is_table = False
    table_file = None
    if sparse_path.is_file() and sparse_path.suffix.lower() == ".parquet":
        table_file = sparse_path
    elif sparse_path.is_dir() and (sparse_path / "sparse.parquet").is_file():
        # the output folder of ``sparsetools project --format parquet``
        try:
            sparse_files = index_input(sparse_path, "sparse", option="--sparse", name=sparse_name)
        except FormatError:
            table_file = sparse_path / "sparse.parquet"
    if table_file is not None:
        sparse_in = read_points_table(table_file)
        sparse_is_table = True
        sparse_path = table_file
        splits = {}
    else:
        sparse_files = index_input(
            sparse_path, "sparse", option="--sparse", name=sparse_name, camera=camera
        )
        sparse_in = sparse_files.files
        splits = dict(sparse_files.splits)
    matched_sparse = match_keys(rgb_files, sparse_in)
    unmatched = {"rgb_without_sparse": len(rgb_files) - len(matched_sparse)}
    keys = sorted(matched_sparse)
    extra: dict[str, dict[FrameKey, Path]] = {}
    for kind, folder in (("gt", gt), ("confidence", confidence)):
        if folder is None:
            continue
        if kind == "gt":
            gt_index = index_input(folder, "gt", option="--gt", name=gt_name, camera=camera)
            found = match_keys(keys, gt_index.files)
            splits.update(gt_index.splits)
        else:
            found = match_keys(keys, _confidence_index(folder, "--confidence"))
        unmatched[f"without_{kind}"] = len(keys) - len(found)
        keys = [k for k in keys if k in found]
        extra[kind] = found
    calib_of: dict[FrameKey, str | None] = dict.fromkeys(keys)
    if calib is not None:
        cpath = Path(calib)
        if not cpath.exists():
            raise ParameterError(f"{cpath} does not exist", param="--calib")
        if is_shared_calibration(cpath):
            calib_of = dict.fromkeys(keys, str(cpath))
        else:
            found = match_keys(
                keys, index_input(cpath, "calib", option="--calib", camera=camera).files
            )
            unmatched["without_calib"] = len(keys) - len(found)
            keys = [k for k in keys if k in found]
            calib_of = {k: str(found[k]) for k in keys}
    elif rgb_index.calib:
        calib_of = {k: str(rgb_index.calib[k]) if k in rgb_index.calib else None for k in keys}
    if not keys:
        raise ParameterError(
            f"no frame has all its inputs ({', '.join(f'{k}: {v}' for k, v in unmatched.items())}); "
            "files are matched by frame (sequence folder and file name)"
        )
    return _Inputs(
        keys, rgb_files, matched_sparse, sparse_is_table, sparse_path, extra, calib_of,
        unmatched, {k: v for k, v in splits.items() if k in set(keys)},
        dict(rgb_index.poses), dict(rgb_index.times),
    )  # fmt: skip


# -- build ---------------------------------------------------------------------------------------
def _dataset_state(out: Path) -> str:
    """'new', 'dataset' (has a manifest) or 'partial' (staged frames, no manifest yet)."""
    if (out / MANIFEST_NAME).is_file():
        return "dataset"
    if (out / STAGING).is_dir():
        return "partial"
    if out.exists() and any(
        p
        for p in out.iterdir()
        if p.name not in ("rgb", SPARSE_DIR, "gt", "confidence", RECORD_DIR, SOURCES_DIR)
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
    sparse_name: str | None = None,
    gt_name: str | None = None,
    camera: int = 2,
    batch: Batch | None = None,
    frames_per_part: int = 1000,
) -> RunSummary:
    """Build (or extend) a dataset folder from per-frame input files.

    Parameters
    ----------
    out_dir : path-like
        Dataset folder; created, or extended when it already holds a dataset.
    rgb : path-like
        Camera images: a folder tree (``DIR/<sequence>/<frame>.png``), a KITTI raw drive /
        date folder / root, or a ``val_selection_cropped`` folder. A frame's key
        ``<sequence>/<frame>`` is the sample id.
    sparse : path-like
        Sparse depth maps (KITTI uint16 PNG or float ``.npy`` metres) matched to the images
        by frame key (or by a frame name unique on both sides): a folder tree, a folder
        written by ``project``/``beams``/``jbf-expand``, a KITTI depth-completion tree;
        or a Parquet table of points with one row per frame (id, u, v, depth lists;
        optional height, width).
    gt, confidence : path-like, optional
        Ground-truth depth (PNG/.npy; a KITTI depth-completion ``groundtruth`` tree) and
        confidence maps (PNG uint16/65535 or uint8/255, or .npy; ``<frame>_conf`` matches
        frame ``<frame>``).
    calib : path-like, optional
        One calibration for every frame (file, or KITTI raw calib folder), or a folder of
        per-frame ``.txt``/``.json`` calibrations matched by frame; gives fx, fy, cx, cy. A
        KITTI raw ``rgb`` tree brings its own.
    sequence_from : str
        ``parent`` (the frame's sequence; the rgb folder's name for a flat folder) or
        ``regex:PATTERN`` (group ``sequence``, else group 1, else the whole match, searched
        in the sample id).
    split : str or mapping, optional
        Fractions per split (default 0.8/0.1/0.1 train/val/test), assigned by sequence; or
        ``"tree"``: the split the input tree gives (KITTI depth completion train / val).
    split_files : iterable, optional
        Split lists (``NAME=PATH`` or a path whose name contains train/val/test); frames
        not listed are left out. Exclusive with ``split``.
    seed : int
        Split seed.
    sparse_format : {"png", "parquet", "both"}
    link : bool
        Symbolically link the input files into the dataset instead of copying them (the
        dataset then never changes an input's data or permissions; moving the inputs breaks
        the links). Converted files (.npy -> PNG) are always written.
    source : str
        Sensor that produced the sparse depth (``lidar``, ``lidar-4beam``, ``radar``...).
    params : dict, optional
        Generation parameters stored (as JSON) in every new row.
    sparse_name, gt_name : str, optional
        KITTI depth-completion map sets (``proj_depth/<name>``) of ``sparse`` and ``gt``
        (default ``velodyne_raw`` / ``groundtruth`` when the tree holds several).
    camera : int
        KITTI camera (``image_02``, ``proj_depth/*/image_02``).
    batch : Batch, optional
        Executor, error policy, progress; ``overwrite``: rebuild every frame given and drop
        the frames of earlier runs (the dataset then holds this run's frames only).

    Returns
    -------
    RunSummary
        Totals: samples (rows in the manifest), sequences, splits (count per split),
        unmatched inputs, linked files, and ``stage_seconds``: ``t_plan`` (indexing and
        matching the inputs), per-frame stages summed over frames (``t_read``, ``t_decode``,
        ``t_encode``: PNG encoding and point extraction, ``t_hash``, ``t_write``: copies /
        links, ``t_stage``: staging records) and ``t_finalize`` (Parquet parts and manifest).
    """
    batch = batch or Batch()
    if sparse_format not in SPARSE_FORMATS:
        raise ParameterError(
            f"must be one of {', '.join(SPARSE_FORMATS)}, got {sparse_format!r}",
            param="sparse_format",
        )
    if split is not None and split_files:
        raise ParameterError("give split fractions or split files, not both")
    if frames_per_part < 1:
        raise ParameterError("frames_per_part must be >= 1")
    from_tree = split == "tree"
    fractions = (
        parse_split_fractions(split) if split is not None and not from_tree else dict(DEFAULT_SPLIT)
    )
    if not str(source).strip():
        raise ParameterError("must not be empty", param="source")
    t_start = time.perf_counter()
    inputs = _index(rgb, sparse, gt, confidence, calib, names=(sparse_name, gt_name), camera=camera)
    keys = inputs.keys
    for k in keys:
        if k.frame.startswith(TMP_PREFIX):
            raise ParameterError(f"frame id {str(k)!r} is reserved")
    seq_fn = sequence_resolver(sequence_from, Path(rgb).resolve().name or "sequence")
    sequence = {k: (k.sequence if sequence_from == "parent" and k.sequence else seq_fn(str(k)))
                for k in keys}  # fmt: skip
    ids = {k: str(k) for k in keys}

    assignment: dict[str, str] | None = None
    split_report = {}
    unmatched = dict(inputs.unmatched)
    if split_files:
        assignment, split_report = _split_file_assignments(
            split_files, {ids[k]: sequence[k] for k in keys}
        )
        unmatched["not_in_split_files"] = sum(1 for k in keys if ids[k] not in assignment)
        keys = [k for k in keys if ids[k] in assignment]
        if not keys:
            raise ParameterError("no frame is listed in the split file(s)")
    elif from_tree:
        if not inputs.splits:
            raise ParameterError(
                "tree: the inputs' layout gives no split (only KITTI depth-completion trees and "
                "val_selection_cropped do)",
                param="split",
            )
        assignment = {ids[k]: inputs.splits[k] for k in keys if k in inputs.splits}
        unmatched["without_tree_split"] = sum(1 for k in keys if ids[k] not in assignment)
        keys = [k for k in keys if ids[k] in assignment]
        split_report = {"method": "tree"}

    paths = [p for p in (rgb, sparse, gt, confidence) if p is not None]
    out = check_output_dir(out_dir, [p for p in paths if Path(p).is_dir()])
    real_out = out.resolve()
    sources = real_out / SOURCES_DIR  # what a `dataset nuscenes`/`kitti-raw` run prepared
    for p in [*paths, calib]:
        rp = None if p is None else Path(p).resolve()
        if rp is not None and (rp == sources or sources in rp.parents):
            continue
        if rp is not None and (rp == real_out or real_out in rp.parents):
            # files would be replaced by copies of themselves (and then hashed and deleted)
            raise OutputError(f"input {p} is inside the dataset folder {out_dir}")
    state = _dataset_state(out)
    existing_ids: set[str] = set()
    if state == "dataset":
        table, _ = read_manifest(out / MANIFEST_NAME)
        existing_ids = set(table.column("id").to_pylist())

    settings = BuildSettings(
        sparse_format=sparse_format,
        sparse_name=sparse_name,
        gt_name=gt_name,
        link=bool(link),
        source=str(source),
        params=params,
        sequence_from=sequence_from,
        split=None if split_files or from_tree else fractions,
        split_files=tuple(str(f) for f in split_files) if split_files else None,
        seed=int(seed),
    )
    given = {"rgb": rgb, "sparse": sparse, "gt": gt, "confidence": confidence, "calib": calib}
    tasks = [_task(out, k, ids[k], sequence[k], inputs, sparse_format, given) for k in keys]

    def complete(t, _ids=existing_ids):
        files = [p for r, p in t.outputs.items() if r != "staged"]
        return all(p.is_file() for p in files) and (
            t.outputs["staged"].is_file() or t.inputs.id in _ids
        )

    t_plan = time.perf_counter() - t_start
    spec = RunSpec(
        "dataset build", out, settings, noun="a dataset",
        shared_outputs=(out / MANIFEST_NAME,),
    )  # fmt: skip
    summary = run_frames(
        DatasetJob(str(out), settings), tasks, batch=batch, spec=spec, complete=complete,
        desc="dataset",
    )  # fmt: skip
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
        if split_files
        else ({"method": "tree"} if from_tree else {"method": "sequence", "fractions": fractions,
                                                    "seed": int(seed)}),
    }  # fmt: skip
    t0 = time.perf_counter()
    final = _finalize(
        out,
        fractions=fractions,
        seed=seed,
        assignment=assignment,
        info=info,
        frames_per_part=frames_per_part,
        only=set(ids[k] for k in keys) if batch.overwrite else None,
    )
    stage_totals["t_finalize"] = round(time.perf_counter() - t0, 4)
    return summary.with_totals(
        {
            **final,
            "unmatched": unmatched,
            "linked": int(summary.total("linked")),
            "stage_seconds": stage_totals,
            "output": str(out),
        }
    )


def _task(
    out: Path, k: FrameKey, fid: str, seq: str, inputs: _Inputs, sparse_format: str, given: dict
) -> FrameTask:
    """The task of one frame: its typed input record, dataset files and input files."""
    rgb_file = inputs.rgb[k]
    desc = {"rgb": _rel_desc(rgb_file, given["rgb"])}
    sparse_file = sparse_points = None
    sources = [rgb_file]
    if inputs.sparse_is_table:
        sparse_points = inputs.sparse[k]
        desc["sparse"] = inputs.sparse_path.name
        sources.append(inputs.sparse_path)
    else:
        sparse_file = str(inputs.sparse[k])
        desc["sparse"] = _rel_desc(inputs.sparse[k], given["sparse"])
        sources.append(inputs.sparse[k])
    extra = {}
    for kind, found in inputs.extra.items():
        extra[kind] = str(found[k])
        desc[kind] = _rel_desc(found[k], given[kind])
        sources.append(found[k])
    cal = inputs.calib.get(k)
    if cal is not None:
        desc["calib"] = _rel_desc(Path(cal), given["calib"]) if given["calib"] else Path(cal).name
        sources.append(Path(cal))
    inp = DatasetFrameInput(
        id=fid,
        sequence=seq,
        frame=k.frame,
        rgb=str(rgb_file),
        sparse=sparse_file,
        sparse_points=sparse_points,
        gt=extra.get("gt"),
        confidence=extra.get("confidence"),
        calib=cal,
        timestamp=inputs.times.get(k),
        pose=inputs.poses.get(k),
        inputs_desc=tuple(sorted(desc.items())),
    )
    outputs = {"rgb": out / f"rgb/{fid}{rgb_file.suffix.lower()}"}
    if sparse_format in ("png", "both"):
        outputs["sparse"] = out / f"{SPARSE_DIR}/{fid}.png"
    for kind in ("gt", "confidence"):
        if kind in extra:
            outputs[kind] = out / f"{kind}/{fid}{Path(extra[kind]).suffix.lower()}"
    outputs["staged"] = out / STAGING / f"{fid}.rec"  # written last: marks the frame complete
    return FrameTask(k, inp, outputs, tuple(sources))


def _rel_desc(path: Path, folder) -> str:
    folder = Path(folder)
    try:
        return Path(path).relative_to(folder).as_posix() if folder.is_dir() else folder.name
    except ValueError:
        return Path(path).name


def _part_index(name: str) -> int | None:
    m = _PART_RE.match(name)
    return int(m.group(1)) if m else None


def _frame_indices(rows: list[dict]) -> None:
    """``frame_index``: each frame's rank in its sequence, frames in natural order (numbers
    compared as numbers: ``2`` before ``10``)."""
    by_seq: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        by_seq[r["sequence"]].append(r)
    for seq_rows in by_seq.values():
        seq_rows.sort(key=lambda r: _natural(r["frame"]))
        for i, r in enumerate(seq_rows):
            r["frame_index"] = i


def _natural(text: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", text))


def _finalize(
    out: Path, *, fractions, seed, assignment, info, frames_per_part, only: set[str] | None = None
) -> dict:
    """Merge staged frames into the manifest and parts (see the module docstring).

    ``only``: keep only these sample ids (``--overwrite``: the dataset holds this run only).
    """
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
    dropped = [] if only is None else [r for r in old_rows if r["id"] not in only]
    if not staged_files and not dropped:
        return _counts(old_rows)

    new_rows = []
    points_of: dict[str, tuple] = {}
    for p in staged_files:
        row, points = _read_record(p)
        new_rows.append({name: row.get(name) for name in MANIFEST_SCHEMA.names})
        if points is not None:
            points_of[row["id"]] = points
    staged_ids = {r["id"] for r in new_rows}
    gone = staged_ids | {r["id"] for r in dropped}
    kept = [r for r in old_rows if r["id"] not in gone]

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
        r["sparse_parquet"] for r in old_rows if r["id"] in gone and r["sparse_parquet"] is not None
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
            sparse_part_table(
                ids,
                [points_of[i] for i in ids],
                [(by_id[i]["height"], by_id[i]["width"]) for i in ids],
            )
        )
        for i, fid in enumerate(ids):
            by_id[fid]["sparse_parquet"], by_id[fid]["sparse_row"] = rel, i

    rows = sorted(kept + new_rows, key=lambda r: r["id"])
    _frame_indices(rows)
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


def _counts(rows: list[dict]) -> dict:
    splits = Counter(r["split"] for r in rows)
    return {
        "samples": len(rows),
        "sequences": len({r["sequence"] for r in rows}),
        "splits": {k: splits[k] for k in sorted(splits, key=str)},
    }
