"""Radar depth expansion: range-aware joint bilateral expansion and the height-extend baseline.

Lo & Vandewalle, "Expanding Sparse Radar Depth Based on Joint Bilateral Filter for
Radar-Guided Monocular Depth Estimation", Sensors 24(6) 1864, 2024 (Algorithm 1), made precise
in METHODS.md section 3:

- every radar pixel p = (x, y) with depth d (a *seed*) opens a window of ``w fx / d`` by
  ``h fy / d`` pixels (a fixed real-world size, default 2.35 m x 2.35 m), symmetric and
  inclusive: offsets i in [-floor(u/2), floor(u/2)], j in [-floor(v/2), floor(v/2)], clipped
  to the image;
- a pixel q of the window gets the confidence
  ``C(q) = exp(-|p-q|^2 / (2 sigma_s^2)) * exp(-|I(p)-I(q)|^2 / (2 sigma_r^2))``
  (UNnormalised Gaussians) and is expanded with the seed's depth when ``C(q) >= threshold``;
- where windows overlap, the nearest seed wins (the paper processes the farthest seeds first
  so that nearer ones overwrite them); seed pixels keep their own depth.

The result does not depend on the order of the seeds: every pixel keeps the best
(depth, confidence) pair of all the seeds that reach it, in a total order (depth first, then
confidence; or the reverse for ``conflict="max-confidence"``).
"""

from __future__ import annotations

import itertools
import math
import os

import numpy as np

from ..errors import ParameterError
from ..validate import (
    check_choice,
    check_dtype,
    check_int_range,
    check_non_negative,
    check_positive,
    check_probability,
    check_same_shape,
    check_shape,
)
from ._jbf_kernels import (
    _offset_table,  # noqa: F401 - looked up here by the tests (cache check)
    band,
    expand,
    mark_seeds,
    prologue,
)

__all__ = [
    "CONFLICTS",
    "KERNELS",
    "RANGE_METRICS",
    "default_threads",
    "height_extend",
    "jbf_expand",
    "pruning_radius",
]

KERNELS = ("jbf", "range", "spatial")
RANGE_METRICS = ("gray", "rgb")
CONFLICTS = ("nearest", "max-confidence")


def pruning_radius(sigma_s: float, threshold: float) -> int:
    """Radius in pixels beyond which the spatial kernel alone is below ``threshold``.

    ``r_max = ceil(sigma_s * sqrt(2 ln(1 / threshold)))``: since the range kernel is at most 1,
    no pixel farther than ``r_max`` from its seed can reach the threshold, so pruning there is
    exact.
    """
    check_positive(sigma_s, "sigma_s")
    check_probability(threshold, "threshold")
    return int(math.ceil(sigma_s * math.sqrt(2.0 * math.log(1.0 / threshold))))


def _check_radar(radar_depth) -> np.ndarray:
    radar = np.asarray(radar_depth)
    check_shape(radar, "(H, W)", "radar_depth")
    if radar.dtype.kind in "iu":  # most likely a depth PNG read as it is stored: say how to read it
        if radar.dtype.itemsize == 1:
            raise ParameterError(
                f"is 8-bit ({radar.dtype}): it cannot hold metric depth; pass float metres "
                "(read_depth_png converts a KITTI uint16 PNG)",
                param="radar_depth",
            )
        raise ParameterError(
            f"must be float metres, got {radar.dtype} (a KITTI uint16 PNG stores depth * 256: "
            "read it with read_depth_png)",
            param="radar_depth",
        )
    check_dtype(radar, "radar_depth", "f")
    if radar.dtype not in (np.float32, np.float64):
        radar = radar.astype(np.float32)
    return radar


def _seeds(radar: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row, column (int64) and depth (float32) of every valid radar pixel, row-major order.

    Validity is judged on the float32 value (0 < d < inf; NaN fails), so a float64 depth
    too small or too large for float32 is not a seed.
    """
    flat = np.ascontiguousarray(radar).ravel()
    idx = np.flatnonzero(flat > 0)  # one vectorised pass; the few hits are checked further
    d = flat[idx].astype(np.float32)
    keep = (d > 0) & (d < np.inf)
    idx, d = idx[keep], d[keep]
    rows, cols = np.divmod(idx, radar.shape[1])
    return rows, cols, d


def _guidance_for(guidance, shape: tuple[int, int], range_metric: str, *, kernel: str = "jbf"):
    """Validated guidance: (H, W) uint8, or (H, W, 3) uint8 for the ``rgb`` metric."""
    g = np.asarray(guidance)
    if g.ndim == 3 and g.shape[2] == 1:
        g = g[:, :, 0]
    check_shape(g, "(H, W) | (H, W, 3)", "guidance")
    check_dtype(g, "guidance", (np.uint8,))
    check_same_shape(g, np.empty(shape, np.bool_), "guidance", "radar_depth", dims=2)
    if g.ndim == 3:
        if kernel == "spatial":
            g = g[:, :, 0]  # never looked at: skip the conversion
        elif range_metric == "gray":
            import cv2

            g = cv2.cvtColor(np.ascontiguousarray(g), cv2.COLOR_RGB2GRAY)
    # A 2-D guidance is used as given by both metrics (the RGB distance of one channel is |dI|).
    return np.ascontiguousarray(g)


def jbf_expand(
    radar_depth: np.ndarray,
    guidance: np.ndarray,
    *,
    fx: float,
    fy: float,
    sigma_s: float = 25.0,
    sigma_r: float = 10.0,
    threshold: float = 0.05,
    window_m: tuple[float, float] = (2.35, 2.35),
    kernel: str = "jbf",
    range_metric: str = "gray",
    conflict: str = "nearest",
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Expand sparse radar depth with the range-aware joint bilateral confidence.

    Parameters
    ----------
    radar_depth : (H, W) float32 or float64, metres
        Sparse radar depth; 0, negative or non-finite = no measurement. Every valid pixel is
        a seed.
    guidance : (H, W) or (H, W, 3) uint8
        Camera image of the same size. RGB is reduced to luminance with OpenCV's RGB-to-gray
        conversion for ``range_metric="gray"``; a 2-D guidance is used as given.
    fx, fy : float, pixels
        Focal lengths at this resolution (> 0).
    sigma_s : float, pixels
        Spatial kernel width (> 0). Ignored by ``kernel="range"``.
    sigma_r : float, intensity levels (0..255)
        Range kernel width (> 0). Ignored by ``kernel="spatial"``.
    threshold : float in (0, 1]
        A pixel is expanded when its confidence is ``>= threshold``.
    window_m : (float, float), metres
        Real-world window width and height (w, h); the window of a seed at depth d is
        ``w fx / d`` by ``h fy / d`` pixels. The paper uses 2.35 x 2.35 m, the authors'
        released scripts 1 x 2 m.
    kernel : {"jbf", "range", "spatial"}
        Both kernels (the method) or one of them alone (the paper's Table 5 ablation).
    range_metric : {"gray", "rgb"}
        ``|I(p) - I(q)|`` on luminance, or the Euclidean RGB distance.
    conflict : {"nearest", "max-confidence"}
        Which seed a pixel reached by several windows takes: the nearest (smallest depth;
        equal depths: the higher confidence), or the most confident (equal confidences: the
        smaller depth). Seeds that tie on both give the same output pixel.
    threads : int, optional
        Threads of the compiled kernel (bands of rows, one per thread). Default: 1 when
        ``NUMBA_NUM_THREADS`` or ``OMP_NUM_THREADS`` is 1 (batch worker processes), else
        numba's thread count (the CPUs this process may use). The result is the same for
        any value.

    Returns
    -------
    depth : (H, W) float32, metres
        Seeds keep their own depth; expanded pixels hold the depth of the winning seed;
        0 elsewhere.
    confidence : (H, W) float32 in [0, 1]
        1 at seeds, the winning confidence at expanded pixels, 0 elsewhere.

    Raises
    ------
    ParameterError
        Sizes differ, non-positive focal length or sigma, threshold outside (0, 1], 8-bit or
        non-2-D radar depth, unknown option.

    Notes
    -----
    The kernel is compiled with numba (``cache=True``: the first call in a fresh environment
    compiles for a few seconds, later processes load the cached machine code). Cost is
    O(seeds x window), with the window cut exactly at :func:`pruning_radius` when the
    spatial kernel takes part. With several threads the rows are split into bands of equal
    estimated work, each written by one thread only; small inputs run on one thread. The
    two returned arrays are views of one (2, H, W) buffer (one allocation instead of two).
    """
    radar = _check_radar(radar_depth)
    fx = check_positive(fx, "fx")
    fy = check_positive(fy, "fy")
    sigma_s = check_positive(sigma_s, "sigma_s")
    sigma_r = check_positive(sigma_r, "sigma_r")
    threshold = check_probability(threshold, "threshold")
    try:
        w_m, h_m = window_m
    except (TypeError, ValueError):
        raise ParameterError(
            f"must be two numbers (w, h) in metres, got {window_m!r}", param="window_m"
        ) from None
    w_m = check_positive(w_m, "window_m")
    h_m = check_positive(h_m, "window_m")
    check_choice(kernel, "kernel", KERNELS)
    check_choice(range_metric, "range_metric", RANGE_METRICS)
    check_choice(conflict, "conflict", CONFLICTS)
    if threads is not None:
        threads = check_int_range(threads, "threads", low=1)
    guide = _guidance_for(guidance, radar.shape, range_metric, kernel=kernel)

    rows, cols, depths = _seeds(radar)
    height, width = radar.shape
    if rows.size == 0:
        return np.zeros((height, width), np.float32), np.zeros((height, width), np.float32)
    half_u, half_v = _half_windows(depths, fx, fy, w_m, h_m)
    return _expand(
        rows,
        cols,
        depths,
        half_u,
        half_v,
        guide,
        sigma_s=sigma_s,
        sigma_r=sigma_r,
        threshold=threshold,
        kernel=kernel,
        conflict=conflict,
        threads=threads,
    )


def _half_windows(depths, fx, fy, w_m, h_m) -> tuple[np.ndarray, np.ndarray]:
    """floor(u / 2), floor(v / 2) with u = w fx / d, v = h fy / d (int64 pixels)."""
    d = depths.astype(np.float64)
    half_u = np.floor(w_m * fx / d / 2.0)
    half_v = np.floor(h_m * fy / d / 2.0)
    # A window wider than 2^31 pixels is clipped to the image anyway.
    big = float(2**31 - 1)
    return np.minimum(half_u, big).astype(np.int64), np.minimum(half_v, big).astype(np.int64)


#: Estimated pixel visits below which one thread is faster than starting several.
_PARALLEL_MIN_WORK = 200_000


def default_threads() -> int:
    """Threads :func:`jbf_expand` uses by default (see its ``threads`` parameter)."""
    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS"):
        if os.environ.get(var, "").strip() == "1":
            return 1  # a worker process of a batch: one thread per process
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


# Python threads run the nogil band kernels in parallel: no OpenMP runtime (its idle threads
# cost milliseconds to wake on some virtual machines, and it is not fork-safe). One pool per
# process: a forked child builds its own.
_POOL: tuple[int, int, object] | None = None


def _thread_pool(workers: int):
    global _POOL
    if _POOL is None or _POOL[0] != os.getpid() or _POOL[1] < workers:
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="sparsetools-jbf")
        _POOL = (os.getpid(), workers, pool)
    return _POOL[2]


def _row_bands(rows, half_v, half_u, height: int, width: int, reach: int, threads: int):
    """Row edges of ``threads`` bands of about equal work (None: one thread is enough).

    The work of a row is the sum of the window widths of the seeds whose window covers it
    (windows cut to ``reach`` pixels, the pruning radius).
    """
    if threads < 2:
        return None
    hv = np.minimum(half_v, reach)
    width_px = 2 * np.minimum(np.minimum(half_u, reach), width) + 1
    top = np.clip(rows - hv, 0, height)
    bottom = np.clip(rows + hv + 1, 0, height)
    change = np.zeros(height + 1)
    np.add.at(change, top, width_px)
    np.add.at(change, bottom, -width_px)
    total = np.cumsum(np.cumsum(change[:-1]))
    if total[-1] < _PARALLEL_MIN_WORK:
        return None
    inner = np.searchsorted(total, total[-1] * np.arange(1, threads) / threads)
    edges = np.unique(np.concatenate([[0], inner + 1, [height]]).clip(0, height))
    return edges.astype(np.int64) if edges.size > 2 else None


def _expand(
    rows,
    cols,
    depths,
    half_u,
    half_v,
    guide,
    *,
    sigma_s,
    sigma_r,
    threshold,
    kernel,
    conflict,
    order=None,
    threads=None,
    edges=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Build the lookup tables and run the compiled kernel.

    ``order`` is the order in which the kernel visits the seeds (default: nearest first, which
    is fastest), ``edges`` the row bands of the threaded kernel (default: from ``threads``);
    the result depends on neither, and the tests check that with random ones.
    """
    height, width = guide.shape[:2]
    use_spatial = kernel in ("jbf", "spatial")
    use_range = kernel in ("jbf", "range")
    # One kernel for any channel count: the guidance as (H, W, C), and C as the length of a
    # tuple, which numba compiles into the kernel (one machine code per C).
    guide = guide.reshape(height, width, -1)
    channels = tuple(range(guide.shape[2]))

    # Squared distances are integers, so both Gaussians are tables indexed by them. Entries
    # past a table can never pass the threshold (each kernel is <= 1), which makes the cut
    # exact: for the spatial one it is the disc of radius r_max. The running minimum is a
    # no-op for any sane sigma (consecutive arguments differ by far more than exp's rounding
    # error); it guarantees the monotonicity the kernel's binary search relies on.
    reach = max(height, width)
    if use_spatial:
        r_max = pruning_radius(sigma_s, threshold)
        reach = r_max
        hu = int(min(half_u.max(), width - 1))
        hv = int(min(half_v.max(), height - 1))
        r2_limit = min(r_max * r_max, hu * hu + hv * hv)
        r2 = np.arange(r2_limit + 1, dtype=np.float64)
        spatial_lut = np.minimum.accumulate(np.exp(-r2 / (2.0 * sigma_s**2)))
    else:
        spatial_lut = np.ones(1, dtype=np.float64)
    if use_range:
        max_sq = 255 * 255 * len(channels)
        cut = 2.0 * sigma_r**2 * math.log(1.0 / threshold)
        n = int(min(max_sq, math.ceil(cut))) + 1
        dI2 = np.arange(n, dtype=np.float64)
        range_lut = np.minimum.accumulate(np.exp(-dI2 / (2.0 * sigma_r**2)))
    else:
        range_lut = np.ones(1, dtype=np.float64)

    if order is None:
        # Nearest seeds first: with conflict="nearest" a pixel already taken by a nearer seed
        # is then skipped before its confidence is computed.
        order = np.argsort(depths, kind="stable")
    if edges is None:
        n_threads = default_threads() if threads is None else int(threads)
        edges = _row_bands(rows, half_v, half_u, height, width, reach, n_threads)
    # One block for both outputs: a single allocation is much cheaper than two fresh ones.
    out = np.empty((2, height, width), np.float32)
    args = (
        np.ascontiguousarray(rows[order], dtype=np.int64),
        np.ascontiguousarray(cols[order], dtype=np.int64),
        np.ascontiguousarray(depths[order], dtype=np.float32),
        np.ascontiguousarray(half_u[order], dtype=np.int64),
        np.ascontiguousarray(half_v[order], dtype=np.int64),
        np.ascontiguousarray(guide),
        channels,
        spatial_lut,
        range_lut,
        use_spatial,
        use_range,
        float(threshold),
        conflict == "max-confidence",
        out[0],
        out[1],
    )
    if edges is None:
        expand(*args)
    else:
        _expand_bands(args, [int(e) for e in edges])
    return out[0], out[1]


def _expand_bands(args, edges: list[int]) -> None:
    """The compiled expansion on row bands ``edges[b]:edges[b + 1]``, one per thread."""
    (rows, cols, depths, half_u, half_v, guide, channels, spatial_lut, range_lut, use_spatial,
     use_range, threshold, max_confidence, depth, conf) = args  # fmt: skip
    tables = prologue(rows, cols, depths, spatial_lut, range_lut, use_spatial, use_range,
                      threshold, depth, conf)  # fmt: skip
    head = (rows, cols, depths, half_u, half_v, guide, channels, spatial_lut, range_lut,
            use_spatial, use_range, max_confidence, *tables, depth, conf)  # fmt: skip
    bands = list(itertools.pairwise(edges))
    pool = _thread_pool(len(bands) - 1) if len(bands) > 1 else None
    futures = [pool.submit(band, *head, lo, hi) for lo, hi in bands[1:]]
    band(*head, *bands[0])  # this thread takes the first band
    for f in futures:
        f.result()
    mark_seeds(rows, cols, depths, depth, conf)


def height_extend(
    radar_depth: np.ndarray, *, fy: float, below_m: float = 0.25, above_m: float = 1.5
) -> np.ndarray:
    """Baseline of Lo & Vandewalle (ICIP 2021): extend each radar point vertically.

    Each seed at row y, depth d covers its own column from ``floor(above_m fy / d)`` rows
    above (smaller row index) to ``floor(below_m fy / d)`` rows below, clipped to the image.
    Where segments overlap the nearest depth wins (seed pixels included: a nearer point's
    segment occludes a farther point, as projecting the extended 3-D points with a z-buffer
    would).

    Parameters
    ----------
    radar_depth : (H, W) float, metres; 0, negative or non-finite = empty.
    fy : float, pixels (> 0)
    below_m, above_m : float, metres (>= 0)

    Returns
    -------
    (H, W) float32, metres, 0 = empty.
    """
    radar = _check_radar(radar_depth)
    fy = check_positive(fy, "fy")
    check_non_negative(below_m, "below_m")
    check_non_negative(above_m, "above_m")
    height, width = radar.shape
    rows, cols, depths = _seeds(radar)
    out = np.full(height * width, np.inf, dtype=np.float32)
    if rows.size:
        d = depths.astype(np.float64)
        top = np.maximum(rows - np.floor(above_m * fy / d).astype(np.int64), 0)
        bottom = np.minimum(rows + np.floor(below_m * fy / d).astype(np.int64), height - 1)
        length = bottom - top + 1
        # Every covered pixel once: segment starts repeated, plus a running offset in each.
        seg = np.repeat(np.arange(rows.size), length)
        starts = np.cumsum(length) - length
        offset = np.arange(seg.size) - starts[seg]
        flat = (top[seg] + offset) * width + cols[seg]
        np.minimum.at(out, flat, depths[seg])
    out[np.isinf(out)] = 0
    return out.reshape(height, width)
