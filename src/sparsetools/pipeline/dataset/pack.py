"""``dataset pack``: a dataset that references its camera images in place (``--store
reference``) turned into a self-contained one, as ``--store copy`` would have written it.

Per sample (:class:`PackJob`, one :class:`~sparsetools.pipeline.core.FrameTask` each, through
:func:`~sparsetools.pipeline.core.run_job`): every file of the sample is copied into ``-o``
-- the referenced image from its root to ``rgb/<id><suffix>``, the sparse PNG, ground truth
and confidence from the dataset -- each checked against its identity in the manifest (size
and SHA-256) before it is written, atomically. Then (:meth:`PackJob.finish`) the Parquet
parts are copied and the manifest written last, with the rows of a copy build: ``rgb_path``
inside the dataset, ``rgb_root`` / ``rgb_size`` / ``rgb_mtime_ns`` empty (a version-2
manifest when nothing is referenced any more), and no ``roots`` in the build information.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from ...errors import FormatError, OutputError
from ...io.atomic import atomic_write_bytes
from ...io.containment import ContainedPaths
from ...io.dataset import (
    MANIFEST_NAME,
    ManifestRow,
    bytes_sha256,
    check_relative_path,
    read_manifest,
    resolve_in_dataset,
)
from ...io.manifest_writer import write_manifest
from ...io.provenance import RECORD_DIR, RUN_FILE
from ..batch import Batch, RunSummary
from ..core import BatchJob, FrameStats, FrameTask, run_job

__all__ = ["PackJob", "PackStats", "pack_dataset", "pack_plan", "packed_row"]

#: The files of a sample other than its image: column of the path, column of the hash.
_OWN_FILES = (
    ("sparse", "sparse_path", "sparse_sha256"),
    ("gt", "gt_path", "gt_sha256"),
    ("confidence", "confidence_path", "confidence_sha256"),
)


def packed_row(row: ManifestRow) -> ManifestRow:
    """The row of a sample whose image is in the dataset, as ``--store copy`` writes it:
    ``rgb/<id><suffix>`` (the suffix lower-case), no root, no recorded identity."""
    if row.rgb_root is None:
        return row
    suffix = PurePosixPath(row.rgb_path).suffix.lower()
    rel = check_relative_path(f"rgb/{row.id}{suffix}", what=f"sample '{row.id}'")
    return dataclasses.replace(row, rgb_path=rel, rgb_root=None, rgb_size=None, rgb_mtime_ns=None)


@dataclass(frozen=True)
class PackInput:
    """One sample: its manifest row and where each of its files is now (by role)."""

    row: ManifestRow
    files: tuple[tuple[str, str], ...]


@dataclass(frozen=True)
class PackStats(FrameStats):
    """One sample packed: bytes copied, of them the referenced image's."""

    bytes: int
    referenced_bytes: int


@dataclass(frozen=True)
class PackJob(BatchJob[PackInput]):
    """``dataset pack``: copy each sample's files into ``-o`` (checked against the manifest),
    then the parts and the manifest (:meth:`finish`).

    Attributes
    ----------
    dataset : str
        The dataset packed (absolute).
    roots : tuple of (name, path)
        Where each root of referenced images is (the recorded paths, or ``--root``); not
        recorded: moving a tree does not change what is packed.
    """

    command = "dataset pack"
    noun = "a packed dataset"
    stats_type = PackStats

    dataset: str
    roots: tuple[tuple[str, str], ...] = field(default=(), metadata={"provenance": False})

    def record(self) -> Mapping:
        return {"dataset": self.dataset}

    def tasks(self, frames: list[PackInput], out_dir: Path) -> list[FrameTask[PackInput]]:
        if os.path.realpath(out_dir) == os.path.realpath(self.dataset):
            raise OutputError(f"{out_dir} is the dataset itself: give another -o")
        if (
            any(p.name != RECORD_DIR for p in out_dir.iterdir())
            and not (out_dir / RECORD_DIR / RUN_FILE).is_file()
        ):
            raise OutputError(
                f"{out_dir} is not empty and was not written by dataset pack: choose a new or "
                "empty folder"
            )
        tasks = []
        for x in frames:
            r = packed_row(x.row)
            outputs = {"rgb": out_dir / r.rgb_path}
            for role, col, _ in _OWN_FILES:
                rel = getattr(r, col)
                if rel is not None:
                    outputs[role] = out_dir / rel
            sources = tuple(Path(p) for _, p in x.files)
            tasks.append(FrameTask(r.id, x, outputs, sources))
        return tasks

    def shared_outputs(self, out_dir: Path) -> tuple[Path, ...]:
        return (out_dir / MANIFEST_NAME,)

    def __call__(self, task: FrameTask[PackInput]) -> PackStats:
        r = task.inputs.row
        files = dict(task.inputs.files)
        expected = {"rgb": (r.rgb_sha256, r.rgb_size)}
        for role, _, sha_col in _OWN_FILES:
            expected[role] = (getattr(r, sha_col), None)
        data_of = {}
        for role in task.outputs:  # read and check every file before writing any
            src = files[role]
            try:
                data = Path(src).read_bytes()
            except OSError as exc:
                raise FormatError(
                    f"sample '{r.id}': cannot read {src} ({exc.strerror or exc})"
                ) from exc
            sha, size = expected[role]
            if size is not None and len(data) != size:
                raise FormatError(
                    f"sample '{r.id}': {src} is {len(data)} bytes, the manifest recorded "
                    f"{size}: it changed since the build (dataset verify)"
                )
            if sha is not None and bytes_sha256(data) != sha:
                raise FormatError(
                    f"sample '{r.id}': {src} changed since the build (sha256 differs from the "
                    "manifest; dataset verify)"
                )
            data_of[role] = data
        for role, data in data_of.items():  # outputs checked contained by run_job
            atomic_write_bytes(task.outputs[role], data)
        ref = len(data_of["rgb"]) if r.rgb_root is not None else 0
        return PackStats(bytes=sum(len(d) for d in data_of.values()), referenced_bytes=ref)

    def finish(self, summary: RunSummary, tasks: list[FrameTask], out_dir: Path) -> dict:
        """Copy the sparse parts (byte for byte) and write the manifest, last."""
        src = Path(self.dataset)
        table, info = read_manifest(src / MANIFEST_NAME)
        rows = [packed_row(r) for r in ManifestRow.from_table(table)]
        done = {t.inputs.row.id for t in tasks}
        if summary.failed or {r.id for r in rows} != done:
            return {"output": str(out_dir), "manifest_written": False}
        contained = ContainedPaths(out_dir)
        parts = sorted({r.sparse_parquet for r in rows if r.sparse_parquet is not None})
        copied = 0
        for rel in parts:
            data = resolve_in_dataset(src, rel, what="sparse_parquet").read_bytes()
            atomic_write_bytes(contained.check(out_dir / rel), data)
            copied += len(data)
        info = {k: v for k, v in info.items() if k not in ("schema_version", "roots")}
        write_manifest(contained.check(out_dir / MANIFEST_NAME), ManifestRow.to_table(rows),
                       info=info)  # fmt: skip
        stats = self.stats(summary)
        return {
            "samples": len(rows),
            "referenced_images": sum(1 for x in stats if x.referenced_bytes),
            "bytes": sum(x.bytes for x in stats) + copied,
            "referenced_bytes": sum(x.referenced_bytes for x in stats),
            "parts": len(parts),
            "output": str(out_dir),
            "manifest_written": True,
        }


def pack_plan(
    dataset: str | os.PathLike, *, roots: Mapping[str, str | os.PathLike] | None = None
) -> tuple[PackJob, list[PackInput], list[Path]]:
    """The job packing ``dataset``, its samples (each file located: a referenced image in its
    root, :func:`~sparsetools.io.dataset_reader.resolve_rgb`) and the input folders (``-o``
    may not be inside one), for :func:`~sparsetools.pipeline.core.run_job`.

    Raises
    ------
    FormatError
        A referenced image cannot be found (root unknown or moved, file gone) or its
        reference leaves its root.
    """
    from ...io.dataset_reader import resolve_rgb, sample_roots

    src = Path(dataset).absolute()
    table, info = read_manifest(src / MANIFEST_NAME)
    where = sample_roots(info, roots)
    frames = []
    for r in ManifestRow.from_table(table):
        files = [("rgb", str(resolve_rgb(src, r, where)))]
        for role, col, _ in _OWN_FILES:
            rel = getattr(r, col)
            if rel is not None:
                files.append((role, str(resolve_in_dataset(src, rel, what=col))))
        frames.append(PackInput(r, tuple(files)))
    job = PackJob(str(src), tuple(sorted((k, str(v)) for k, v in where.items())))
    return job, frames, [src, *(p for p in where.values() if p.is_dir())]


def pack_dataset(
    dataset: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    roots: Mapping[str, str | os.PathLike] | None = None,
    batch: Batch | None = None,
) -> RunSummary:
    """Pack a dataset into ``out_dir``: every referenced image copied in, every file checked
    against the manifest, the manifest rewritten as ``--store copy`` writes it.

    Parameters
    ----------
    dataset : path-like
        A dataset folder (one without references is copied as it is).
    out_dir : path-like
        The packed dataset (created; a non-empty folder that ``dataset pack`` did not write is
        refused, unless ``batch.overwrite``).
    roots : mapping of str -> path-like, optional
        Where the roots of referenced images are now (default: the paths the build recorded).
    batch : Batch, optional

    Raises
    ------
    FormatError
        A referenced image is missing, or differs from the manifest (size or SHA-256).
    """
    job, frames, inputs = pack_plan(dataset, roots=roots)
    return run_job(job, frames, out_dir, batch=batch or Batch(), inputs=inputs, desc="pack")
