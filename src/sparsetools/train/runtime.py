"""What every training and evaluation run shares: torch settings, loaders, files, progress.

- :func:`torch_settings` turns on deterministic algorithms and pins the torch thread count for
  the duration of a run (restored afterwards). On CPU that makes two runs with the same seed
  and thread count bit-identical.
- :func:`make_loader` builds a DataLoader over an explicit list of sample indices; with
  :func:`epoch_order` (a permutation drawn from ``(seed, epoch)``) the order of the samples,
  and hence the results, never depend on the number of worker processes.
- :func:`batches` iterates a loader so that an error raised in a worker keeps its one-line
  message.
- :func:`write_json`, :func:`write_csv` and :func:`write_png` write atomically.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from ..errors import ParameterError, SparsetoolsError
from ..io.atomic import atomic_path

__all__ = [
    "available_cores",
    "batches",
    "epoch_order",
    "make_loader",
    "progress_bar",
    "resolve_device",
    "save_torch",
    "torch_settings",
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


@contextlib.contextmanager
def torch_settings(threads: int | None, device: torch.device) -> Iterator[None]:
    """Deterministic algorithms and a thread count for the duration of a run, then restored.

    Parameters
    ----------
    threads : int or None
        torch CPU threads; None = every core available (:func:`available_cores`). Results on
        CPU are identical only between runs with the same thread count.
    device : torch.device
        On CUDA, non-deterministic kernels only warn (some have no deterministic version).
    """
    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    prev_threads = torch.get_num_threads()
    if device.type == "cuda":  # cuBLAS needs this for deterministic matrix products
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True, warn_only=device.type != "cpu")
    torch.set_num_threads(int(threads) if threads else available_cores())
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(prev_det, warn_only=prev_warn)
        torch.set_num_threads(prev_threads)


def _worker_init(worker_id: int) -> None:
    # Augmentation uses explicit per-sample generators; this only keeps any other library's
    # global RNG reproducible in worker processes and avoids oversubscribing the cores.
    import random

    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)  # noqa: NPY002 - global state of third-party code, not ours
    random.seed(seed)
    torch.set_num_threads(1)


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
    """A DataLoader over ``dataset`` in the given sample ``order`` (default: 0..n-1)."""
    from torch.utils.data import DataLoader

    return DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=order if order is not None else list(range(len(dataset))),
        num_workers=workers,
        collate_fn=collate,
        worker_init_fn=_worker_init if workers else None,
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


def progress_bar(total: int, desc: str, enabled: bool):
    """A tqdm bar on stderr (a no-op when not ``enabled``)."""
    from tqdm import tqdm

    return tqdm(
        total=total,
        desc=desc,
        unit="batch",
        file=sys.stderr,
        disable=not enabled,
        leave=False,
        dynamic_ncols=True,
    )


def save_torch(obj, path: Path) -> None:
    """``torch.save`` to a temporary name, then rename (a crash never leaves half a file)."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json(path: Path, obj) -> None:
    """``obj`` as indented JSON, atomically (numpy scalars and paths allowed)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, default=_json_default) + "\n")


def _csv_value(v):
    if isinstance(v, float):
        return repr(v)  # round-trips exactly
    return "" if v is None else v


def write_csv(path: Path, rows: list[dict], columns: list[str]) -> None:
    """Rows as CSV with the given columns (floats written exactly, None as empty), atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: _csv_value(r.get(k)) for k in columns})
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An (H, W, 3) uint8 RGB picture as PNG (atomically, through :mod:`sparsetools.io.image`)."""
    from ..io.image import write_image

    write_image(path, rgb)
