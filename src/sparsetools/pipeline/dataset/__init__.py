"""``dataset build / info / verify``: the batch job behind the commands, one module per concern.

- :mod:`.splits`: split fractions, split files, sequence names, assignment by sequence;
- :mod:`.official_splits`: the split lists shipped with sparsetools (``--split eigen``);
- :mod:`.settings`: what the samples depend on (:class:`BuildSettings`);
- :mod:`.build`: finding and matching the inputs, the job (:class:`DatasetJob`);
- :mod:`.staging`: one frame's work and its staging record;
- :mod:`.merge`: merging the staged frames into the manifest;
- :mod:`.inspect`: ``info`` and ``verify`` (:mod:`.references`: of images referenced in place);
- :mod:`.pack`: ``pack``, a ``--store reference`` dataset made self-contained.
"""

from .build import BuildInputs, DatasetJob, build_dataset, find_build_inputs
from .inspect import DatasetInfo, dataset_info
from .official_splits import OFFICIAL_SPLITS, official_split_lists, official_split_names
from .pack import pack_dataset
from .settings import SPARSE_FORMATS, BuildSettings
from .splits import (
    DEFAULT_SPLIT,
    SplitList,
    SplitListsReport,
    assign_splits,
    match_split_lines,
    parse_split_fractions,
    read_split_file,
    sequence_resolver,
)
from .staged import read_record, read_staged, write_record
from .staging import STAGING, DatasetFrameInput, DatasetFrameStats
from .verify import VerifyReport, verify_dataset

__all__ = [
    "DEFAULT_SPLIT",
    "OFFICIAL_SPLITS",
    "SPARSE_FORMATS",
    "STAGING",
    "BuildInputs",
    "BuildSettings",
    "DatasetFrameInput",
    "DatasetFrameStats",
    "DatasetInfo",
    "DatasetJob",
    "SplitList",
    "SplitListsReport",
    "VerifyReport",
    "assign_splits",
    "build_dataset",
    "dataset_info",
    "find_build_inputs",
    "match_split_lines",
    "official_split_lists",
    "official_split_names",
    "pack_dataset",
    "parse_split_fractions",
    "read_record",
    "read_split_file",
    "read_staged",
    "sequence_resolver",
    "verify_dataset",
    "write_record",
]
