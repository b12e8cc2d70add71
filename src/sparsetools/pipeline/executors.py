"""Where frames run: this process, a local process pool, or Dask (:mod:`.dask`).

An executor maps a picklable per-frame function over tasks (``map(fn, items)``; results may
arrive in any order). Workers are capped by what can be used: never more processes than
tasks, nor than the CPUs this process may run on. Local worker processes die with their
parent (``PR_SET_PDEATHSIG`` on Linux, and a watchdog that notices a new parent), so a killed
run leaves no worker writing outputs behind it.

Threads (:func:`thread_limits`): while frames run, BLAS uses one thread in every process (the
kernels' matrix products are skinny ``(N, 3) @ (3, k)`` ones, which a thread pool only slows
down, badly so on a busy machine); in a pool every worker also runs OpenMP, numba, OpenCV
and torch with one thread, so ``--workers N`` uses N cores and not N x cores; a single
process keeps those at the CPUs it may use. The limits are set in the parent before the pool
starts (forked workers inherit them; libraries a worker imports later read the environment),
never by calling OpenCV's or torch's thread setters in a forked child (their locks may be held
by a parent thread at fork time: the call can hang forever).

Memory: :mod:`.allocator`.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol

__all__ = [
    "Executor",
    "LocalExecutor",
    "SerialExecutor",
    "available_cpus",
    "limit_blas_threads",
    "make_executor",
    "thread_limits",
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
    limit = max(1, n_tasks)
    why = f"{n_tasks} task(s)"
    cpus = available_cpus()
    if cap_cpus and cpus < limit:
        limit, why = cpus, f"{cpus} CPU(s) available"
    if requested > limit:
        log.warning("--workers %d capped to %d (%s)", requested, limit, why)
        return limit
    return requested


#: Read by OpenBLAS, MKL, OpenMP (torch, numba's omp layer), numba, Apple's Accelerate and
#: OpenCV when they are loaded: a worker that imports one later gets one thread.
_THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMBA_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
)

# (setter, getter) of the OpenBLAS builds numpy and scipy ship (64-bit-integer and plain),
# and of a system OpenBLAS.
_OPENBLAS_API = (
    ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
    ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
    ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
    ("openblas_set_num_threads", "openblas_get_num_threads"),
)


def _loaded_openblas() -> list[tuple[Callable, Callable]]:
    """(set, get) thread-count functions of every OpenBLAS loaded in this process (Linux)."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as fh:
            paths = {
                parts[5]
                for parts in (line.split(None, 5) for line in fh)
                if len(parts) == 6 and "openblas" in parts[5].lower()
            }
    except OSError:
        return []
    found = []
    for path in sorted(p.strip() for p in paths):
        try:  # RTLD_NOLOAD: a handle to the copy already loaded, never a second copy
            lib = ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
        except OSError:
            continue
        for set_name, get_name in _OPENBLAS_API:
            try:
                found.append((getattr(lib, set_name), getattr(lib, get_name)))
                break
            except AttributeError:
                continue
    return found


@contextlib.contextmanager
def limit_blas_threads(n: int) -> Iterator[None]:
    """BLAS uses at most ``n`` threads in this process inside the block.

    Through threadpoolctl when it is installed (every BLAS it knows), else through the
    thread-count functions of the OpenBLAS libraries loaded (numpy's and scipy's). Forked
    children started inside the block inherit the limit.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        threadpool_limits = None
    if threadpool_limits is not None:
        limits = threadpool_limits(limits=n, user_api="blas")
        try:
            yield
        finally:
            limits.restore_original_limits()
        return
    libs = _loaded_openblas()
    before = [get() for _, get in libs]
    for set_threads, _ in libs:
        set_threads(n)
    try:
        yield
    finally:
        for (set_threads, _), k in zip(libs, before, strict=True):
            set_threads(k)


@contextlib.contextmanager
def thread_limits(*, pool: bool) -> Iterator[None]:
    """The thread policy while frames run in this process (``pool=False``) or in a pool of
    worker processes started inside the block (``pool=True``).

    BLAS gets one thread in either case. For a pool, the environment variables every numeric
    library reads when it loads are set to 1 (workers inherit them) and, when OpenCV is
    loaded here already, its thread count is set to 1 in this process, so forked workers
    inherit that too. Everything is restored on exit.
    """
    saved_env = {}
    cv2 = sys.modules.get("cv2")
    cv2_threads = None
    if pool:
        saved_env = {var: os.environ.get(var) for var in _THREAD_VARS}
        os.environ.update({var: "1" for var in _THREAD_VARS})
        if cv2 is not None and hasattr(cv2, "setNumThreads"):
            cv2_threads = cv2.getNumThreads()
            cv2.setNumThreads(1)  # in the parent: safe; a forked child must not call it
    try:
        with limit_blas_threads(1):
            yield
    finally:
        if cv2_threads is not None:
            cv2.setNumThreads(cv2_threads)
        for var, value in saved_env.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


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
    """Run in each worker process: die with the parent, one thread per numeric library.

    The parent set the limits before forking (:func:`thread_limits`); the environment is set
    again here for workers started another way.
    """
    _die_with_parent(parent_pid)
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    # OpenCV's and torch's thread pools must not be touched in a forked child (their locks
    # may be held by a parent thread at fork time: the call can hang forever).


def __getattr__(name: str):
    # concurrent.futures.process pulls in multiprocessing and socket (~25 ms): imported when
    # a pool is first needed, not at the start of every command.
    if name == "ProcessPoolExecutor":
        from concurrent.futures import ProcessPoolExecutor

        return ProcessPoolExecutor
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _pool_context():
    """``fork`` where the platform has it: workers start in milliseconds with the parent's
    imports, and the parent is their parent (which :func:`_die_with_parent` relies on)."""
    import multiprocessing

    if "fork" in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("fork")
    return multiprocessing.get_context()


def _prepare(fn) -> None:
    """Let the job load what every frame needs (libraries, tables) once, here, before the pool
    forks: every worker then inherits it instead of loading its own copy. Best effort: a
    failure here shows again, as that frame's error, when the frame runs."""
    prepare = getattr(fn, "prepare", None)
    if callable(prepare):
        try:
            prepare()
        except Exception as exc:  # the frames report it
            log.debug("job preparation failed: %s", exc)


class SerialExecutor:
    """Runs everything in this process (``--workers 1``): simplest, best for debugging."""

    workers = 1

    def map(self, fn, items):
        with thread_limits(pool=False):
            for item in items:
                yield fn(item)


class LocalExecutor:
    """A local pool of ``workers`` processes that die with their parent.

    Frames go in chunks sized from the measured work (about 50 ms of work per chunk, at least
    4 chunks per worker), at most ``2 x workers`` chunks in flight: tasks are taken from the
    iterable only as workers free up (:mod:`.chunking`).
    """

    #: Work per chunk (seconds): a local task costs 0.1-0.3 ms of pickling and pipes.
    target_seconds = 0.05

    def __init__(self, workers: int, *, n_items: int | None = None):
        self.workers = workers  # >= 1: checked by make_executor
        self.n_items = n_items

    def map(self, fn, items):
        from concurrent.futures import FIRST_COMPLETED, wait

        from .chunking import ChunkSizer, map_in_chunks, run_chunk

        if self.n_items is None:  # the size is needed for the chunks: take the items
            items = list(items)
        n = len(items) if self.n_items is None else self.n_items
        if n == 0:
            return
        workers = min(self.workers, n)
        _prepare(fn)
        sizer = ChunkSizer(n, workers, target_seconds=self.target_seconds, first=2, most=64)
        pool_class = globals().get("ProcessPoolExecutor") or __getattr__("ProcessPoolExecutor")
        with (
            thread_limits(pool=True),
            pool_class(
                max_workers=workers,
                mp_context=_pool_context(),
                initializer=worker_initializer,
                initargs=(os.getpid(),),
            ) as pool,
        ):
            yield from map_in_chunks(
                items,
                submit=lambda chunk: pool.submit(run_chunk, fn, chunk),
                wait_any=lambda fs: wait(fs, return_when=FIRST_COMPLETED).done,
                sizer=sizer,
                window=2 * workers,
            )


def make_executor(
    kind: str = "local",
    *,
    workers: int = 1,
    scheduler: str | None = None,
    n_items: int | None = None,
) -> Executor:
    """Executor by name: ``local`` (serial for 1 worker, else a process pool) or ``dask``.

    ``n_items``: how many items the map will get at most (the pools size their chunks from it
    and then take the items lazily); None: the pools take the items into a list first."""
    from ..validate import check_choice, check_int_range

    check_int_range(workers, "workers", low=1)
    check_choice(kind, "executor", ("local", "dask"))
    if kind == "local":
        return SerialExecutor() if workers == 1 else LocalExecutor(workers, n_items=n_items)
    from .dask import DaskExecutor  # optional dependency, imported only when asked

    return DaskExecutor(workers=workers, scheduler=scheduler, n_items=n_items)
