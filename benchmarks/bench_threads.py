"""BLAS threads and the skinny matrix products of the kernels: pinned to one thread vs default.

Run: ``.venv/bin/python benchmarks/bench_threads.py`` (``make bench`` runs it with the others).

The kernels' matrix products are ``(N, 3) @ (3, k)``: 120k points times a 3x3 rotation or
the 3x4 camera matrix. numpy's OpenBLAS spreads each over every core by default, which costs
more in start-up and synchronisation than the product itself, and on a busy machine (threads
waiting for a core) far more. Every batch command runs its frames with one BLAS thread
(``sparsetools.pipeline.executors.thread_limits``); this measures what that buys: ours = one
thread, reference = OpenBLAS's default thread count, in alternating runs on the same input.
Inputs: the real KITTI frame 000001 from ../shared/data/real (a synthetic scan when absent).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import interleaved, load

ROOT = Path(__file__).resolve().parent.parent


def threads_now() -> list[int]:
    from sparsetools.pipeline.executors import _loaded_openblas

    return [get() for _, get in _loaded_openblas()]


def main() -> None:
    from bench_beams import load_frame
    from sparsetools.ops.beams import select_beams
    from sparsetools.ops.projection import accumulate_sweeps, project_uvz

    points, calib, name = load_frame()
    xyz = points[:, :3].astype(np.float64)
    R = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    T = np.eye(4)
    T[:3, :3] = R
    cases = {
        "(N, 3) @ (3, 3) float64": lambda: xyz @ R.T,
        "project_uvz (N, 3) @ (3, 3) + t": lambda: project_uvz(points, calib.projection),
        "accumulate_sweeps, 2 sweeps": lambda: accumulate_sweeps([(points, T), (points, T)]),
        "select_beams pl++ 4 beams": lambda: select_beams(points, n=4, select="pl++", calib=calib),
    }
    print(f"frame: {name}, {points.shape[0]} points; OpenBLAS threads by default: "
          f"{threads_now()} | {load()}")  # fmt: skip

    from sparsetools.pipeline.executors import _loaded_openblas

    libs = _loaded_openblas()
    default = [get() for _, get in libs]
    block = 7

    def with_threads(fn, counts):
        def run():  # switch once per block of calls: the switch itself is not timed per call
            for (set_threads, _), n in zip(libs, counts, strict=True):
                set_threads(n)
            for _ in range(block):
                fn()

        return run

    for label, fn in cases.items():
        t = interleaved(
            {"one": with_threads(fn, [1] * len(libs)), "default": with_threads(fn, default)},
            repeat=7,
        )
        one, many = t["one"] / block, t["default"] / block
        print(
            f"{label:<40} 1 thread {one * 1e3:8.3f} ms | default threads {many * 1e3:8.3f} ms "
            f"| ratio {many / one:6.2f}x | {load()}"
        )
    for (set_threads, _), n in zip(libs, default, strict=True):
        set_threads(n)


if __name__ == "__main__":
    main()
