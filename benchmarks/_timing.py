"""Shared timing helper for the benchmarks: medians of repeated runs, ratio, one line each."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def median_seconds(fn: Callable[[], object], *, repeat: int = 7, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeat`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def compare(
    name: str,
    ours: Callable[[], object],
    reference: Callable[[], object],
    *,
    reference_name: str = "reference",
    repeat: int = 7,
) -> dict:
    """Time ``ours`` and ``reference`` on the same input; print medians and the speed ratio."""
    t_ours = median_seconds(ours, repeat=repeat)
    t_ref = median_seconds(reference, repeat=repeat)
    ratio = t_ref / t_ours if t_ours > 0 else float("inf")
    print(
        f"{name:<48} ours {t_ours * 1e3:9.2f} ms | {reference_name} {t_ref * 1e3:9.2f} ms "
        f"| ratio {ratio:7.1f}x"
    )
    return {"name": name, "ours_ms": t_ours * 1e3, "reference_ms": t_ref * 1e3, "ratio": ratio}
