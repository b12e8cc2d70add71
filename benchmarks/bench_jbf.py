"""jbf_expand (numba kernel) vs a straightforward vectorised-numpy expansion, same input.

Frames: 800x450 and 1600x900 (nuScenes CAM_FRONT and its half), 200 radar seeds (about five
merged sweeps) at depths 5-60 m around the horizon band, the real nuScenes CAM_FRONT image as
guidance when ../shared/data/real is present (else a smooth random image). The reference
computes each seed's window confidence with numpy array operations and merges with the same
nearest rule, so both produce the same maps (checked below). Ours runs with one thread and
with the default (bands of rows, one per CPU this process may use; the same maps), each
against the reference in alternating runs; goal (issue 18): >= 20x at 800x450. Every line
states the machine's load: threads only help when a core is free.

The package keeps one band kernel for a gray and an RGB guidance (issue 22: the channel count
compiled into the kernel); :func:`merged_vs_separate` times it against the two kernels it
replaced, loaded from the git history (:data:`SEPARATE_KERNELS_COMMIT`, so no copy of them
lives in the tree), on the same arguments, interleaved, one thread: the merge stays if it is
within 3 % for gray and for RGB.
Run: ``python benchmarks/bench_jbf.py`` (all), ``python benchmarks/bench_jbf.py --kernels``
(the merged-vs-separate comparison alone).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import compare_interleaved, load, median_seconds

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
ROOT = Path(__file__).resolve().parent.parent
#: The last commit whose ops/_jbf_kernels.py has one band kernel per guidance (gray, RGB).
SEPARATE_KERNELS_COMMIT = "31995e29649dc20e0e74ec00a4ff6b3e072cfe14"
NUSCENES_FX = 1266.417203046554  # CAM_FRONT of the mmdet3d demo sample, 1600x900


def guidance_image(width: int, height: int) -> np.ndarray:
    import cv2

    cams = sorted((REAL / "nuscenes-mmdet3d-demo").glob("*__CAM_FRONT__*.jpg"))
    if cams:
        rgb = cv2.imread(str(cams[0]))[:, :, ::-1]
        return np.ascontiguousarray(cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA))
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8)
    return cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)


def radar_seeds(width: int, height: int, n: int = 200, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    radar = np.zeros((height, width), np.float32)
    rows = rng.integers(int(0.40 * height), int(0.65 * height), n)
    cols = rng.integers(0, width, n)
    radar[rows, cols] = rng.uniform(5.0, 60.0, n).astype(np.float32)
    return radar


def numpy_reference(
    radar, gray, *, fx, fy, sigma_s=25.0, sigma_r=10.0, threshold=0.05, window_m=(2.35, 2.35)
):
    """Per seed: the window's confidence with array ops; farthest first, nearer overwrite."""
    H, W = radar.shape
    depth = np.zeros((H, W), np.float32)
    conf = np.zeros((H, W), np.float32)
    g = gray.astype(np.float64)
    ys, xs = np.nonzero(radar > 0)
    ds = radar[ys, xs]
    for k in np.argsort(-ds, kind="stable"):
        y0, x0, d = ys[k], xs[k], ds[k]
        hu = int(np.floor(window_m[0] * fx / float(d) / 2))
        hv = int(np.floor(window_m[1] * fy / float(d) / 2))
        top, bottom = max(y0 - hv, 0), min(y0 + hv, H - 1) + 1
        left, right = max(x0 - hu, 0), min(x0 + hu, W - 1) + 1
        yy, xx = np.ogrid[top:bottom, left:right]
        dist2 = (yy - y0) ** 2 + (xx - x0) ** 2
        diff2 = (g[top:bottom, left:right] - g[y0, x0]) ** 2
        c = np.exp(-dist2 / (2 * sigma_s**2)) * np.exp(-diff2 / (2 * sigma_r**2))
        c32 = c.astype(np.float32)
        cur_d = depth[top:bottom, left:right]
        cur_c = conf[top:bottom, left:right]
        take = (c >= threshold) & ((cur_d == 0) | (d < cur_d) | ((d == cur_d) & (c32 > cur_c)))
        cur_d[take] = d
        cur_c[take] = c32[take]
    depth[ys, xs] = ds
    conf[ys, xs] = 1.0
    return depth, conf


def algorithm1_numpy(
    radar, gray, *, fx, fy, sigma_s=25.0, sigma_r=10.0, threshold=0.05, window_m=(2.35, 2.35)
):
    """The paper's Algorithm 1 transcribed literally with numpy (meshgrid, distances, fancy
    indexing), farthest seed first so that nearer ones overwrite; seeds restored at the end."""
    H, W = radar.shape
    depth = np.zeros((H, W), np.float32)
    conf = np.zeros((H, W), np.float32)
    I = gray.astype(np.float64)
    ys, xs = np.nonzero(radar > 0)
    ds = radar[ys, xs]
    for k in np.argsort(-ds, kind="stable"):
        y, x, d = ys[k], xs[k], ds[k]
        u = window_m[0] * fx / float(d)
        v = window_m[1] * fy / float(d)
        rows = np.arange(max(y - int(v / 2), 0), min(y + int(v / 2), H - 1) + 1)
        cols = np.arange(max(x - int(u / 2), 0), min(x + int(u / 2), W - 1) + 1)
        qy, qx = np.meshgrid(rows, cols, indexing="ij")
        Ds = np.sqrt((qy - y) ** 2 + (qx - x) ** 2)
        Dr = np.abs(I[qy, qx] - I[y, x])
        C = np.exp(-(Ds**2) / (2 * sigma_s**2)) * np.exp(-(Dr**2) / (2 * sigma_r**2))
        keep = C >= threshold
        depth[qy[keep], qx[keep]] = d
        conf[qy[keep], qx[keep]] = C[keep]
    depth[ys, xs] = ds
    conf[ys, xs] = 1.0
    return depth, conf


_COLD = """
import time, numpy as np
t0 = time.perf_counter()
from sparsetools.ops.jbf import jbf_expand
t1 = time.perf_counter()
r = np.zeros((450, 800), np.float32); r[200, 400] = 10.0
jbf_expand(r, np.zeros((450, 800), np.uint8), fx=633.0, fy=633.0)
t2 = time.perf_counter()
print(f"{t1 - t0:.3f} {t2 - t1:.3f}")
"""


def first_call_seconds(cache_dir: str) -> tuple[float, float]:
    """(import, first call) seconds in a fresh interpreter using ``cache_dir`` as numba cache."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    out = subprocess.run(
        [sys.executable, "-c", _COLD], env=env, capture_output=True, text=True, check=True
    )
    a, b = out.stdout.split()
    return float(a), float(b)


def bench_size(width: int, height: int) -> dict:
    import cv2

    from sparsetools.ops.jbf import jbf_expand

    fx = NUSCENES_FX * width / 1600
    rgb = guidance_image(width, height)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    radar = radar_seeds(width, height)
    depth, conf = jbf_expand(radar, rgb, fx=fx, fy=fx)
    ref_depth, ref_conf = numpy_reference(radar, gray, fx=fx, fy=fx)
    assert np.array_equal(depth, ref_depth), "numba and numpy expansions differ"
    assert np.array_equal(conf, ref_conf), "numba and numpy confidences differ"
    n_seeds = int(np.count_nonzero(radar))
    n_out = int(np.count_nonzero(depth))
    print(
        f"{width}x{height}: {n_seeds} seeds -> {n_out} pixels ({100 * n_out / depth.size:.1f} %), "
        "depth and confidence identical to the numpy reference"
    )
    from sparsetools.ops.jbf import default_threads

    reference = lambda: numpy_reference(radar, gray, fx=fx, fy=fx)  # noqa: E731
    goal = 20.0 if (width, height) == (800, 450) else None
    compare_interleaved(
        f"jbf_expand {width}x{height}, {n_seeds} seeds, 1 thread",
        lambda: jbf_expand(radar, rgb, fx=fx, fy=fx, threads=1),
        reference,
        reference_name="numpy",
        repeat=15,
        goal=goal,
    )
    result = compare_interleaved(
        f"jbf_expand {width}x{height}, {n_seeds} seeds, {default_threads()} threads",
        lambda: jbf_expand(radar, rgb, fx=fx, fy=fx),
        reference,
        reference_name="numpy",
        repeat=15,
        goal=goal,
    )
    literal = algorithm1_numpy(radar, gray, fx=fx, fy=fx)
    # Same pixels and depths (depths are distinct, so no tie decides anything); confidences
    # may differ in the last float32 bit (sqrt then square).
    assert np.array_equal(literal[0], depth)
    t_lit = median_seconds(lambda: algorithm1_numpy(radar, gray, fx=fx, fy=fx), repeat=5)
    print(
        f"  literal Algorithm 1 in numpy (meshgrid, sqrt, fancy indexing): {t_lit * 1e3:.2f} ms"
        f" -> ratio {t_lit / (result['ours_ms'] / 1e3):.1f}x"
    )
    for kernel in ("range", "spatial"):
        t = median_seconds(lambda k=kernel: jbf_expand(radar, rgb, fx=fx, fy=fx, kernel=k))
        print(f"  kernel={kernel:<8} ours {t * 1e3:8.2f} ms | {load()}")
    t = median_seconds(lambda: jbf_expand(radar, rgb, fx=fx, fy=fx, range_metric="rgb"))
    print(f"  range_metric=rgb ours {t * 1e3:8.2f} ms | {load()}")
    return result


def kernel_args(radar, guide, fx: float, **kw) -> tuple:
    """The arguments ``jbf._expand`` passes to the one-thread compiled expansion (one call)."""
    from sparsetools.ops import jbf

    captured = []
    real = jbf.expand
    jbf.expand = lambda *args: (captured.append(args), real(*args))
    try:
        jbf.jbf_expand(radar, guide, fx=fx, fy=fx, threads=1, **kw)
    finally:
        jbf.expand = real
    return captured[0]


def separate_kernels():
    """``(expand_gray, expand_rgb)`` of :data:`SEPARATE_KERNELS_COMMIT`, or None outside a git
    checkout that has it. The module is self-contained (numba and numpy only): it is written
    to a temporary folder and imported from there by name (numba's cache finds it again)."""
    import importlib

    name = "src/sparsetools/ops/_jbf_kernels.py"
    r = subprocess.run(["git", "show", f"{SEPARATE_KERNELS_COMMIT}:{name}"], cwd=ROOT,
                       capture_output=True, text=True)  # fmt: skip
    if r.returncode != 0:
        return None
    # One folder per commit: numba's cache=True then compiles the old kernels once.
    folder = Path(tempfile.gettempdir()) / f"sparsetools-bench-jbf-{SEPARATE_KERNELS_COMMIT[:12]}"
    folder.mkdir(exist_ok=True)
    path = folder / "jbf_kernels_separate.py"
    if not path.exists() or path.read_text() != r.stdout:
        path.write_text(r.stdout)
    sys.path.insert(0, str(folder))
    try:
        module = importlib.import_module("jbf_kernels_separate")
    finally:
        sys.path.remove(str(folder))
    return module.expand_gray, module.expand_rgb


def merged_vs_separate(sizes=((800, 450), (1600, 900)), *, repeat: int = 41) -> list[dict]:
    """The merged band kernel against the gray and RGB kernels it replaced: same arguments,
    runs interleaved (merged, separate, merged, ...), one thread, medians of ``repeat``.

    Every combination of guidance (gray, rgb), conflict rule and size; both must give the same
    bytes. Prints one line each with the ratio merged / separate (> 1: the merged kernel is
    slower) and the load, then the worst ratio per guidance.
    """
    from sparsetools.ops._jbf_kernels import expand

    kernels = separate_kernels()
    if kernels is None:
        print(f"merged vs separate kernels: skipped (no git history {SEPARATE_KERNELS_COMMIT})")
        return []
    expand_gray, expand_rgb = kernels
    rows = []
    print(f"merged band kernel vs the separate gray/RGB kernels, 1 thread | {load()}")
    for width, height in sizes:
        fx = NUSCENES_FX * width / 1600
        rgb = guidance_image(width, height)
        radar = radar_seeds(width, height)
        for metric in ("gray", "rgb"):
            for conflict in ("nearest", "max-confidence"):
                args = kernel_args(radar, rgb, fx, range_metric=metric, conflict=conflict)
                guide = args[5]
                old_args = list(args[:6]) + list(args[7:])
                if metric == "gray":
                    old_args[5] = np.ascontiguousarray(guide[:, :, 0])
                separate = expand_gray if metric == "gray" else expand_rgb
                merged_out = np.empty((2, height, width), np.float32)
                separate_out = np.empty((2, height, width), np.float32)
                new_args = (*args[:-2], merged_out[0], merged_out[1])
                old_args = (*old_args[:-2], separate_out[0], separate_out[1])
                expand(*new_args)
                separate(*old_args)
                assert merged_out.tobytes() == separate_out.tobytes(), "merged kernel differs"
                t = _interleaved_wall_and_cpu(
                    {"merged": lambda a=new_args: expand(*a),
                     "separate": lambda a=old_args, f=separate: f(*a)},
                    repeat=repeat,
                )  # fmt: skip
                row = dict(size=f"{width}x{height}", guidance=metric, conflict=conflict,
                           load=os.getloadavg()[0])  # fmt: skip
                for clock in ("wall", "cpu"):
                    row[f"merged_{clock}_ms"] = t["merged"][clock] * 1e3
                    row[f"separate_{clock}_ms"] = t["separate"][clock] * 1e3
                    row[f"ratio_{clock}"] = t["merged"][clock] / t["separate"][clock]
                rows.append(row)
                print(
                    f"  {row['size']:>9} {metric:<4} {conflict:<14} merged/separate: wall "
                    f"{row['merged_wall_ms']:7.3f}/{row['separate_wall_ms']:7.3f} ms = "
                    f"{row['ratio_wall']:.3f}, thread CPU {row['merged_cpu_ms']:7.3f}/"
                    f"{row['separate_cpu_ms']:7.3f} ms = {row['ratio_cpu']:.3f} | {load()}"
                )
    for metric in ("gray", "rgb"):
        for clock in ("wall", "cpu"):
            ratios = [r[f"ratio_{clock}"] for r in rows if r["guidance"] == metric]
            mid = statistics.median(ratios)
            verdict = "within 3 %" if mid <= 1.03 else "NOT within 3 %"
            print(
                f"  {metric}: merged/separate ({clock}) median {mid:.3f} ({verdict}), "
                f"worst {max(ratios):.3f}"
            )
    return rows


def _interleaved_wall_and_cpu(fns: dict, *, repeat: int, warmup: int = 2) -> dict:
    """Median wall and thread-CPU seconds of each function, runs alternating (a b b a a b ...:
    each goes first in half the rounds, so neither always finds the caches the other left).

    The thread's CPU time counts only the cycles the kernel ran, not the time it waited for
    a core: on a shared machine it is the steadier of the two.
    """
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    times = {name: {"wall": [], "cpu": []} for name in fns}
    order = list(fns.items())
    for i in range(repeat):
        for name, fn in order if i % 2 == 0 else order[::-1]:
            c0, t0 = time.thread_time(), time.perf_counter()
            fn()
            t1, c1 = time.perf_counter(), time.thread_time()
            times[name]["wall"].append(t1 - t0)
            times[name]["cpu"].append(c1 - c0)
    return {
        name: {clock: statistics.median(v) for clock, v in by_clock.items()}
        for name, by_clock in times.items()
    }


def main() -> None:
    if "--kernels" in sys.argv[1:]:
        merged_vs_separate()
        return
    with tempfile.TemporaryDirectory() as cache:
        imp, cold = first_call_seconds(cache)
        _, warm = first_call_seconds(cache)
    print(f"first call in a fresh process, empty numba cache: {cold:.2f} s (compilation)")
    print(
        f"first call in a new process, cache=True cache filled: {warm * 1e3:.0f} ms "
        f"(import of sparsetools.ops.jbf, numba included: {imp * 1e3:.0f} ms)"
    )
    print(f"numpy reference single-threaded (one BLAS thread) | {load()}")
    for width, height in ((800, 450), (1600, 900)):
        bench_size(width, height)
    merged_vs_separate()


if __name__ == "__main__":
    from sparsetools.pipeline.executors import limit_blas_threads

    with limit_blas_threads(1):
        main()
