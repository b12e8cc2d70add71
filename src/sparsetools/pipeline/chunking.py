"""Frames sent to workers in chunks, a bounded number at a time.

Both pool executors (local processes and Dask) send a worker a *chunk* of frames per task, for
two reasons measured in issue 28:

- **per-task cost**: a task costs the scheduler and the pickling of the job whatever its size
  (0.1-0.3 ms locally, several ms on Dask); a chunk is sized from the work seconds the workers
  report so that this cost stays a small part of the chunk's work (:class:`ChunkSizer`);
- **memory**: tasks are taken from a lazy iterable only when a worker can take them (at most
  ``window`` chunks in flight), so a run over a million frames never holds a million tasks or
  futures.

Results come back in completion order (any order); what a frame computes never depends on the
chunk it was sent in.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

__all__ = ["ChunkSizer", "map_in_chunks", "run_chunk"]


def run_chunk(fn: Callable[[Any], Any], chunk: list) -> tuple[list, float]:
    """``fn`` over ``chunk`` where it runs (a worker): the results and the work's seconds."""
    t0 = time.perf_counter()
    out = [fn(item) for item in chunk]
    return out, time.perf_counter() - t0


class ChunkSizer:
    """How many frames the next chunk takes.

    The first chunks take ``first`` frames; once a chunk has come back, a chunk takes as many
    frames as ``target_seconds`` of work at the measured seconds per frame (a running mean over
    every chunk so far), never more than ``n_items / (balance * workers)`` (so every worker
    gets about ``balance`` chunks and none waits long for the last one) nor than ``most``.
    Towards the end a chunk takes at most a ``2 * workers``-th of the frames not yet handed
    out (:meth:`took` counts them; guided self-scheduling): the last chunks shrink, so the
    workers finish within about a small chunk's work of each other instead of one waiting
    out a whole chunk of the other's.

    Parameters
    ----------
    n_items : int
        The run's frames (an upper bound: frames found up to date are never sent).
    workers : int
    target_seconds : float
        Work per chunk, seconds.
    first : int
        Frames per chunk before any chunk has come back.
    most : int
        Largest chunk.
    balance : int
        Chunks per worker at least (when there are frames enough).
    fixed : int, optional
        Every chunk takes this many frames (the measurements are ignored).
    """

    def __init__(
        self, n_items: int, workers: int, *, target_seconds: float, first: int = 4,
        most: int = 1024, balance: int = 4, fixed: int | None = None,
    ):  # fmt: skip
        self.fixed = fixed
        self.n_items = n_items
        self.workers = max(1, workers)
        self.cap = max(1, min(most, n_items // max(1, balance * workers)))
        self.first = max(1, min(first, self.cap))
        self.target = float(target_seconds)
        self._frames = 0
        self._seconds = 0.0
        self._taken = 0

    def took(self, frames: int) -> None:
        """``frames`` frames were handed out in a chunk."""
        self._taken += frames

    def observe(self, frames: int, seconds: float) -> None:
        """A chunk of ``frames`` frames took ``seconds`` of work in its worker."""
        self._frames += frames
        self._seconds += max(0.0, seconds)

    def next_size(self) -> int:
        if self.fixed:
            return self.fixed
        if self._frames == 0:
            return self.first
        per_frame = self._seconds / self._frames
        size = self.cap if per_frame <= 0 else math.ceil(self.target / per_frame)
        tail = math.ceil((self.n_items - self._taken) / (2 * self.workers))
        return max(1, min(self.cap, size, tail))


def map_in_chunks(
    items: Iterable,
    *,
    submit: Callable[[list], Any],
    wait_any: Callable[[set], Iterable],
    sizer: ChunkSizer,
    window: int,
) -> Iterator:
    """Results of every item, in completion order, at most ``window`` chunks in flight.

    Parameters
    ----------
    items : iterable
        Taken lazily, a chunk at a time.
    submit : callable(list) -> future
        Sends one chunk (to :func:`run_chunk` in a worker); the future's result is
        ``(results, seconds)``.
    wait_any : callable(set of futures) -> iterable of futures
        Blocks until at least one is done; returns those done.
    sizer : ChunkSizer
    window : int
        Chunks in flight at most (>= 1).
    """
    it = iter(items)
    pending: dict[Any, int] = {}
    exhausted = False
    while True:
        while not exhausted and len(pending) < window:
            chunk = list(itertools.islice(it, sizer.next_size()))
            if not chunk:
                exhausted = True
                break
            sizer.took(len(chunk))
            pending[submit(chunk)] = len(chunk)
        if not pending:
            return
        for fut in wait_any(set(pending)):
            n = pending.pop(fut)
            results, seconds = fut.result()
            sizer.observe(n, seconds)
            yield from results
