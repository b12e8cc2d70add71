"""``dataset info``: what a dataset holds (``dataset verify``, whether it is intact: :mod:`.verify`)."""

from __future__ import annotations

import dataclasses
import json
import os
import stat
import statistics
from collections import Counter, defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from ...errors import FormatError
from ...io.dataset import (
    MANIFEST_NAME,
    ManifestRow,
    read_manifest,
    resolve_in_dataset,
)
from .build import SOURCES_DIR

__all__ = ["DatasetInfo", "SplitCounts", "Spread", "dataset_info"]


# -- info ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Spread:
    """Minimum, median, mean and maximum of a per-sample value (None without samples)."""

    min: float | None = None
    median: float | None = None
    mean: float | None = None
    max: float | None = None

    @classmethod
    def of(cls, values: list[float]) -> Spread:
        if not values:
            return cls()
        return cls(min(values), statistics.median(values), statistics.fmean(values), max(values))


@dataclass(frozen=True)
class SplitCounts:
    """One split of a dataset: its samples, sequences and samples with ground truth."""

    samples: int
    sequences: int
    with_gt: int


@dataclass(frozen=True)
class DatasetInfo:
    """What ``dataset info`` reports: counts, sizes, density, file sizes, schema version.

    ``str(info)`` is the text report, :meth:`to_dict` the JSON one.

    Attributes
    ----------
    dataset : str
    schema_version : int
    created_by : str, optional
        The sparsetools that built the dataset.
    samples, sequences : int
    splits : dict of split -> SplitCounts
    image_sizes, sources : dict of str -> int
        Samples per ``WxH`` image size and per sparse-depth source, most common first.
    with_gt, with_confidence, with_intrinsics : int
        Samples that have them.
    n_sparse : Spread
        Sparse points per sample.
    density_percent : Spread
        Sparse points per 100 pixels.
    bytes : dict of kind -> int
        File sizes per kind: the files the manifest names (``rgb``, ``sparse_png``,
        ``sparse_parquet``, ``gt``, ``confidence``, ``manifest``), then the rest of what is
        on disk in the folder: ``sources`` (what a route staged in ``.sources/``) and
        ``other`` (records, an unfinished build's files, files of others).
    total_bytes : int
        What the folder holds on disk (every regular file once; links not followed).
    missing_files : int
        Files the manifest names that are gone.
    split_method : dict, optional
        How the splits were assigned (the manifest's metadata).
    official_split : str, optional
        The official split whose lists made the splits (``eigen``, ``official``...); None for
        other splits and for datasets made before sparsetools recorded it.
    gt_methods : dict of str -> int
        Samples per ground-truth method (``generation_params["sample"]["gt_method"]`` of the
        one-command routes: ``scan``, ``accumulated(...)``, ``sweeps(N)``...; ``unrecorded``
        for samples with ground truth that do not say), most common first.
    referenced_files, referenced_bytes : int
        Camera images referenced in place (``--store reference``) and their bytes, each file
        once: on disk, but outside the dataset (not in ``total_bytes``).
    missing_references : int
        Referenced images not found (their root not given or moved, or the file gone).
    """

    dataset: str
    schema_version: int | None
    created_by: str | None
    samples: int
    sequences: int
    splits: dict[str, SplitCounts]
    image_sizes: dict[str, int]
    sources: dict[str, int]
    with_gt: int
    with_confidence: int
    with_intrinsics: int
    n_sparse: Spread
    density_percent: Spread
    bytes: dict[str, int]
    total_bytes: int
    missing_files: int
    split_method: dict | None
    official_split: str | None = None
    gt_methods: dict[str, int] = dataclasses.field(default_factory=dict)
    referenced_files: int = 0
    referenced_bytes: int = 0
    missing_references: int = 0

    def to_dict(self) -> dict:
        """The report as JSON values (``dataset info --json``)."""
        return dataclasses.asdict(self)

    def format(self) -> str:
        """The report as aligned ``name  value`` lines (``dataset info``)."""
        lines = [
            ("dataset", self.dataset),
            ("schema version", self.schema_version),
            ("created by", self.created_by),
            ("samples", f"{self.samples} in {self.sequences} sequence(s)"),
        ]
        for name, s in self.splits.items():
            lines.append(
                (
                    f"  {name}",
                    f"{s.samples} sample(s), {s.sequences} sequence(s), {s.with_gt} with gt",
                )
            )
        if isinstance(self.split_method, dict):
            lines.append(("split by", _split_text(self.split_method)))
        if self.gt_methods and set(self.gt_methods) != {"unrecorded"}:
            lines.append(
                ("gt methods", ", ".join(f"{k} ({v})" for k, v in self.gt_methods.items()))
            )
        lines += [
            ("image sizes", ", ".join(f"{k} ({v})" for k, v in self.image_sizes.items())),
            ("sources", ", ".join(f"{k} ({v})" for k, v in self.sources.items())),
            (
                "with gt / confidence / intrinsics",
                f"{self.with_gt} / {self.with_confidence} / {self.with_intrinsics}",
            ),
        ]
        n, dens = self.n_sparse, self.density_percent
        if n.mean is not None:
            lines.append(("sparse points", f"mean {n.mean:.1f}, min {n.min:.0f}, max {n.max:.0f}"))
            lines.append(
                (
                    "density %",
                    f"min {dens.min:.4g}, median {dens.median:.4g}, mean {dens.mean:.4g}, "
                    f"max {dens.max:.4g}",
                )
            )
        sizes = ", ".join(f"{k} {_human(v)}" for k, v in self.bytes.items())
        if self.referenced_files or self.missing_references:
            lines.append(("size in the dataset", f"{_human(self.total_bytes)} ({sizes})"))
            missing = (f", {self.missing_references} not found (run 'dataset verify')"
                       if self.missing_references else "")  # fmt: skip
            lines.append(("size referenced", f"{_human(self.referenced_bytes)} "
                          f"({self.referenced_files} image(s) kept in place{missing})"))  # fmt: skip
        else:
            lines.append(("size", f"{_human(self.total_bytes)} ({sizes})"))
        if self.missing_files:
            lines.append(("missing files", f"{self.missing_files} (run 'dataset verify')"))
        width = max(len(k) for k, _ in lines)
        return "\n".join(f"{k:<{width}}  {v}" for k, v in lines)

    __str__ = format


def _split_text(method: dict) -> str:
    """How the splits were made, in words (``official split eigen (train kitti/...)``); the
    manifest's record is read as text, whatever it holds."""
    kind = method.get("method")
    if kind == "official":
        files = method.get("files")
        files = ", ".join(f"{k} {v}" for k, v in files.items()) if isinstance(files, dict) else ""
        return f"official split {method.get('name')} ({files})"
    if kind == "sequence":
        fractions = method.get("fractions")
        if isinstance(fractions, dict):
            fractions = ", ".join(f"{k} {v}" for k, v in fractions.items())
        return f"sequence ({fractions}; seed {method.get('seed')})"
    if kind == "split-file":
        return (
            f"split files ({method.get('listed')} lines, {method.get('missing')} matching no frame)"
        )
    return str(kind)


def _human(n: float) -> str:
    """A byte count in B, KB, MB or GB (powers of 1024)."""
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)  # pragma: no cover


_FILE_KINDS = (
    ("rgb", "rgb_path"),
    ("sparse_png", "sparse_path"),
    ("gt", "gt_path"),
    ("confidence", "confidence_path"),
)


def dataset_info(
    path: str | os.PathLike, *, roots: Mapping[str, str | os.PathLike] | None = None
) -> DatasetInfo:
    """Counts per split, image sizes, density statistics, file sizes and the schema version.

    ``roots``: where the roots of referenced images are now (as
    :class:`~sparsetools.io.dataset_reader.DatasetReader`'s); their bytes are counted apart.
    """
    from ...io.dataset_reader import resolve_rgb, sample_roots

    root = Path(path)
    table, info = read_manifest(root / MANIFEST_NAME)
    rows = ManifestRow.from_table(table)
    where = sample_roots(info, roots)
    per_split: dict[str, SplitCounts] = {}
    for name in sorted({r.split for r in rows}, key=str):
        sub = [r for r in rows if r.split == name]
        per_split[str(name)] = SplitCounts(
            samples=len(sub),
            sequences=len({r.sequence for r in sub}),
            with_gt=sum(r.gt_path is not None for r in sub),
        )
    sizes = Counter(f"{r.width}x{r.height}" for r in rows)
    bytes_by_kind: dict[str, int] = defaultdict(int)
    counted: set[str] = set()
    missing = 0

    def count(kind: str, rel: str) -> None:
        nonlocal missing
        try:
            p = resolve_in_dataset(root, rel)
            size = p.stat().st_size
        except OSError:
            missing += 1
            return
        if os.path.realpath(p) not in counted:  # a file named twice is on disk once
            counted.add(os.path.realpath(p))
            bytes_by_kind[kind] += size

    ref_seen: set[str] = set()
    ref_bytes = ref_missing = 0
    for r in rows:
        for kind, col in _FILE_KINDS:
            rel = getattr(r, col)
            if rel is None:
                continue
            if col == "rgb_path" and r.rgb_root is not None:
                try:
                    p = os.path.realpath(resolve_rgb(root, r, where))
                    size = os.stat(p).st_size
                except (FormatError, OSError):
                    ref_missing += 1
                    continue
                if p not in ref_seen:
                    ref_seen.add(p)
                    ref_bytes += size
                continue
            count(kind, rel)
    for rel in sorted({r.sparse_parquet for r in rows if r.sparse_parquet is not None}):
        count("sparse_parquet", rel)
    count("manifest", MANIFEST_NAME)
    for kind, size in _unlisted_bytes(root, counted).items():
        bytes_by_kind[kind] += size
    split = info.get("split")
    return DatasetInfo(
        dataset=str(root),
        schema_version=info.get("schema_version"),
        created_by=info.get("created_by"),
        samples=table.num_rows,
        sequences=len({r.sequence for r in rows}),
        splits=per_split,
        image_sizes=dict(sizes.most_common()),
        sources=dict(Counter(r.source for r in rows).most_common()),
        with_gt=sum(r.gt_path is not None for r in rows),
        with_confidence=sum(r.confidence_path is not None for r in rows),
        with_intrinsics=sum(r.fx is not None for r in rows),
        n_sparse=Spread.of([float(r.n_sparse) for r in rows]),
        density_percent=Spread.of([100.0 * r.density for r in rows]),
        bytes=dict(bytes_by_kind),
        total_bytes=int(sum(bytes_by_kind.values())),
        missing_files=missing,
        split_method=split,
        official_split=str(split["name"])
        if isinstance(split, dict) and split.get("method") == "official" and "name" in split
        else None,
        gt_methods=dict(
            Counter(_gt_method(r) for r in rows if r.gt_path is not None).most_common()
        ),
        referenced_files=len(ref_seen),
        referenced_bytes=ref_bytes,
        missing_references=ref_missing,
    )


#: Ground truth of a route's rows that record no ``gt_method``: ``dataset kitti-raw``'s default
#: (and every version before 0.3) projects one scan, ``kitti-dc`` stores KITTI's annotation.
_ROUTE_GT = {"kitti-raw": "scan", "kitti-dc": "annotated"}


def _gt_method(row) -> str:
    """A row's ``generation_params["sample"]["gt_method"]``; else what its route's ground
    truth is (:data:`_ROUTE_GT`), else ``unrecorded``."""
    try:
        params = json.loads(row.generation_params or "{}")
        method = params.get("sample", {}).get("gt_method")
        route = params.get("params", {}).get("route")
    except (ValueError, AttributeError):
        method = route = None
    if isinstance(method, str):
        return method
    return _ROUTE_GT.get(route, "unrecorded") if isinstance(route, str) else "unrecorded"


def _unlisted_bytes(root: Path, counted: set[str]) -> dict[str, int]:
    """Bytes of the regular files under ``root`` that the manifest does not name (links not
    followed): ``sources``, what a route staged in ``DATASET/.sources/`` (reused by its
    reruns), and ``other`` (the build's records, files left by an unfinished build, files
    of others)."""
    out: dict[str, int] = {}
    sources = root / SOURCES_DIR
    for folder, _, files in os.walk(root):
        kind = "sources" if Path(folder) == sources or sources in Path(folder).parents else "other"
        for name in files:
            p = os.path.join(folder, name)
            try:
                st = os.lstat(p)
            except OSError:
                continue
            if stat.S_ISREG(st.st_mode) and os.path.realpath(p) not in counted:
                out[kind] = out.get(kind, 0) + st.st_size
    return out


# -- verify ----------------------------------------------------------------------------------------
