"""Where frames run: this process, a local process pool, or Dask (:mod:`.dask`).

An executor maps a picklable per-frame function over tasks (``map(fn, items)``; results may
arrive in any order). Workers are capped by what can be used: never more processes than
tasks, nor than the CPUs this process may run on. Local worker processes die with their
parent (``PR_SET_PDEATHSIG`` on Linux, and a watchdog that notices a new parent), so a killed
run leaves no worker writing outputs behind it, and each runs its numeric libraries with one
thread, so ``--workers N`` uses N cores and not N x cores.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Protocol

from ..errors import ParameterError

__all__ = [
    "Executor",
    "LocalExecutor",
    "SerialExecutor",
    "available_cpus",
    "make_executor",
    "usable_workers",
    "worker_initializer",
]

log = logging.getLogger(__name__)


class Executor(Protocol):
    """Maps a function over items; results may arrive in any order."""

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]: ...


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def usable_workers(requested: int, n_tasks: int, *, cap_cpus: bool = True) -> int:
    """``requested`` capped by the task count and (``cap_cpus``) the available CPUs, with a
    log line when capped."""
    if requested < 1:
        raise ParameterError(f"must be >= 1, got {requested}", param="workers")
    limit = max(1, n_tasks)
    why = f"{n_tasks} task(s)"
    cpus = available_cpus()
    if cap_cpus and cpus < limit:
        limit, why = cpus, f"{cpus} CPU(s) available"
    if requested > limit:
        log.warning("--workers %d capped to %d (%s)", requested, limit, why)
        return limit
    return requested


_THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMBA_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
)


def _die_with_parent(parent_pid: int) -> None:
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            PR_SET_PDEATHSIG = 1
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before the prctl call
        os._exit(1)

    def watch() -> None:
        import time

        while True:
            time.sleep(0.5)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="sparsetools-parent-watch", daemon=True).start()


def worker_initializer(parent_pid: int) -> None:
    """Run in each worker process: die with the parent, one thread per numeric library."""
    _die_with_parent(parent_pid)
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    # OpenCV's and torch's thread pools must not be touched in a forked child (their locks
    # may be held by a parent thread at fork time: the call can hang forever).


class SerialExecutor:
    """Runs everything in this process (``--workers 1``): simplest, best for debugging."""

    workers = 1

    def map(self, fn, items):
        for item in items:
            yield fn(item)


class LocalExecutor:
    """A local pool of ``workers`` processes that die with their parent."""

    def __init__(self, workers: int):
        if workers < 1:
            raise ParameterError(f"must be >= 1, got {workers}", param="workers")
        self.workers = workers

    def map(self, fn, items):
        items = list(items)
        if not items:
            return
        workers = min(self.workers, len(items))
        # chunksize keeps the inter-process overhead small for cheap frames.
        chunksize = max(1, min(16, len(items) // (4 * workers) or 1))
        with ProcessPoolExecutor(
            max_workers=workers, initializer=worker_initializer, initargs=(os.getpid(),)
        ) as pool:
            yield from pool.map(fn, items, chunksize=chunksize)


def make_executor(
    kind: str = "local", *, workers: int = 1, scheduler: str | None = None
) -> Executor:
    """Executor by name: ``local`` (serial for 1 worker, else a process pool) or ``dask``."""
    if workers < 1:
        raise ParameterError(f"must be >= 1, got {workers}", param="workers")
    if kind == "local":
        return SerialExecutor() if workers == 1 else LocalExecutor(workers)
    if kind == "dask":
        from .dask import DaskExecutor  # optional dependency, imported only when asked

        return DaskExecutor(workers=workers, scheduler=scheduler)
    raise ParameterError(f"unknown executor '{kind}' (choose local or dask)", param="executor")
