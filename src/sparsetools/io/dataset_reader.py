"""Reading a sparsetools dataset: :class:`DatasetReader` (manifest + PNG / Parquet samples).

The on-disk format is :mod:`sparsetools.io.dataset`.
"""

from __future__ import annotations

import bisect
import os
from collections import OrderedDict
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..errors import FormatError, ParameterError
from .dataset import (
    MANIFEST_NAME,
    PART_SCHEMA,
    ManifestRow,
    brief_error,
    depth_to_points,
    points_to_depth,
    read_manifest,
    resolve_in_dataset,
    resolve_reference,
)
from .dataset_parts import part_rows
from .depth_files import read_confidence_file, read_depth_file
from .image import read_depth_png, read_image

__all__ = ["DatasetReader", "resolve_rgb", "sample_roots"]


def sample_roots(info: dict, given: Mapping[str, str | os.PathLike] | None) -> dict[str, Path]:
    """The roots of a dataset's referenced files: those its manifest recorded at build time
    (``info["roots"]``), overridden by ``given`` (the tree moved)."""
    from .dataset import check_root_name

    roots = {k: Path(v) for k, v in (info.get("roots") or {}).items()}
    for name, path in (given or {}).items():
        roots[check_root_name(name, what="roots")] = Path(path)
    return roots


def resolve_rgb(dataset: Path, row: ManifestRow, roots: Mapping[str, Path]) -> Path:
    """The camera image of a row: in the dataset, or referenced in place (``rgb_root``).

    Raises
    ------
    FormatError
        One line naming the sample and the root option: the root is unknown or not where it
        was, the file is missing, or its reference would leave the root.
    """
    if row.rgb_root is None:
        return resolve_in_dataset(dataset, row.rgb_path, what="rgb_path")
    name = row.rgb_root
    hint = f"give its place: roots={{'{name}': PATH}} (--root {name}=PATH)"
    root = roots.get(name)
    if root is None:
        raise FormatError(
            f"sample '{row.id}': its image is in root '{name}', which the manifest does not "
            f"record; {hint}"
        )
    if not root.is_dir():
        raise FormatError(f"sample '{row.id}': root '{name}' is not at {root} (moved?); {hint}")
    path = resolve_reference(root, row.rgb_path, name=name, sample=row.id)
    if not path.is_file():
        raise FormatError(
            f"sample '{row.id}': its image {row.rgb_path} is missing from root '{name}' "
            f"({root}); {hint}"
        )
    return path


class _PartCache:
    """Random access to rows of sparse parts: open files and a few decoded row groups."""

    def __init__(self, max_groups: int = 4):
        self.files: dict[Path, tuple[pq.ParquetFile, list[int]]] = {}
        self.groups: OrderedDict[tuple[Path, int], list] = OrderedDict()
        self.max_groups = max_groups

    def row(self, path: Path, row: int):
        if path not in self.files:
            try:
                pf = pq.ParquetFile(path)
            except (pa.ArrowException, OSError) as exc:
                raise FormatError(
                    f"{path}: cannot read the sparse part ({brief_error(exc)})"
                ) from exc
            starts = [0]
            for g in range(pf.num_row_groups):
                starts.append(starts[-1] + pf.metadata.row_group(g).num_rows)
            self.files[path] = (pf, starts)
        pf, starts = self.files[path]
        if not 0 <= row < starts[-1]:
            raise FormatError(f"{path}: no row {row} (the part has {starts[-1]} rows)")
        g = bisect.bisect_right(starts, row) - 1
        key = (path, g)
        rows = self.groups.get(key)
        if rows is None:
            try:
                table = pf.read_row_group(g, columns=PART_SCHEMA.names).cast(PART_SCHEMA)
                table.validate(full=True)
            except (pa.ArrowException, OSError) as exc:
                raise FormatError(
                    f"{path}: cannot decode row group {g} ({brief_error(exc)})"
                ) from exc
            rows = list(part_rows(table))
            self.groups[key] = rows
            while len(self.groups) > self.max_groups:
                self.groups.popitem(last=False)
        else:
            self.groups.move_to_end(key)
        return rows[row - starts[g]]


# -- reader --------------------------------------------------------------------------------------
class DatasetReader:
    """Read a sparsetools dataset sample by sample (the base of the training Dataset).

    Parameters
    ----------
    path : path-like
        The dataset folder (holding ``manifest.parquet``).
    split : str, optional
        Only the samples of this split (same as ``DatasetReader(path).split(name)``).
    roots : mapping of str -> path-like, optional
        Where the roots of referenced images are now (``{"kitti": "/new/place"}``),
        overriding the paths the manifest recorded at build time (``--store reference``,
        docs/dataset.md "Reference mode").

    Attributes
    ----------
    root : Path
    manifest : pyarrow.Table
        The manifest rows of this reader (of its split only, when one is chosen).
    info : dict
        ``schema_version`` and the build information from the manifest metadata.
    roots : dict of str -> Path
        The roots referenced images are read from.

    Notes
    -----
    The reader is cheap to pickle (open files and caches are dropped), so a torch
    ``Dataset`` can hold one and be used with ``DataLoader(num_workers=N)``.

    Examples
    --------
    >>> ds = DatasetReader("out/dataset").split("train")      # doctest: +SKIP
    >>> s = ds.sample(0)                                        # doctest: +SKIP
    >>> s["rgb"].shape, s["sparse"].dtype, s["intrinsics"]      # doctest: +SKIP
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        split: str | None = None,
        roots: Mapping[str, str | os.PathLike] | None = None,
    ):
        self.root = Path(path)
        table, info = read_manifest(self.root / MANIFEST_NAME)
        self.roots = sample_roots(info, roots)
        self._init(table, info, split)

    def _init(self, table: pa.Table, info: dict, split: str | None) -> None:
        self._all = table
        self.info = info
        if split is not None:
            names = sorted({s for s in table.column("split").to_pylist() if s is not None})
            if split not in names:
                raise ParameterError(
                    f"no split '{split}' in {self.root} (has: {', '.join(names) or 'none'})"
                )
            import pyarrow.compute as pc

            table = table.filter(pc.equal(table.column("split"), split))
        self.split_name = split
        self.manifest = table
        self._rows = ManifestRow.from_table(table)
        self._index = {r.id: i for i, r in enumerate(self._rows)}
        self._by_frame: dict[tuple[str, str], list[int]] = {}
        for i, r in enumerate(self._rows):
            self._by_frame.setdefault((r.sequence, r.frame), []).append(i)
        self._parts = _PartCache()
        self._points_tables: dict = {}

    # -- container protocol
    def __len__(self) -> int:
        return len(self._rows)

    def __iter__(self) -> Iterator[dict]:
        for i in range(len(self)):
            yield self.sample(i)

    def __getitem__(self, key: int | str) -> dict:
        return self.sample(key)

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_parts"] = None
        state["_points_tables"] = {}
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._parts = _PartCache()
        self._points_tables: dict = {}

    def __repr__(self) -> str:
        where = f", split={self.split_name!r}" if self.split_name else ""
        return f"DatasetReader({str(self.root)!r}{where}, samples={len(self)})"

    # -- views
    @property
    def ids(self) -> list[str]:
        return [r.id for r in self._rows]

    @property
    def splits(self) -> list[str]:
        """Names of the splits present in the whole dataset."""
        return sorted({s for s in self._all.column("split").to_pylist() if s is not None})

    def split(self, name: str) -> DatasetReader:
        """A reader over the samples of split ``name`` only."""
        view = object.__new__(DatasetReader)
        view.root = self.root
        view.roots = self.roots
        view._init(self._all, self.info, name)
        return view

    def row(self, key: int | str) -> ManifestRow:
        """The manifest row of a sample (by position or id)."""
        if isinstance(key, str):
            if key not in self._index:
                raise ParameterError(f"no sample '{key}' in {self}")
            return self._rows[self._index[key]]
        i = int(key)
        if not -len(self) <= i < len(self):
            raise IndexError(f"sample {i} out of range ({len(self)} samples)")
        return self._rows[i]

    def path(self, rel: str, *, what: str = "path") -> Path:
        """Absolute path of a manifest path, refusing anything outside the dataset."""
        return resolve_in_dataset(self.root, rel, what=what)

    def rgb_path(self, key: int | str) -> Path:
        """The camera image file of a sample: in the dataset, or where its reference points
        (:func:`resolve_rgb`)."""
        return resolve_rgb(self.root, self.row(key), self.roots)

    # -- data
    def sparse_points(self, key: int | str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, depth) of a sample's sparse depth (uint16, uint16, float32 metres)."""
        r = self.row(key)
        if r.sparse_parquet is not None:
            fid, u, v, d, h, w = self._parts.row(
                self.path(r.sparse_parquet, what="sparse_parquet"), int(r.sparse_row)
            )
            if fid != r.id or (h, w) != (r.height, r.width):
                raise FormatError(
                    f"{r.sparse_parquet} row {r.sparse_row} holds '{fid}' ({w}x{h}), "
                    f"expected '{r.id}' ({r.width}x{r.height})"
                )
            return u, v, d
        return depth_to_points(self._read_sparse_png(r))

    def _read_sparse_png(self, r: ManifestRow) -> np.ndarray:
        if r.sparse_path is None:
            raise FormatError(f"sample '{r.id}' has no sparse depth")
        return self._checked(
            read_depth_png(self.path(r.sparse_path, what="sparse_path")), r, "sparse"
        )

    @staticmethod
    def _checked(arr: np.ndarray, r: ManifestRow, what: str) -> np.ndarray:
        if arr.shape[:2] != (r.height, r.width):
            raise FormatError(
                f"sample '{r.id}': {what} is {arr.shape[1]}x{arr.shape[0]}, "
                f"the manifest says {r.width}x{r.height}"
            )
        return arr

    def sample(self, key: int | str) -> dict:
        """Load one sample.

        Parameters
        ----------
        key : int or str
            Position in this reader, or sample id.

        Returns
        -------
        dict
            ``id``, ``sequence``, ``frame``, ``split`` (str);
            ``rgb`` (H, W, 3) uint8;
            ``sparse`` (H, W) float32 metres, 0 = empty (from the Parquet points when
            present: bit-exact, else from the PNG);
            ``gt`` (H, W) float32 metres or None; ``confidence`` (H, W) float32 or None;
            ``intrinsics`` (3, 3) float64 K or None (the ``K`` column when stored, else
            from fx, fy, cx, cy);
            ``camera`` (str or None: the rig's camera in a dataset of several);
            the geometry where stored, else None (datasets built without it, schema 2):
            ``T_cam_lidar``, ``T_ego_cam``, ``T_world_ego``, ``T_world_cam`` (4, 4) float64
            and ``baseline_m`` (float, metres); see :meth:`geometry`.
        """
        r = self.row(key)
        rgb = self._checked(read_image(resolve_rgb(self.root, r, self.roots)), r, "rgb")
        if r.sparse_parquet is not None:
            u, v, d = self.sparse_points(key)
            sparse = points_to_depth(u, v, d, r.height, r.width)
        else:
            sparse = self._read_sparse_png(r)
        gt = None
        if r.gt_path is not None:
            gt = self._checked(read_depth_file(self.path(r.gt_path, what="gt_path")), r, "gt")
        confidence = None
        if r.confidence_path is not None:
            confidence = self._checked(
                read_confidence_file(self.path(r.confidence_path, what="confidence_path")),
                r,
                "confidence",
            )
        return {
            "id": r.id,
            "sequence": r.sequence,
            "frame": r.frame,
            "split": r.split,
            "camera": r.camera,
            "rgb": rgb,
            "sparse": sparse,
            "gt": gt,
            "confidence": confidence,
            **self.geometry(key),
        }

    def geometry(self, key: int | str) -> dict:
        """A sample's geometry from its manifest row (no file is read).

        Returns
        -------
        dict
            ``intrinsics`` (3, 3) float64 K in pixels: the ``K`` column when stored, else
            built from fx, fy, cx, cy, else None;
            ``T_cam_lidar`` (sensor -> camera), ``T_ego_cam`` (camera -> ego),
            ``T_world_ego`` (ego -> world), ``T_world_cam`` (camera -> world): (4, 4)
            float64, metres, or None where the dataset does not store them;
            ``baseline_m``: float or None.
        """
        r = self.row(key)
        K = None
        if r.K is not None:
            K = np.array(r.K, dtype=np.float64).reshape(3, 3)
        elif r.fx is not None:
            K = np.array(
                [[r.fx, 0.0, r.cx], [0.0, r.fy, r.cy], [0.0, 0.0, 1.0]],
                dtype=np.float64,
            )
        out = {"intrinsics": K}
        for name in ("T_cam_lidar", "T_ego_cam", "T_world_ego", "T_world_cam"):
            m = getattr(r, name)
            out[name] = None if m is None else np.array(m, dtype=np.float64).reshape(4, 4)
        out["baseline_m"] = r.baseline_m
        return out

    def samples(self, keys: Sequence[int | str]) -> list[dict]:
        return [self.sample(k) for k in keys]

    def points(self, key: int | str) -> tuple[np.ndarray, np.ndarray | None]:
        """A sample's stored points (``--store-points``): the sensor's points that land in
        its image, in the camera frame.

        Returns
        -------
        xyz : (N, 3) float64
            Metres, ``T_cam_lidar @ x_sensor``: ``K @ xyz.T`` projects them to this image.
        ring : (N,) int16 or None
            Each point's laser (0 = highest), None when unknown.

        Raises
        ------
        FormatError
            The sample has no stored points, or its part does not hold it.
        """
        r = self.row(key)
        if r.points_parquet is None:
            raise FormatError(f"sample '{r.id}' has no stored points (build with --store-points)")
        path = self.path(r.points_parquet, what="points_parquet")
        one = self._points_row(path, int(r.points_row))
        if one.column("id")[0].as_py() != r.id:
            raise FormatError(
                f"{r.points_parquet} row {r.points_row} does not hold sample '{r.id}'"
            )
        xyz = np.stack(
            [one.column(c).combine_chunks().values.to_numpy() for c in ("x", "y", "z")], axis=1
        )
        ring = one.column("ring")
        ring = None if ring.null_count else ring.combine_chunks().values.to_numpy()
        return xyz, ring

    def _points_row(self, path: Path, row: int) -> pa.Table:
        """One row of a points part, reading only its row group (one group cached: a part
        holds up to 100 samples of about 0.5 MB each)."""
        from .dataset import POINTS_SCHEMA

        cache = self._points_tables
        try:
            if cache.get("path") != path:
                pf = pq.ParquetFile(path)
                starts = [0]
                for g in range(pf.num_row_groups):
                    starts.append(starts[-1] + pf.metadata.row_group(g).num_rows)
                cache.clear()
                cache.update(path=path, file=pf, starts=starts)
            starts = cache["starts"]
            if not 0 <= row < starts[-1]:
                raise FormatError(f"{path}: no row {row} (the part has {starts[-1]} rows)")
            g = bisect.bisect_right(starts, row) - 1
            if cache.get("group") != g:
                table = cache["file"].read_row_group(g, columns=POINTS_SCHEMA.names)
                table = table.cast(POINTS_SCHEMA)
                table.validate(full=True)
                cache.update(group=g, table=table)
        except (pa.ArrowException, OSError) as exc:
            cache.clear()
            raise FormatError(f"{path}: cannot read the points part ({brief_error(exc)})") from exc
        return cache["table"].slice(row - starts[g], 1)

    def camera_ids(self, key: int | str) -> dict[str | None, str]:
        """The ids of the cameras of a sample's frame, by camera: every row of this reader
        with the same sequence and frame (``{None: id}`` in a one-camera dataset)."""
        r = self.row(key)
        return {self._rows[i].camera: self._rows[i].id for i in self._by_frame[r.sequence, r.frame]}

    def cameras(self, key: int | str) -> dict[str | None, dict]:
        """The samples of every camera of a sample's frame, by camera name.

        ``reader.cameras("drive/image_02/0000000005")`` gives ``{"image_02": {...},
        "image_03": {...}}`` (each as :meth:`sample`); the rows of one frame are those with
        the same ``sequence`` and ``frame``. In a one-camera dataset the key is None.
        """
        return {cam: self.sample(fid) for cam, fid in self.camera_ids(key).items()}

    def frames(self) -> list[tuple[str, str]]:
        """The (sequence, frame) pairs of this reader, in the order of their first row: one
        per frame however many cameras it has (iterate these to train on whole rigs)."""
        return list(self._by_frame)
