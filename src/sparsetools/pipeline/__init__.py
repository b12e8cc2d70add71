"""Batch execution: the frame runner (:mod:`.core`), its resume rule (:mod:`.provenance`),
executors, and one job module per command.

Each ``pipeline/<command>.py`` holds the command's :class:`BatchJob`: its settings record,
the tasks of the frames (from :mod:`sparsetools.io.sources`), the per-frame job and its
:class:`FrameStats`; :func:`run_job` runs any of them with a :class:`Batch` and returns a
:class:`RunSummary`::

    from sparsetools.io.sources import cloud_source
    from sparsetools.pipeline import run_job
    from sparsetools.pipeline.project import ProjectJob, ProjectSettings

    source = cloud_source(kitti_raw=["raw/2011_09_26"])
    summary = run_job(ProjectJob(ProjectSettings(camera=source.camera)), source.frames, "out")
"""

from .batch import Batch, FrameResult, RunSummary
from .core import (
    BatchJob,
    FrameStats,
    FrameTask,
    RunSpec,
    check_output_dir,
    run_frames,
    run_job,
)
from .executors import Executor, LocalExecutor, SerialExecutor, make_executor

__all__ = [
    "Batch",
    "BatchJob",
    "Executor",
    "FrameResult",
    "FrameStats",
    "FrameTask",
    "LocalExecutor",
    "RunSpec",
    "RunSummary",
    "SerialExecutor",
    "check_output_dir",
    "make_executor",
    "run_frames",
    "run_job",
]
