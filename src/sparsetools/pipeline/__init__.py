"""Batch execution: the frame runner (:mod:`.core`), its resume rule (:mod:`.provenance`),
executors, and one job module per command.

Each ``pipeline/<command>.py`` turns frames (from :mod:`sparsetools.io.sources`) into
:class:`FrameTask` lists with a typed input record per frame, holds the picklable per-frame
job, and returns a :class:`RunSummary` from its ``run_*`` function, which takes a
:class:`Batch`.
"""

from .batch import Batch, FrameResult, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames
from .executors import Executor, LocalExecutor, SerialExecutor, make_executor

__all__ = [
    "Batch",
    "Executor",
    "FrameResult",
    "FrameTask",
    "LocalExecutor",
    "RunSpec",
    "RunSummary",
    "SerialExecutor",
    "check_output_dir",
    "make_executor",
    "run_frames",
]
