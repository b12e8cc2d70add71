"""``dataset build``: find the inputs, stage every frame, merge into the manifest.

A build runs in three steps, so that an interrupted run resumes and appending works:

1. **Find** (:func:`find_build_inputs`, main process): index the input folders, match files
   by frame key, derive each frame's sequence and the split the inputs give it.
2. **Frames** (:class:`DatasetJob`, one :class:`FrameTask` each, any executor, through
   :func:`~sparsetools.pipeline.core.run_job`): :func:`.staging.stage_frame`.
3. **Finish** (:meth:`DatasetJob.finish`, main process): merge the existing manifest with
   every staged record, assign splits (by sequence), write the new ``sparse/part-*.parquet``
   files, then the manifest atomically, then delete parts no longer referenced and the
   staging folder.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

from ..._version import __version__
from ...errors import FormatError, OutputError, ParameterError
from ...io.atomic import TMP_PREFIX
from ...io.containment import remove_output
from ...io.dataset import MANIFEST_NAME, SPARSE_DIR, check_root_name, read_manifest
from ...io.points_table import read_points_table
from ...io.provenance import RECORD_DIR
from ...io.sources import FrameKey, index_input, is_shared_calibration, match_keys
from ...validate import check_int_range
from ..batch import Batch, RunSummary
from ..core import BatchJob, FrameTask, run_job
from ..provenance import option_names, settings_dict
from .merge import merge_staged
from .official_splits import official_split_lists
from .settings import SPARSE_FORMATS, BuildSettings
from .splits import SplitListsReport, sequence_resolver, split_file_assignments
from .staged import PACK_SUFFIX, latest_entries
from .staging import (
    STAGES,
    STAGING,
    DatasetFrameInput,
    DatasetFrameStats,
    InputFolders,
    sample_files,
    stage_frame,
)

__all__ = [
    "SPARSE_FORMATS",
    "BuildInputs",
    "BuildSettings",
    "DatasetJob",
    "build_dataset",
    "find_build_inputs",
]

log = logging.getLogger(__name__)

RGB_SUFFIXES = (".png", ".jpg", ".jpeg")
CALIB_SUFFIXES = (".txt", ".json")
#: jbf-expand names its confidence maps ``<stem>_conf.png``; they match frame ``<stem>``.
CONF_SUFFIX = "_conf"
#: Where the one-command routes (``dataset nuscenes`` / ``kitti-raw``) keep what they prepare
#: (camera images, projected maps): each a sparsetools output folder with its own record.
SOURCES_DIR = ".sources"


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


# -- finding the frames ----------------------------------------------------------------------------
@dataclass(frozen=True)
class BuildInputs:
    """What :func:`find_build_inputs` found.

    Attributes
    ----------
    frames : list of DatasetFrameInput
        One per frame to build, in frame-key order.
    roots : tuple of Path
        The input paths given (the dataset may not be inside one of them).
    unmatched : dict of str -> int
        Frames left out, by reason (``rgb_without_sparse``, ``without_gt``,
        ``not_in_split_files``, ...).
    split_lists : SplitListsReport, optional
        With split files or an official split: what each list matched, and the frames in no
        list (left out).
    seconds : float
        Time spent indexing and matching.
    rgb_root : Path, optional
        The folder of the camera images (``--rgb``, or the folder holding that file): the
        root ``rgb`` of ``--store reference``.
    """

    frames: list[DatasetFrameInput]
    roots: tuple[Path, ...]
    unmatched: dict[str, int]
    split_lists: SplitListsReport | None = None
    seconds: float = 0.0
    rgb_root: Path | None = None


def find_build_inputs(
    settings: BuildSettings,
    *,
    rgb: str | os.PathLike,
    sparse: str | os.PathLike,
    gt: str | os.PathLike | None = None,
    confidence: str | os.PathLike | None = None,
    calib: str | os.PathLike | None = None,
    camera: int = 2,
) -> BuildInputs:
    """The frames of a build: every frame that has all its inputs (see :func:`build_dataset`
    for the inputs), its sequence, and its split when split files or the tree give it.

    Raises
    ------
    ParameterError
        No frame has all its inputs, none is in the split files, or the tree gives no split.
    """
    t_start = time.perf_counter()
    inputs = _index(
        rgb, sparse, gt, confidence, calib, names=(settings.sparse_name, settings.gt_name),
        camera=camera,
    )  # fmt: skip
    keys = inputs.keys
    for k in keys:
        if k.frame.startswith(TMP_PREFIX):
            raise ParameterError(f"frame id {str(k)!r} is reserved")
    seq_fn = sequence_resolver(settings.sequence_from, Path(rgb).resolve().name or "sequence")
    parent = settings.sequence_from == "parent"
    sequence = {k: (k.sequence if parent and k.sequence else seq_fn(str(k))) for k in keys}
    unmatched = dict(inputs.unmatched)
    split_of: dict[FrameKey, str] = {}
    split_lists = None
    if settings.split_files or settings.official_split:
        lists = (
            official_split_lists(settings.official_split)
            if settings.official_split
            else settings.split_files
        )
        # A frame's camera is the image_0N of its key, else the one the build reads.
        assignment, split_lists = split_file_assignments(
            lists, {str(k): sequence[k] for k in keys}, camera=camera,
            name=settings.official_split,
        )  # fmt: skip
        not_listed = sum(1 for k in keys if str(k) not in assignment)
        unmatched["not_in_split_files"] = not_listed
        split_lists = replace(split_lists, not_listed=not_listed)
        keys = [k for k in keys if str(k) in assignment]
        if not keys:
            which = f"the {settings.official_split} lists" if settings.official_split else (
                "the split file(s)")  # fmt: skip
            raise ParameterError(
                f"no frame is listed in {which}: {split_lists.listed} line(s), none matched "
                "a frame of the inputs"
            )
        split_of = {k: assignment[str(k)] for k in keys}
    elif settings.split_from_tree:
        if not inputs.splits:
            raise ParameterError(
                "tree: the inputs' layout gives no split (only KITTI depth-completion trees and "
                "val_selection_cropped do)",
                param="--splits",
            )
        unmatched["without_tree_split"] = sum(1 for k in keys if k not in inputs.splits)
        keys = [k for k in keys if k in inputs.splits]
        split_of = {k: inputs.splits[k] for k in keys}
    folders = InputFolders.of(rgb=rgb, sparse=sparse, gt=gt, confidence=confidence, calib=calib)
    frames = [_frame_input(k, sequence[k], split_of.get(k), inputs, folders) for k in keys]
    roots = tuple(Path(p) for p in (rgb, sparse, gt, confidence) if p is not None)
    rgb_root = Path(rgb).absolute()
    rgb_root = rgb_root if rgb_root.is_dir() else rgb_root.parent
    return BuildInputs(frames, roots, unmatched, split_lists, time.perf_counter() - t_start,
                       rgb_root=rgb_root)  # fmt: skip


def _frame_input(
    k: FrameKey, seq: str, split: str | None, inputs: _Inputs, folders: InputFolders
) -> DatasetFrameInput:
    """One frame's typed input record: its files (or points) and what they were given as."""
    sparse_file = sparse_points = sparse_table = None
    if inputs.sparse_is_table:
        sparse_points = inputs.sparse[k]
        sparse_table = str(inputs.sparse_path)
    else:
        sparse_file = str(inputs.sparse[k])
    extra = {kind: str(found[k]) for kind, found in inputs.extra.items()}
    return DatasetFrameInput(
        id=str(k),
        sequence=seq,
        frame=k.frame,
        rgb=str(inputs.rgb[k]),
        sparse=sparse_file,
        sparse_points=sparse_points,
        sparse_table=sparse_table,
        gt=extra.get("gt"),
        confidence=extra.get("confidence"),
        calib=inputs.calib.get(k),
        timestamp=inputs.times.get(k),
        pose=inputs.poses.get(k),
        split=split,
        folders=folders,
    )


# -- the job -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DatasetJob(BatchJob[DatasetFrameInput]):
    """``dataset build``: stage every frame (:func:`.staging.stage_frame`), then merge the
    staged frames into the dataset (:meth:`finish`).

    Attributes
    ----------
    settings : BuildSettings
    unmatched, split_lists, plan_seconds
        What finding the inputs reported (:class:`BuildInputs`), for the summary and the
        manifest's metadata.
    frames_per_part : int
        Frames per ``sparse/part-*.parquet`` file.
    param_options : mapping of str -> str
        How messages name the keys of ``settings.params``: a route's own options (``sweeps``
        -> ``--sweeps``); a key not named is ``--params KEY``.
    """

    command = "dataset build"
    noun = "a dataset"
    stats_type = DatasetFrameStats
    tasks_per_frame = True

    settings: BuildSettings
    unmatched: Mapping[str, int] = field(default_factory=dict)
    split_lists: SplitListsReport | None = None
    plan_seconds: float = 0.0
    frames_per_part: int = 1000
    param_options: Mapping[str, str] = field(default_factory=dict)
    rgb_root: tuple[str, str] | None = None

    def __post_init__(self) -> None:
        check_int_range(self.frames_per_part, "frames_per_part", low=1)
        if self.settings.store == "reference":
            if self.rgb_root is None:
                raise ParameterError("--store reference needs the root of the camera images")
            name, path = self.rgb_root
            check_root_name(name, what="root")
            object.__setattr__(self, "rgb_root", (name, os.path.abspath(path)))

    @classmethod
    def for_inputs(
        cls,
        settings: BuildSettings,
        found: BuildInputs,
        *,
        frames_per_part: int = 1000,
        param_options: Mapping[str, str] | None = None,
        rgb_root: tuple[str, str | os.PathLike] | None = None,
    ) -> DatasetJob:
        """The job building the frames ``found``; ``rgb_root``: (name, folder) of the camera
        images, the root their references name with ``settings.store == "reference"``
        (default ``("rgb", found.rgb_root)``: the ``--rgb`` folder)."""
        if rgb_root is None and found.rgb_root is not None:
            rgb_root = ("rgb", found.rgb_root)
        root = None if rgb_root is None else (rgb_root[0], os.fspath(rgb_root[1]))
        return cls(settings, found.unmatched, found.split_lists, found.seconds,
                   frames_per_part=frames_per_part,
                   param_options=dict(param_options or {}),
                   rgb_root=root if settings.store == "reference" else None)  # fmt: skip

    def option_names(self) -> dict:
        names = dict(option_names(self.settings))
        names["link"] = "--store link"  # recorded as 0.2 / 0.3 did (BuildSettings.record_store)
        names.update({f"params.{k}": v for k, v in self.param_options.items()})
        return names

    def record(self) -> dict:
        # Split files are recorded as sparsetools 0.2 wrote them (str of each item), so that
        # its datasets resume.
        record = self.settings.record_store(settings_dict(self.settings))
        if self.settings.official_split is None:  # as 0.2 / 0.3 recorded it
            del record["official_split"]
        if self.settings.split_files:
            record["split_files"] = [str(f) for f in self.settings.split_files]
        return record

    def tasks(self, frames: list[DatasetFrameInput], out_dir: Path) -> list[FrameTask]:
        _check_dataset_folder(out_dir)
        fmt, store = self.settings.sparse_format, self.settings.store
        tasks = [
            FrameTask(x.id, x, {role: out_dir / rel for role, rel in sample_files(
                x, fmt, store, store_points=self.settings.store_points).items()}, x.sources)
            for x in frames
        ]  # fmt: skip
        _check_inputs_outside(out_dir, tasks)
        return tasks

    def shared_outputs(self, out_dir: Path) -> tuple[Path, ...]:
        return (out_dir / MANIFEST_NAME,)

    def before(self, out_dir: Path, batch: Batch) -> None:
        """With ``--overwrite`` every frame of the run is staged again: the packs of earlier
        runs are removed first (their entries would stand for frames this run leaves out)."""
        staging = out_dir / STAGING
        if batch.overwrite and staging.is_dir():
            for p in sorted(staging.glob("*" + PACK_SUFFIX)):
                remove_output(out_dir, p)

    def is_complete(self, out_dir: Path) -> Callable[[FrameTask], bool]:
        """A frame is complete when its files exist and it is in the manifest or staged (an
        entry of a staging pack, or the record file of an earlier version)."""
        manifest = out_dir / MANIFEST_NAME
        merged = set()
        if manifest.is_file():
            merged = set(read_manifest(manifest)[0].column("id").to_pylist())
        staged = set(latest_entries(out_dir / STAGING))

        def complete(task: FrameTask) -> bool:
            files = [p for role, p in task.outputs.items() if role not in ("staged", "points")]
            return all(p.is_file() for p in files) and (
                task.inputs.id in merged
                or task.inputs.id in staged
                or task.outputs["staged"].is_file()
            )

        return complete

    def __call__(self, task: FrameTask[DatasetFrameInput]) -> DatasetFrameStats:
        return stage_frame(task.inputs, task.outputs, self.settings, self.rgb_root)

    def finish(self, summary: RunSummary, tasks: list[FrameTask], out_dir: Path) -> dict:
        """Merge the staged frames into the manifest and parts (with ``--overwrite``, rows of
        frames this run does not build are dropped); the build's totals."""
        t0 = time.perf_counter()
        s = self.settings
        split = s.split_method()
        if self.split_lists is not None:
            split.update(self.split_lists.manifest_dict())
        info = {"created_by": f"sparsetools {__version__}", "sparse_format": s.sparse_format,
                "split": split}  # fmt: skip
        if self.rgb_root is not None:  # --store reference: where each root was at build time
            info["roots"] = {self.rgb_root[0]: self.rgb_root[1]}
        # split files and the tree give each frame its split; fractions split by sequence
        given = None if s.split is not None else {t.inputs.id: t.inputs.split for t in tasks}
        merged = merge_staged(
            out_dir,
            fractions=s.split,
            seed=s.seed,
            assignment=given,
            info=info,
            frames_per_part=self.frames_per_part,
            only={t.inputs.id for t in tasks} if summary.overwrite else None,
            failed={r.frame_id for r in summary.failed},
        )
        linked, stages = 0, {"t_plan": round(self.plan_seconds, 4)}
        sums = dict.fromkeys(STAGES, 0.0)
        for _, x in self.iter_stats(summary):  # one frame's statistics at a time
            linked += x.linked
            for k in STAGES:
                sums[k] += getattr(x, k)
        stages.update({k: round(v, 4) for k, v in sums.items()})
        stages["t_finalize"] = round(time.perf_counter() - t0, 4)
        lists = {}
        if self.split_lists is not None:
            lists = {"split_report": self.split_lists.lines(),
                     "split_lists": self.split_lists.to_dict()}  # fmt: skip
        return {
            **merged,
            "unmatched": dict(self.unmatched),
            **lists,
            "linked": linked,
            "stage_seconds": stages,
            "output": str(out_dir),
        }


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
    official_split: str | None = None,
    seed: int = 0,
    sparse_format: str = "both",
    store: str = "copy",
    link: bool = False,
    source: str = "lidar",
    params: dict | None = None,
    sparse_name: str | None = None,
    gt_name: str | None = None,
    camera: int = 2,
    batch: Batch | None = None,
    frames_per_part: int = 1000,
    param_options: Mapping[str, str] | None = None,
    sample_params: Mapping[str, tuple[tuple[str, object], ...]] | None = None,
    geometry: bool = False,
    store_points: bool = False,
    frame_fields: Mapping[str, Mapping[str, object]] | None = None,
    rgb_root_name: str = "rgb",
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
        The command line's ``--splits``.
    split_files : iterable, optional
        Split lists (``NAME=PATH`` or a path whose name contains train/val/test); frames
        not listed are left out. Exclusive with ``split``.
    official_split : str, optional
        A split list set shipped with sparsetools (``eigen``, ``eigen_full``,
        ``eigen_benchmark``, ``odom``; ``official``, ``mini`` for nuScenes scenes): as
        ``split_files``, with the shipped lists. Exclusive with ``split`` and ``split_files``.
    seed : int
        Split seed.
    sparse_format : {"png", "parquet", "both"}
    store : {"copy", "link", "reference"}
        ``copy`` the input files into the dataset; ``link``: reflink them where the file
        system can (copy-on-write: the dataset never shares an inode with an input), else
        copy them; ``reference``: leave the camera images where they are, recorded in the
        manifest by the root ``rgb_root_name`` (the ``rgb`` folder), their path in it and
        their identity (docs/dataset.md, "Reference mode").
    link : bool
        Deprecated: ``store="link"``.
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
    frames_per_part : int
        Frames per ``sparse/part-*.parquet`` file.
    param_options : mapping of str -> str, optional
        How messages name the keys of ``params`` (a route's options: ``{"sweeps":
        "--sweeps"}``); default ``--params KEY``.
    sample_params : mapping of sample id -> tuple of (name, value), optional
        What varies per sample (a route's ``gt_method``), stored in that row's
        ``generation_params["sample"]``.
    geometry : bool
        Store each sample's ``K``, ``T_cam_lidar`` (and ``baseline_m`` for a KITTI raw stereo
        pair) from its calibration in the manifest (``--store-geometry``).
    store_points : bool
        Store the points too (``--store-points``; routes only: the frames need their
        ``cloud``, given by ``frame_fields``).
    frame_fields : mapping of field -> (mapping of sample id -> value), optional
        Per-frame fields of :class:`~.staging.DatasetFrameInput` a route knows (``cloud``).
    rgb_root_name : str
        Name of the ``rgb`` folder as a root of ``--store reference`` (the routes: ``kitti``).

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
    if link:
        if store not in ("copy", "link"):
            raise ParameterError(f"link=True is store='link': not with store={store!r}")
        store = "link"
    settings = BuildSettings.with_splits(
        split, split_files, official_split=official_split, sparse_format=sparse_format,
        sparse_name=sparse_name,
        gt_name=gt_name, store=store, source=source, params=params, sequence_from=sequence_from,
        seed=seed, geometry=geometry, store_points=store_points,
    )  # fmt: skip
    found = find_build_inputs(
        settings, rgb=rgb, sparse=sparse, gt=gt, confidence=confidence, calib=calib,
        camera=camera,
    )  # fmt: skip
    if frame_fields:
        found = dataclasses.replace(found, frames=[
            dataclasses.replace(x, **{k: v.get(x.id) for k, v in frame_fields.items()})
            for x in found.frames
        ])  # fmt: skip
    if sample_params:
        found = dataclasses.replace(found, frames=[
            dataclasses.replace(x, sample_params=tuple(sample_params.get(x.id, ())))
            for x in found.frames
        ])  # fmt: skip
    job = DatasetJob.for_inputs(settings, found, frames_per_part=frames_per_part,
                                param_options=param_options,
                                rgb_root=(rgb_root_name, found.rgb_root))  # fmt: skip
    return run_job(job, found.frames, out_dir, batch=batch, inputs=found.roots, desc="dataset")


# -- the dataset folder ------------------------------------------------------------------------------
def _check_dataset_folder(out: Path) -> None:
    """Refuse a folder that holds other things than a dataset (new, partial or complete)."""
    if (out / MANIFEST_NAME).is_file() or (out / STAGING).is_dir():
        return
    allowed = ("rgb", SPARSE_DIR, "gt", "confidence", RECORD_DIR, SOURCES_DIR, "points")
    if out.exists() and any(p for p in out.iterdir() if p.name not in allowed):
        raise OutputError(
            f"{out} exists and is not a sparsetools dataset (no {MANIFEST_NAME}); "
            "choose a new or empty folder"
        )


def _check_inputs_outside(out: Path, tasks: list[FrameTask]) -> None:
    """Refuse input files inside the dataset (they would be replaced by copies of themselves,
    then hashed and deleted), except in ``DATASET/.sources/`` (what a one-command route
    prepared)."""
    real_out = out.resolve()
    prepared = real_out / SOURCES_DIR
    folders = {os.path.dirname(os.path.abspath(p)) for t in tasks for p in t.sources}
    for folder in sorted(folders):
        real = Path(folder).resolve()
        if real == prepared or prepared in real.parents:
            continue
        if real == real_out or real_out in real.parents:
            raise OutputError(f"input {folder} is inside the dataset folder {out}")
