"""Shared timing helper for the benchmarks: medians of repeated runs, ratio, one line each."""

from __future__ import annotations

import os
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


def load() -> str:
    """The machine's load averages (1, 5, 15 min) and CPU count, for every printed figure."""
    one, five, fifteen = os.getloadavg()
    return f"load {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} CPUs"


def interleaved(
    fns: dict[str, Callable[[], object]], *, repeat: int = 7, warmup: int = 1
) -> dict[str, float]:
    """Median seconds of each function, the runs alternating (a b a b ...) so that a change
    in the machine's load hits every function alike."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(v) for name, v in times.items()}


def compare_interleaved(
    name: str,
    ours: Callable[[], object],
    reference: Callable[[], object],
    *,
    reference_name: str = "reference",
    repeat: int = 7,
    warmup: int = 1,
    goal: float | None = None,
) -> dict:
    """:func:`compare` with alternating runs; prints the load and, with ``goal``, whether the
    ratio (reference / ours) reaches it."""
    t = interleaved({"ours": ours, "ref": reference}, repeat=repeat, warmup=warmup)
    ratio = t["ref"] / t["ours"] if t["ours"] > 0 else float("inf")
    verdict = (
        "" if goal is None else f" (goal >= {goal:g}x: {'met' if ratio >= goal else 'NOT met'})"
    )
    print(
        f"{name:<48} ours {t['ours'] * 1e3:9.2f} ms | {reference_name} {t['ref'] * 1e3:9.2f} ms "
        f"| ratio {ratio:7.2f}x{verdict} | {load()}"
    )
    return {
        "name": name,
        "ours_ms": t["ours"] * 1e3,
        "reference_ms": t["ref"] * 1e3,
        "ratio": ratio,
        "load": os.getloadavg()[0],
    }
