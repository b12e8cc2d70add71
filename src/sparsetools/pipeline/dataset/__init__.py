"""``dataset build / info / verify``: the batch jobs behind the commands, one module per concern.

- :mod:`.splits`: split fractions, split files, sequence names, assignment by sequence;
- :mod:`.staging`: the per-frame job and its staging record;
- :mod:`.build`: indexing and matching the inputs, the build, merging into the manifest;
- :mod:`.inspect`: ``info`` and ``verify``.
"""

from .build import SPARSE_FORMATS, BuildSettings, build_dataset
from .inspect import dataset_info, verify_dataset
from .splits import (
    DEFAULT_SPLIT,
    assign_splits,
    match_split_lines,
    parse_split_fractions,
    read_split_file,
    sequence_resolver,
)
from .staging import STAGING, DatasetFrameInput, DatasetJob, read_record, write_record

__all__ = [
    "DEFAULT_SPLIT",
    "SPARSE_FORMATS",
    "STAGING",
    "BuildSettings",
    "DatasetFrameInput",
    "DatasetJob",
    "assign_splits",
    "build_dataset",
    "dataset_info",
    "match_split_lines",
    "parse_split_fractions",
    "read_record",
    "read_split_file",
    "sequence_resolver",
    "verify_dataset",
    "write_record",
]
