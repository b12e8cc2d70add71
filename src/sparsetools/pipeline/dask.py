"""Dask executor: the same per-frame functions on a Dask cluster.

Frames are sent in chunks (``chunk_size`` frames per Dask task); every frame writes its own
deterministically named files atomically, so a rerun is idempotent and a lost worker loses
at most the frames it had not finished. Results do not depend on the number of workers:
per-frame randomness comes from :func:`sparsetools.random.frame_rng` (seed, frame id).

Without a scheduler address a ``LocalCluster`` of ``workers`` single-threaded processes is
started for the run and closed afterwards.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from ..errors import DependencyError, ParameterError
from ..validate import check_int_range

__all__ = ["DaskExecutor"]

log = logging.getLogger(__name__)


def _run_chunk(fn: Callable[[Any], Any], chunk: list) -> list:
    return [fn(item) for item in chunk]


class DaskExecutor:
    """Run per-frame functions on Dask.

    Parameters
    ----------
    workers : int
        Worker processes of the local cluster (ignored with ``scheduler``).
    scheduler : str, optional
        Address of a running ``dask scheduler`` (e.g. ``tcp://10.0.0.5:8786``).
    chunk_size : int, optional
        Frames per Dask task; default: about 4 tasks per worker, at most 32 frames.
    """

    def __init__(
        self, *, workers: int = 1, scheduler: str | None = None, chunk_size: int | None = None
    ):
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
                return Client(self.scheduler, timeout="10s"), None
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
        return Client(cluster), cluster

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]:
        items = list(items)
        if not items:
            return
        from distributed import as_completed

        n_workers = self.workers
        size = self.chunk_size or max(1, min(32, -(-len(items) // (4 * n_workers))))
        chunks = [items[i : i + size] for i in range(0, len(items), size)]
        client, cluster = self._client()
        try:
            futures = client.map(_run_chunk, [fn] * len(chunks), chunks, pure=False)
            for fut in as_completed(futures):
                yield from fut.result()
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
