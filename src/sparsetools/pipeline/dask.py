"""Dask executor: the same per-frame functions on a Dask cluster.

Frames are sent in chunks, many frames per Dask task: a Dask task costs the scheduler a few
milliseconds whatever it holds, so a chunk is sized from the work its workers report (about
0.25 s of work, at least 2 chunks per worker) to keep that cost under 5 % of the chunk's work
(issue 28); at most ``3 x workers`` chunks are in flight, taken lazily from the frames
(:mod:`.chunking`). Every frame writes its own
deterministically named files atomically, so a rerun is idempotent and a lost worker loses
at most the frames it had not finished. Results do not depend on the number of workers:
per-frame randomness comes from :func:`sparsetools.random.frame_rng` (seed, frame id).

Without a scheduler address a ``LocalCluster`` of ``workers`` single-threaded processes is
started for the run and closed afterwards.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from ..errors import DependencyError, ParameterError
from ..validate import check_int_range

__all__ = ["DaskExecutor", "cluster_threads"]

log = logging.getLogger(__name__)


#: How long a scheduler given by address may take to answer before the run is refused.
CONNECT_TIMEOUT = "10s"


class DaskExecutor:
    """Run per-frame functions on Dask.

    Parameters
    ----------
    workers : int
        Worker processes of the local cluster (ignored with ``scheduler``).
    scheduler : str, optional
        Address of a running ``dask scheduler`` (e.g. ``tcp://10.0.0.5:8786``).
    chunk_size : int, optional
        Frames per Dask task; default: sized from the measured work (``target_seconds``).
    n_items : int, optional
        How many frames the map will get at most (the items are then taken lazily); None:
        they are taken into a list first.
    """

    #: Work per Dask task (seconds): a task costs the scheduler a few ms whatever it holds.
    target_seconds = 0.25

    def __init__(
        self, *, workers: int = 1, scheduler: str | None = None, chunk_size: int | None = None,
        n_items: int | None = None,
    ):  # fmt: skip
        try:
            import distributed  # noqa: F401
        except ImportError as exc:
            raise DependencyError(
                "--executor dask needs dask[distributed]: pip install 'sparsetools[dask]'"
            ) from exc
        if chunk_size is not None:
            check_int_range(chunk_size, "chunk_size", low=1)
        self.workers = workers  # >= 1: checked by make_executor
        self.scheduler = scheduler
        self.chunk_size = chunk_size
        self.n_items = n_items

    def _client(self):
        from distributed import Client, LocalCluster

        # distributed logs INFO lines (cluster start, worker addresses) on stderr: keep it quiet.
        for name in (
            "distributed",
            "distributed.scheduler",
            "distributed.nanny",
            "distributed.worker",
        ):
            logging.getLogger(name).setLevel(logging.WARNING)

        if self.scheduler:
            try:
                return Client(self.scheduler, timeout=CONNECT_TIMEOUT), None
            except (OSError, TimeoutError) as exc:
                raise ParameterError(
                    f"cannot reach the Dask scheduler at {self.scheduler}: {exc}"
                ) from exc
        cluster = LocalCluster(
            n_workers=self.workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.ERROR,
        )
        client = Client(cluster)
        # the run's own worker processes get a batch command's allocator policy (a
        # scheduler given by address runs someone else's workers: left as they are)
        from .allocator import steady_allocator

        client.run(steady_allocator)
        return client, cluster

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        from .chunking import ChunkSizer, map_in_chunks, run_chunk

        if self.n_items is None:
            items = list(items)
        n = len(items) if self.n_items is None else self.n_items
        if n == 0:
            return
        from distributed import wait

        client, cluster = self._client()
        try:
            # a running cluster's size is what its scheduler says (``workers`` is the local
            # cluster's): chunks and chunks in flight follow it, or most of it would idle
            workers = cluster_threads(client) if self.scheduler else self.workers
            sizer = ChunkSizer(n, workers, target_seconds=self.target_seconds, first=8,
                               most=4096, balance=2, fixed=self.chunk_size)  # fmt: skip
            yield from map_in_chunks(
                items,
                submit=lambda chunk: client.submit(run_chunk, fn, chunk, pure=False),
                wait_any=lambda fs: wait(list(fs), return_when="FIRST_COMPLETED").done,
                sizer=sizer,
                window=3 * workers,
            )
        finally:
            client.close()
            if cluster is not None:
                cluster.close()


def cluster_threads(client) -> int:
    """Threads of the cluster behind ``client`` (every worker's ``nthreads``), at least 1.

    Taken when a run starts: workers that join later get chunks too, but the chunk sizes and
    the chunks in flight are set for the cluster as it was.
    """
    return max(1, sum(client.nthreads().values()))
