"""What every training and evaluation run shares: torch settings, loaders, files, progress.

- :func:`torch_settings` turns on deterministic algorithms and pins the torch thread count for
  the duration of a run (restored afterwards). On CPU that makes two runs with the same seed
  and thread count bit-identical. :func:`default_threads` is the count used when none is
  given: the CPUs this process may use (its affinity mask, at most torch's own default), a
  fixed function of the machine, never of its load at the moment.
- :func:`make_loader` builds a DataLoader over an explicit list of sample indices; with
  :func:`epoch_order` (a permutation drawn from ``(seed, epoch)``) the order of the samples,
  and hence the results, never depend on the number of worker processes. Its workers are
  capped (:func:`usable_loader_workers`) and die with their parent (Linux).
- :func:`background_saves` moves checkpoint writing (:func:`save_torch`, :func:`copy_file`)
  to a background thread; the tensors are copied at the call, every file is written
  atomically and all are complete when the block is left.
- :func:`batches` iterates a loader so that an error raised in a worker keeps its one-line
  message.
- :func:`write_json`, :func:`write_csv` and :func:`write_png` write atomically.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import queue
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from ..errors import OutputError, ParameterError, SparsetoolsError
from ..io.atomic import atomic_path
from .output_files import progress_bar, write_csv, write_json

log = logging.getLogger(__name__)

__all__ = [
    "BackgroundWriter",
    "available_cores",
    "background_saves",
    "batches",
    "copy_file",
    "default_threads",
    "epoch_order",
    "make_loader",
    "progress_bar",
    "resolve_device",
    "resolve_threads",
    "save_torch",
    "torch_settings",
    "usable_loader_workers",
    "write_csv",
    "write_json",
    "write_png",
]


def resolve_device(name: str) -> torch.device:
    """The torch device called ``name`` (``cpu``, ``cuda``, ``cuda:N``), checked.

    Raises
    ------
    ParameterError
        Unknown name, or CUDA requested where it is not available.
    """
    if name == "cpu":
        return torch.device("cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ParameterError(f"device {name!r} requested but CUDA is not available here")
        return torch.device(name)
    raise ParameterError(f"unknown device {name!r}; use cpu or cuda")


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


#: torch's own thread default at import (physical cores, or OMP_NUM_THREADS): an upper bound.
_TORCH_DEFAULT_THREADS = torch.get_num_threads()


def default_threads(*, cores: int | None = None, cap: int | None = None) -> int:
    """torch CPU threads for a run that was given none: a fixed function of the machine.

    The count is the CPUs this process may use (``cores``, :func:`available_cores`: its
    affinity mask), at most ``cap`` (torch's own default: the physical cores, or
    ``OMP_NUM_THREADS``), at least 1. It does not depend on the load of the moment: the same
    command on the same machine (and affinity) always gets the same count, so its CPU results
    are the same bits. On a busy machine pass a smaller count (``--threads``): torch's threads
    wait for each other at every operation when another process holds a core (issue 18 saw
    283 s instead of 11 s).

    The thread count is recorded in the run's ``config.json`` (and kept by ``--resume``): CPU
    results are bit-identical between runs with the same count (docs/scale.md says how much
    they differ otherwise).
    """
    cores = available_cores() if cores is None else int(cores)
    cap = _TORCH_DEFAULT_THREADS if cap is None else int(cap)
    return max(1, min(cores, cap))


def resolve_threads(threads: int | None) -> int:
    """``threads`` when given, else :func:`default_threads`."""
    return int(threads) if threads else default_threads()


def _set_deterministic(mode: bool, warn_only: bool) -> None:
    # torch.use_deterministic_algorithms also imports torch._inductor (2-3 s) to set a flag
    # of the compiler, which is not used here; set the ATen switch alone where it exists.
    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None:  # pragma: no cover - other torch versions
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        setter(mode, warn_only=warn_only)


@contextlib.contextmanager
def torch_settings(threads: int | None, device: torch.device) -> Iterator[None]:
    """Deterministic algorithms and a thread count for the duration of a run, then restored.

    Parameters
    ----------
    threads : int or None
        torch CPU threads; None = :func:`default_threads`. Results on CPU are identical only
        between runs with the same thread count.
    device : torch.device
        On CUDA, non-deterministic kernels only warn (some have no deterministic version).

    Notes
    -----
    Fresh tensors are not filled with NaN (``torch.utils.deterministic.fill_uninitialized_memory``
    off): every tensor the code allocates uninitialised is written before it is read, and the
    fill costs a pass over memory per allocation.
    """
    from torch.utils import deterministic

    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    prev_fill = deterministic.fill_uninitialized_memory
    prev_threads = torch.get_num_threads()
    if device.type == "cuda":  # cuBLAS needs this for deterministic matrix products
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    _set_deterministic(True, warn_only=device.type != "cpu")
    deterministic.fill_uninitialized_memory = False
    torch.set_num_threads(resolve_threads(threads))
    try:
        yield
    finally:
        _set_deterministic(prev_det, warn_only=prev_warn)
        deterministic.fill_uninitialized_memory = prev_fill
        torch.set_num_threads(prev_threads)


def _die_with_parent(parent: int) -> None:
    """Ask Linux to SIGKILL this process when its parent dies (``PR_SET_PDEATHSIG``).

    torch's workers check their parent only between items; a worker inside a slow item
    would go on after the parent was killed.
    """
    if not sys.platform.startswith("linux"):  # pragma: no cover
        return
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - no prctl
        return
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


def _worker_init(parent: int, worker_id: int) -> None:
    # Augmentation uses explicit per-sample generators; this only keeps any other library's
    # global RNG reproducible in worker processes and avoids oversubscribing the cores.
    import random

    _die_with_parent(parent)
    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)  # noqa: NPY002 - global state of third-party code, not ours
    random.seed(seed)
    torch.set_num_threads(1)


#: (requested, capped) pairs already reported: a loader is built per epoch, one line suffices.
_CAPS_REPORTED: set[tuple[int, int]] = set()


def usable_loader_workers(workers: int, n_batches: int) -> int:
    """``workers`` capped by the batches to load and the CPUs available (one warning line).

    Parameters
    ----------
    workers : int
        DataLoader worker processes asked for (0 = load in the main process).
    n_batches : int
        Batches the loader will yield.
    """
    workers = max(0, int(workers))
    if workers == 0:
        return 0
    cores = available_cores()
    capped = min(workers, cores, max(int(n_batches), 1))
    if capped < workers and (workers, capped) not in _CAPS_REPORTED:
        _CAPS_REPORTED.add((workers, capped))
        why = (
            f"{cores} CPU(s) available"
            if capped == cores and cores <= n_batches
            else f"{max(int(n_batches), 1)} batch(es) to load"
        )
        log.warning("--loader-workers %d capped to %d (%s)", workers, capped, why)
    return capped


def epoch_order(seed: int, epoch: int, n: int) -> list[int]:
    """The order of ``n`` training samples in ``epoch``: a permutation drawn from (seed, epoch)."""
    return np.random.default_rng([int(seed), 7919, int(epoch)]).permutation(n).tolist()


def make_loader(
    dataset,
    *,
    batch_size: int,
    order: list[int] | None,
    workers: int,
    seed: int,
    collate: Callable,
):
    """A DataLoader over ``dataset`` in the given sample ``order`` (default: 0..n-1).

    ``workers`` is capped by :func:`usable_loader_workers`; the worker processes die with
    this process.
    """
    from torch.utils.data import DataLoader

    order = order if order is not None else list(range(len(dataset)))
    workers = usable_loader_workers(workers, math.ceil(len(order) / max(int(batch_size), 1)))
    return DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=order,
        num_workers=workers,
        collate_fn=collate,
        worker_init_fn=functools.partial(_worker_init, os.getpid()) if workers else None,
        generator=torch.Generator().manual_seed(int(seed)),
        persistent_workers=False,
    )


def batches(loader) -> Iterator:
    """Iterate a DataLoader; an error raised in a worker process keeps its one-line message.

    torch re-raises a worker's exception with the worker's formatted traceback as the message;
    the user should see only the original message, as with ``workers=0``.
    """
    try:
        yield from loader
    except SparsetoolsError as exc:
        text = str(exc)
        if "DataLoader worker" not in text:
            raise
        last = [line for line in text.splitlines() if line.strip()][-1]
        name = type(exc).__name__
        message = last.split(f"{name}: ", 1)[1] if f"{name}: " in last else last
        raise type(exc)(message) from None


def _snapshot(obj):
    """``obj`` with every tensor copied (training goes on changing the originals)."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().clone()
    if isinstance(obj, dict):
        return type(obj)((k, _snapshot(v)) for k, v in obj.items())
    if isinstance(obj, list | tuple):
        return type(obj)(_snapshot(v) for v in obj)
    return obj


def _write_torch(obj, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _copy_atomic(src: Path, dst: Path) -> None:
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


class BackgroundWriter:
    """Writes checkpoints on one background thread, in the order they were asked for.

    :meth:`save` copies the tensors at the call and returns; the file is written
    atomically (temporary name, then rename), so a crash leaves the old file or the new one,
    whole. One snapshot at most waits in memory: :meth:`save` first waits for the writes
    queued before it (by the next epoch they are long done). A failed write is raised (as
    :class:`~sparsetools.errors.OutputError`) by the next call or by :meth:`close`, and the
    writes queued after it are dropped.
    """

    def __init__(self) -> None:
        self._jobs: queue.Queue = queue.Queue()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="checkpoint-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            try:
                if job is None:
                    return
                if self._error is None:
                    job()
            except BaseException as exc:  # handed to the training thread
                self._error = exc
            finally:
                self._jobs.task_done()

    def _raise_failure(self) -> None:
        exc, self._error = self._error, None
        if exc is None:
            return
        if isinstance(exc, SparsetoolsError):
            raise exc
        raise OutputError(f"could not write a checkpoint: {exc}") from exc

    def save(self, obj, path: str | os.PathLike) -> None:
        """Queue ``torch.save(obj, path)`` of a copy of ``obj`` taken now."""
        self.wait()
        self._jobs.put(functools.partial(_write_torch, _snapshot(obj), Path(path)))

    def copy(self, src: str | os.PathLike, dst: str | os.PathLike) -> None:
        """Queue a copy of ``src`` (as it is after the writes queued before) to ``dst``."""
        self._raise_failure()
        self._jobs.put(functools.partial(_copy_atomic, Path(src), Path(dst)))

    def wait(self) -> None:
        """Block until every queued write is done; raise the first failure."""
        self._jobs.join()
        self._raise_failure()

    def close(self) -> None:
        """Finish the queued writes, stop the thread; raise the first failure."""
        self._jobs.put(None)
        self._thread.join()
        self._raise_failure()


_WRITER: BackgroundWriter | None = None


@contextlib.contextmanager
def background_saves() -> Iterator[BackgroundWriter]:
    """Route :func:`save_torch` and :func:`copy_file` through a :class:`BackgroundWriter`.

    Every file is complete when the block is left, also when it is left by an exception
    (which is then raised rather than a write failure).
    """
    global _WRITER
    previous, writer = _WRITER, BackgroundWriter()
    _WRITER = writer
    try:
        yield writer
    except BaseException:
        _WRITER = previous
        with contextlib.suppress(SparsetoolsError):
            writer.close()
        raise
    _WRITER = previous
    writer.close()


def save_torch(obj, path: Path) -> None:
    """``torch.save`` to a temporary name, then rename (a crash never leaves half a file).

    Inside :func:`background_saves`, a copy of ``obj`` is written on the writer thread.
    """
    if _WRITER is not None:
        _WRITER.save(obj, path)
    else:
        _write_torch(obj, Path(path))


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` atomically (after the queued writes in :func:`background_saves`)."""
    if _WRITER is not None:
        _WRITER.copy(src, dst)
    else:
        _copy_atomic(Path(src), Path(dst))


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An (H, W, 3) uint8 RGB picture as PNG (atomically, through :mod:`sparsetools.io.image`)."""
    from ..io.image import write_image

    write_image(path, rgb)
