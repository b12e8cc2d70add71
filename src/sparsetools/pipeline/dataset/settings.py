"""What a dataset's samples depend on (:class:`BuildSettings`): compared on every run that
adds to the dataset."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from ...errors import ParameterError
from ...validate import check_choice, check_int_range
from .official_splits import official_split
from .splits import DEFAULT_SPLIT, parse_split_fractions, sequence_resolver

__all__ = ["SPARSE_FORMATS", "STORE_MODES", "BuildSettings"]

SPARSE_FORMATS = ("png", "parquet", "both")
#: How a build stores the camera images (``--store``): copied, reflinked where the file
#: system can (else copied), or referenced in place (a root name, a path, its identity).
STORE_MODES = ("copy", "link", "reference")


@dataclass(frozen=True)
class BuildSettings:
    """What a dataset's samples depend on: recorded, and compared on every run that adds to it.

    Attributes
    ----------
    sparse_format : {"png", "parquet", "both"}
    sparse_name, gt_name : str, optional
        KITTI depth-completion map sets of the sparse input and the ground truth.
    store : {"copy", "link", "reference"}
        ``copy`` the input files into the dataset; ``link``: reflink them where the file
        system can (else copy); ``reference``: keep the camera images where they are and
        record them (root name, relative path, identity) in the manifest; the other files
        are copied.
    source : str
        Sensor of the sparse depth (``lidar``, ``lidar-4beam``, ``radar``...).
    params : dict, optional
        Generation parameters stored (as JSON) in every new row.
    sequence_from : str
        ``parent`` or ``regex:PATTERN`` (see :func:`.splits.sequence_resolver`).
    split : mapping of split -> fraction, optional
        Fractions of the sequences per split (``--splits``). None: the split comes from
        ``split_files``, or without them from the inputs' tree (``--splits tree``).
    split_files : tuple, optional
        Split lists, each a path or a ``(name, path)`` pair (``--split-file``).
    seed : int
        Seed of the split assignment.
    official_split : str, optional
        A split shipped with sparsetools (``--split eigen``, see :mod:`.official_splits`):
        its lists give each frame's split. Recorded only when given, so that a dataset made
        before it existed resumes.
    geometry : bool
        Store each sample's geometry (``K``, ``T_cam_lidar``, ``baseline_m`` from its
        calibration; the route's ``T_ego_cam`` / ``T_world_ego``) in the manifest's optional
        columns (``--store-geometry``). Recorded only when on.
    store_points : bool
        Store each sample's sensor points in the camera frame in ``points/part-*.parquet``
        (``--store-points``; implies ``geometry``). Recorded only when on.
    """

    sparse_format: str = "both"
    sparse_name: str | None = None
    gt_name: str | None = None
    store: str = field(default="copy", metadata={"option": "--store"})
    source: str = "lidar"
    params: dict | None = None
    sequence_from: str = "parent"
    split: Mapping[str, float] | None = field(
        default_factory=lambda: dict(DEFAULT_SPLIT), metadata={"option": "--splits"}
    )
    split_files: tuple | None = field(default=None, metadata={"option": "--split-file"})
    seed: int = 0
    official_split: str | None = field(default=None, metadata={"option": "--split"})
    store_points: bool = field(
        default=False, metadata={"option": "--store-points", "omit_default": True}
    )
    geometry: bool = field(
        default=False, metadata={"option": "--store-geometry", "omit_default": True}
    )

    def __post_init__(self) -> None:
        check_choice(self.sparse_format, "sparse_format", SPARSE_FORMATS)
        if not str(self.source).strip():
            raise ParameterError("must not be empty", param="source")
        sequence_resolver(self.sequence_from, "sequence")  # refuses a bad spec
        given = [self.split is not None, bool(self.split_files), self.official_split is not None]
        if sum(given) > 1:
            raise ParameterError(
                "give one of split fractions, split files and an official split, not two"
            )
        if self.official_split is not None:
            object.__setattr__(self, "official_split", official_split(self.official_split).name)
        if self.split is not None:
            object.__setattr__(self, "split", parse_split_fractions(self.split))
        if self.split_files is not None:
            object.__setattr__(self, "split_files", tuple(self.split_files) or None)
        check_choice(self.store, "store", STORE_MODES)
        object.__setattr__(self, "store_points", bool(self.store_points))
        object.__setattr__(self, "geometry", bool(self.geometry) or self.store_points)
        object.__setattr__(self, "source", str(self.source))
        object.__setattr__(self, "seed", check_int_range(self.seed, "seed"))

    @classmethod
    def with_splits(
        cls,
        splits: str | Mapping[str, float] | None = None,
        split_files: Iterable[str | tuple[str, str]] | None = None,
        official_split: str | None = None,
        **settings,
    ) -> BuildSettings:
        """Settings from a choice of splits as the command line gives it.

        ``splits``: fractions (``0.8,0.1,0.1``, ``train=0.7,val=0.3`` or a mapping),
        ``"tree"`` (the split the inputs' tree gives), or None: the default fractions
        (0.8/0.1/0.1 train/val/test) unless ``split_files`` or an ``official_split`` (a name
        of :data:`.official_splits.OFFICIAL_SPLITS`) are given.
        """
        split_files = tuple(split_files or ())
        if sum([splits is not None, bool(split_files), official_split is not None]) > 1:
            raise ParameterError(
                "give one of split fractions, split files and an official split, not two"
            )
        if official_split is not None:
            return cls(split=None, official_split=official_split, **settings)
        if split_files or splits == "tree":
            return cls(split=None, split_files=split_files or None, **settings)
        return cls(split=DEFAULT_SPLIT if splits is None else splits, **settings)

    @property
    def split_from_tree(self) -> bool:
        """Whether each frame's split is the one its input tree gives (KITTI depth
        completion ``train`` / ``val``, ``val_selection``)."""
        return self.split is None and not self.split_files and self.official_split is None

    def split_method(self) -> dict:
        """How splits are assigned, as the manifest's metadata says (without split-file counts)."""
        if self.official_split is not None:
            split = official_split(self.official_split)
            return {"method": "official", "name": split.name,
                    "files": {k: f"{split.dataset}/{f}" for k, f in split.lists}}  # fmt: skip
        if self.split_files:
            return {"method": "split-file"}
        if self.split_from_tree:
            return {"method": "tree"}
        return {"method": "sequence", "fractions": dict(self.split), "seed": self.seed}

    def record_store(self, record: dict) -> dict:
        """``record`` (the settings as recorded) with the store mode as earlier versions
        recorded it: ``link`` (a bool, as 0.2 and 0.3 wrote it), and ``store`` only for
        ``reference``, so that their folders resume."""
        record = dict(record)
        record.pop("store", None)
        record["link"] = self.store == "link"
        if self.store == "reference":
            record["store"] = "reference"
        return record
