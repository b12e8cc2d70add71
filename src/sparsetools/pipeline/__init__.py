"""Batch execution: the frame runner (:mod:`.core`) and one job module per command.

Each ``pipeline/<command>.py`` turns command inputs into :class:`FrameTask` lists and holds
the picklable per-frame function; :func:`run_frames` executes them.
"""

from .core import (
    Executor,
    FrameResult,
    FrameTask,
    LocalExecutor,
    RunSummary,
    SerialExecutor,
    check_output_dir,
    make_executor,
    run_frames,
)

__all__ = [
    "Executor",
    "FrameResult",
    "FrameTask",
    "LocalExecutor",
    "RunSummary",
    "SerialExecutor",
    "check_output_dir",
    "make_executor",
    "run_frames",
]
