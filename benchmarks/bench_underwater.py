"""Underwater median compensation per 12-megapixel frame with a window of 31 frames.

Ours: :class:`UnderwaterCompensator` streaming 8-bit frames through its ring buffer (exact
radix-select median in a numba kernel, one thread per core, fused correction). Reference:
the straightforward ``numpy.median(stack, axis=0)`` over the same 31 frames followed by the
same arithmetic in numpy. The paper's CUDA prototype does about 2 frames/s on a GPU.

A 1-megapixel case is timed with more repeats; the 12-megapixel reference runs once (it
takes about 15 s and 1.5 GB). Memory: the ring buffer is 31 x 36 MB = 1.1 GB of uint8.

Run: ``.venv/bin/python benchmarks/bench_underwater.py [--megapixels 12]``
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import compare

WINDOW = 31


def frames(shape, count, seed=0):
    """A few distinct random frames cycled (generating 12-MP noise per frame would dominate)."""
    rng = np.random.default_rng(seed)
    base = [rng.integers(30, 230, shape, dtype=np.uint8) for _ in range(5)]
    for t in range(count):
        yield base[t % len(base)]


def reference_frame(stack: np.ndarray, frame: np.ndarray, B: np.ndarray, a_ref, eps=1e-3):
    M = np.median(stack, axis=0)
    F = (M - B) / a_ref
    valid = np.all(F >= eps, axis=2)
    return (frame - B) / np.maximum(F, eps), valid


def steady_state_seconds(shape, n_frames: int) -> tuple[float, float]:
    """(first-window seconds, median seconds per frame after it) of a streaming pass."""
    from sparsetools.ops.underwater import UnderwaterCompensator

    water = [np.full(shape, 12, np.uint8)] * 3
    comp = UnderwaterCompensator(water, window=WINDOW)
    stamps = [time.perf_counter()]
    for _ in comp.process(frames(shape, WINDOW + n_frames)):
        stamps.append(time.perf_counter())
    h = WINDOW // 2
    first = stamps[1] - stamps[0]  # reading the first window, its median, frame 0
    # Frames h+1 .. : one new frame, one median, one correction each.
    per = [b - a for a, b in zip(stamps[h + 1 : -h - 1], stamps[h + 2 : -h], strict=True)]
    return first, statistics.median(per)


def one_megapixel() -> None:
    """1 MP, repeated: ours vs numpy.median on the same window."""
    from sparsetools.ops.underwater import UnderwaterCompensator, window_median

    shape = (750, 1334, 3)
    stack = np.stack(list(frames(shape, WINDOW, seed=1)))
    B = np.full(shape, 12, np.float32)
    comp = UnderwaterCompensator.from_backscatter(B, window=WINDOW, a_ref=[60.0, 60.0, 60.0])
    flat = stack.reshape(WINDOW, -1)
    compare(
        "window-31 median + correction, 1 MP",
        lambda: comp._correct(flat[15], comp._median(flat)),
        lambda: reference_frame(stack, stack[15], B, np.float32(60.0)),
        reference_name="numpy.median",
        repeat=5,
    )
    same = np.array_equal(window_median(stack), np.median(stack, axis=0))
    print(f"{'  median identical to numpy.median':<48} {same}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--megapixels", type=float, default=12.0)
    args = ap.parse_args()
    from sparsetools.ops.underwater import window_median

    # Warm up numba (compiled once, then cached on disk).
    window_median(np.zeros((3, 10), np.uint8))

    one_megapixel()

    # 12 MP streaming.
    mp = args.megapixels
    h = int(round(np.sqrt(mp * 1e6 * 3 / 4)))
    shape = (h, int(round(h * 4 / 3)), 3)
    first, per = steady_state_seconds(shape, 5)
    print(f"{f'streaming {shape[1]}x{shape[0]} ({mp:g} MP), window 31':<48} "
          f"{per * 1e3:9.1f} ms/frame ({1 / per:.2f} frames/s); first window {first:.1f} s")  # fmt: skip
    stack = np.stack(list(frames(shape, WINDOW, seed=2)))
    B = np.full(shape, 12, np.float32)
    t0 = time.perf_counter()
    reference_frame(stack, stack[15], B, np.float32(60.0))
    t_ref = time.perf_counter() - t0
    print(f"{'  reference numpy.median, same window (1 run)':<48} {t_ref * 1e3:9.1f} ms/frame "
          f"| ratio {t_ref / per:6.1f}x")  # fmt: skip


if __name__ == "__main__":
    main()
