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

import math

import numba
import numpy as np

from ..errors import ParameterError

__all__ = ["CONFLICTS", "KERNELS", "RANGE_METRICS", "height_extend", "jbf_expand", "pruning_radius"]

KERNELS = ("jbf", "range", "spatial")
RANGE_METRICS = ("gray", "rgb")
CONFLICTS = ("nearest", "max-confidence")


def pruning_radius(sigma_s: float, threshold: float) -> int:
    """Radius in pixels beyond which the spatial kernel alone is below ``threshold``.

    ``r_max = ceil(sigma_s * sqrt(2 ln(1 / threshold)))``: since the range kernel is at most 1,
    no pixel farther than ``r_max`` from its seed can reach the threshold, so pruning there is
    exact.
    """
    return int(math.ceil(sigma_s * math.sqrt(2.0 * math.log(1.0 / threshold))))


def _check_positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ParameterError(f"{name} must be finite and > 0, got {value!r}")
    return v


def _check_radar(radar_depth) -> np.ndarray:
    radar = np.asarray(radar_depth)
    if radar.ndim != 2:
        raise ParameterError(f"radar_depth must be a 2-D (H, W) depth map, got shape {radar.shape}")
    if radar.dtype.kind != "f":
        if radar.dtype.itemsize == 1:
            raise ParameterError(
                f"radar_depth is 8-bit ({radar.dtype}): it cannot hold metric depth; pass float "
                "metres (read_depth_png converts a KITTI uint16 PNG)"
            )
        raise ParameterError(
            f"radar_depth must be float metres, got {radar.dtype} (a KITTI uint16 PNG stores "
            "depth * 256: read it with read_depth_png)"
        )
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
    if g.ndim not in (2, 3) or (g.ndim == 3 and g.shape[2] != 3):
        raise ParameterError(f"guidance must be (H, W) or (H, W, 3), got shape {g.shape}")
    if g.dtype != np.uint8:
        raise ParameterError(f"guidance must be uint8 (0..255), got {g.dtype}")
    if g.shape[:2] != shape:
        raise ParameterError(
            f"guidance is {g.shape[1]}x{g.shape[0]} but the radar depth map is "
            f"{shape[1]}x{shape[0]} (W x H): they must have the same size"
        )
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
    spatial kernel takes part. Single-threaded: batches parallelise over frames. The two
    returned arrays are views of one (2, H, W) buffer (one allocation instead of two).
    """
    radar = _check_radar(radar_depth)
    fx = _check_positive("fx", fx)
    fy = _check_positive("fy", fy)
    sigma_s = _check_positive("sigma_s", sigma_s)
    sigma_r = _check_positive("sigma_r", sigma_r)
    threshold = float(threshold)
    if not (0.0 < threshold <= 1.0):
        raise ParameterError(f"threshold must be in (0, 1], got {threshold}")
    try:
        w_m, h_m = (float(v) for v in window_m)
    except (TypeError, ValueError):
        raise ParameterError(
            f"window_m must be two numbers (w, h) in metres, got {window_m!r}"
        ) from None
    w_m = _check_positive("window width", w_m)
    h_m = _check_positive("window height", h_m)
    if kernel not in KERNELS:
        raise ParameterError(f"kernel must be one of {', '.join(KERNELS)}, got {kernel!r}")
    if range_metric not in RANGE_METRICS:
        raise ParameterError(
            f"range_metric must be one of {', '.join(RANGE_METRICS)}, got {range_metric!r}"
        )
    if conflict not in CONFLICTS:
        raise ParameterError(f"conflict must be one of {', '.join(CONFLICTS)}, got {conflict!r}")
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
    )


def _half_windows(depths, fx, fy, w_m, h_m) -> tuple[np.ndarray, np.ndarray]:
    """floor(u / 2), floor(v / 2) with u = w fx / d, v = h fy / d (int64 pixels)."""
    d = depths.astype(np.float64)
    half_u = np.floor(w_m * fx / d / 2.0)
    half_v = np.floor(h_m * fy / d / 2.0)
    # A window wider than 2^31 pixels is clipped to the image anyway.
    big = float(2**31 - 1)
    return np.minimum(half_u, big).astype(np.int64), np.minimum(half_v, big).astype(np.int64)


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
) -> tuple[np.ndarray, np.ndarray]:
    """Build the lookup tables and run the compiled kernel.

    ``order`` is the order in which the kernel visits the seeds (default: nearest first, which
    is fastest); the result does not depend on it, and the tests check that with random ones.
    """
    height, width = guide.shape[:2]
    use_spatial = kernel in ("jbf", "spatial")
    use_range = kernel in ("jbf", "range")
    rgb = guide.ndim == 3

    # Squared distances are integers, so both Gaussians are tables indexed by them. Entries
    # past a table can never pass the threshold (each kernel is <= 1), which makes the cut
    # exact: for the spatial one it is the disc of radius r_max. The running minimum is a
    # no-op for any sane sigma (consecutive arguments differ by far more than exp's rounding
    # error); it guarantees the monotonicity the kernel's binary search relies on.
    if use_spatial:
        r_max = pruning_radius(sigma_s, threshold)
        hu = int(min(half_u.max(), width - 1))
        hv = int(min(half_v.max(), height - 1))
        r2_limit = min(r_max * r_max, hu * hu + hv * hv)
        r2 = np.arange(r2_limit + 1, dtype=np.float64)
        spatial_lut = np.minimum.accumulate(np.exp(-r2 / (2.0 * sigma_s**2)))
    else:
        spatial_lut = np.ones(1, dtype=np.float64)
    if use_range:
        max_sq = 255 * 255 * (3 if rgb else 1)
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
    # One block for both outputs: a single allocation is much cheaper than two fresh ones.
    out = np.empty((2, height, width), np.float32)
    kernel_fn = _expand_rgb if rgb else _expand_gray
    kernel_fn(
        np.ascontiguousarray(rows[order], dtype=np.int64),
        np.ascontiguousarray(cols[order], dtype=np.int64),
        np.ascontiguousarray(depths[order], dtype=np.float32),
        np.ascontiguousarray(half_u[order], dtype=np.int64),
        np.ascontiguousarray(half_v[order], dtype=np.int64),
        np.ascontiguousarray(guide),
        spatial_lut,
        range_lut,
        use_spatial,
        use_range,
        float(threshold),
        conflict == "max-confidence",
        out[0],
        out[1],
    )
    return out[0], out[1]


# -- compiled kernel ----------------------------------------------------------------------------
#
# For every seed the kernels visit the rows of its window, cut to the pruning disc, in two
# passes per row:
#
# 1. a candidate mask, computed with affine loads only so that LLVM vectorises it: a pixel at
#    offset (i, j) passes iff its squared intensity difference t is <= pass_t[j, i], the
#    largest t that passes at that offset (an exact integer form of C >= threshold, see
#    _offset_table), and, for conflict="nearest", it is not already taken by a nearer seed;
# 2. the few candidates, found 8 mask bytes at a time, get their confidence from the lookup
#    tables and are updated.
#
# Loop indices start at 0 so that numba emits no negative-index wraparound code.

# Internal confidence of a seed pixel: above any real confidence, so nothing replaces it.
_SEED_CONF = np.float32(2.0)
_ANY_T = 1 << 30  # passes whatever the intensity difference (above 3 * 255^2)
_BYTES_LOW = np.uint64(0x0101010101010101)
_BYTES_GATHER = np.uint64(0x0102040810204080)


@numba.njit(cache=True, nogil=True)
def _largest_passing_t(w, range_lut, threshold):  # pragma: no cover - compiled
    """Largest t with ``w * range_lut[t] >= threshold`` (-1: none).

    ``range_lut`` is non-increasing and multiplying by ``w > 0`` is monotone in IEEE
    arithmetic, so the passing t form a prefix and a binary search finds its end exactly.
    """
    if not (w * range_lut[0] >= threshold):
        return -1
    lo = 0
    hi = range_lut.shape[0] - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if w * range_lut[mid] >= threshold:
            lo = mid
        else:
            hi = mid - 1
    return lo


@numba.njit(cache=True, nogil=True)
def _offset_table(spatial_lut, range_lut, use_spatial, use_range, threshold, height, width):
    """Largest passing squared intensity difference at each pixel offset.

    Returns ``(pass_t, half_width, center)``. With the spatial kernel, ``pass_t[j, center + i]``
    is the table for offsets (i, j), |i|, |j| <= R (the disc radius), and ``half_width[j]``
    the largest |i| that can pass in row offset j (-1: none). Without it, every offset is
    alike: one row of ``2 width + 1`` entries and no row limit.
    """  # pragma: no cover - compiled
    if not use_spatial:
        t = _largest_passing_t(1.0, range_lut, threshold) if use_range else _ANY_T
        pass_t = np.full((1, 2 * width + 1), t, dtype=np.int32)
        half_width = np.full(height + 1, width + 1, dtype=np.int64)
        return pass_t, half_width, width
    r2_last = spatial_lut.shape[0] - 1
    R = np.int64(np.sqrt(r2_last)) + 1
    pass_t = np.full((R + 1, 2 * R + 1), -1, dtype=np.int32)
    half_width = np.full(R + 1, -1, dtype=np.int64)
    for j in range(R + 1):
        for i in range(R + 1):
            r2 = i * i + j * j
            if r2 > r2_last:
                break
            if use_range:
                t = _largest_passing_t(spatial_lut[r2], range_lut, threshold)
            else:
                t = _ANY_T if spatial_lut[r2] >= threshold else -1
            pass_t[j, R + i] = t
            pass_t[j, R - i] = t
            if t >= 0:
                half_width[j] = i
    return pass_t, half_width, R


@numba.njit(cache=True, nogil=True)
def _byte_positions():  # pragma: no cover - compiled
    """For each 8-bit pattern: how many bits are set, and their positions."""
    positions = np.zeros((256, 8), dtype=np.int64)
    counts = np.zeros(256, dtype=np.int64)
    for b in range(256):
        c = 0
        for p in range(8):
            if (b >> p) & 1:
                positions[b, c] = p
                c += 1
        counts[b] = c
    return positions, counts


@numba.njit(cache=True, nogil=True)
def _mark_seeds(rows, cols, depths, depth, conf, value):  # pragma: no cover - compiled
    for s in range(rows.shape[0]):
        depth[rows[s], cols[s]] = depths[s]
        conf[rows[s], cols[s]] = value


@numba.njit(cache=True, nogil=True)
def _better(d, c, bd, bc, max_confidence):  # pragma: no cover - compiled
    """Whether (d, c) replaces the current (bd, bc) of a pixel that is not a seed.

    A total order on (depth, confidence) pairs, so the result does not depend on the order
    of the seeds (equal pairs are the same output).
    """
    if bd == 0:
        return True
    if max_confidence:
        return c > bc or (c == bc and d < bd)
    return d < bd or (d == bd and c > bc)


@numba.njit(cache=True, nogil=True)
def _expand_gray(
    rows,
    cols,
    depths,
    half_u,
    half_v,
    guide,
    spatial_lut,
    range_lut,
    use_spatial,
    use_range,
    threshold,
    max_confidence,
    depth,
    conf,
):  # pragma: no cover - compiled
    """Kernel for an (H, W) uint8 guidance (see :func:`_expand`)."""
    height, width = guide.shape
    depth[:, :] = 0.0
    conf[:, :] = 0.0
    _mark_seeds(rows, cols, depths, depth, conf, _SEED_CONF)
    pass_t, half_width, center = _offset_table(
        spatial_lut, range_lut, use_spatial, use_range, threshold, height, width
    )
    positions, counts = _byte_positions()
    mask = np.zeros(8 * ((width + 7) // 8 + 1), dtype=np.uint8)
    words = mask.view(np.uint64)
    for s in range(rows.shape[0]):
        y0 = rows[s]
        x0 = cols[s]
        d = depths[s]
        g0 = np.int32(guide[y0, x0])
        hv = min(half_v[s], half_width.shape[0] - 1)
        for y in range(max(y0 - hv, 0), min(y0 + hv, height - 1) + 1):
            j = abs(y - y0)
            hu = min(half_u[s], half_width[j])
            left = max(x0 - hu, 0)
            right = min(x0 + hu, width - 1) + 1
            m = right - left
            if m <= 0:
                continue
            g_seg = guide[y, left:right]
            d_seg = depth[y, left:right]
            t_seg = pass_t[j if use_spatial else 0, center + left - x0 : center + right - x0]
            if max_confidence:
                for k in range(m):
                    diff = np.int32(g_seg[k]) - g0
                    mask[k] = np.uint8(diff * diff <= t_seg[k])
            else:
                for k in range(m):
                    diff = np.int32(g_seg[k]) - g0
                    bd = d_seg[k]
                    mask[k] = np.uint8((diff * diff <= t_seg[k]) & ((bd == 0) | (bd >= d)))
            n_words = (m + 7) // 8
            for k in range(m, n_words * 8):
                mask[k] = 0
            c_seg = conf[y, left:right]
            j2 = (y - y0) * (y - y0)
            for w in range(n_words):
                word = words[w]
                if word == 0:
                    continue
                b = ((word & _BYTES_LOW) * _BYTES_GATHER) >> np.uint64(56)
                for p in range(counts[b]):
                    k = w * 8 + positions[b, p]
                    bc = c_seg[k]
                    if bc == _SEED_CONF:
                        continue
                    t = 0
                    if use_range:
                        diff = np.int64(g_seg[k]) - g0
                        t = diff * diff
                    if use_spatial:
                        i = left + k - x0
                        c = np.float32(spatial_lut[i * i + j2] * range_lut[t])
                    else:
                        c = np.float32(range_lut[t])
                    if _better(d, c, d_seg[k], bc, max_confidence):
                        d_seg[k] = d
                        c_seg[k] = c
    _mark_seeds(rows, cols, depths, depth, conf, np.float32(1.0))


@numba.njit(cache=True, nogil=True)
def _expand_rgb(
    rows,
    cols,
    depths,
    half_u,
    half_v,
    guide,
    spatial_lut,
    range_lut,
    use_spatial,
    use_range,
    threshold,
    max_confidence,
    depth,
    conf,
):  # pragma: no cover - compiled
    """Kernel for an (H, W, 3) uint8 guidance compared by Euclidean RGB distance."""
    height, width, _ = guide.shape
    depth[:, :] = 0.0
    conf[:, :] = 0.0
    _mark_seeds(rows, cols, depths, depth, conf, _SEED_CONF)
    pass_t, half_width, center = _offset_table(
        spatial_lut, range_lut, use_spatial, use_range, threshold, height, width
    )
    positions, counts = _byte_positions()
    mask = np.zeros(8 * ((width + 7) // 8 + 1), dtype=np.uint8)
    words = mask.view(np.uint64)
    for s in range(rows.shape[0]):
        y0 = rows[s]
        x0 = cols[s]
        d = depths[s]
        r0 = np.int32(guide[y0, x0, 0])
        g0 = np.int32(guide[y0, x0, 1])
        b0 = np.int32(guide[y0, x0, 2])
        hv = min(half_v[s], half_width.shape[0] - 1)
        for y in range(max(y0 - hv, 0), min(y0 + hv, height - 1) + 1):
            j = abs(y - y0)
            hu = min(half_u[s], half_width[j])
            left = max(x0 - hu, 0)
            right = min(x0 + hu, width - 1) + 1
            m = right - left
            if m <= 0:
                continue
            p_seg = guide[y, left:right]
            d_seg = depth[y, left:right]
            t_seg = pass_t[j if use_spatial else 0, center + left - x0 : center + right - x0]
            for k in range(m):
                dr = np.int32(p_seg[k, 0]) - r0
                dg = np.int32(p_seg[k, 1]) - g0
                db = np.int32(p_seg[k, 2]) - b0
                ok = dr * dr + dg * dg + db * db <= t_seg[k]
                if not max_confidence:
                    bd = d_seg[k]
                    ok = ok & ((bd == 0) | (bd >= d))
                mask[k] = np.uint8(ok)
            n_words = (m + 7) // 8
            for k in range(m, n_words * 8):
                mask[k] = 0
            c_seg = conf[y, left:right]
            j2 = (y - y0) * (y - y0)
            for w in range(n_words):
                word = words[w]
                if word == 0:
                    continue
                b = ((word & _BYTES_LOW) * _BYTES_GATHER) >> np.uint64(56)
                for p in range(counts[b]):
                    k = w * 8 + positions[b, p]
                    bc = c_seg[k]
                    if bc == _SEED_CONF:
                        continue
                    t = 0
                    if use_range:
                        dr = np.int64(p_seg[k, 0]) - r0
                        dg = np.int64(p_seg[k, 1]) - g0
                        db = np.int64(p_seg[k, 2]) - b0
                        t = dr * dr + dg * dg + db * db
                    if use_spatial:
                        i = left + k - x0
                        c = np.float32(spatial_lut[i * i + j2] * range_lut[t])
                    else:
                        c = np.float32(range_lut[t])
                    if _better(d, c, d_seg[k], bc, max_confidence):
                        d_seg[k] = d
                        c_seg[k] = c
    _mark_seeds(rows, cols, depths, depth, conf, np.float32(1.0))


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
    fy = _check_positive("fy", fy)
    for name, v in (("below_m", below_m), ("above_m", above_m)):
        if not (math.isfinite(float(v)) and float(v) >= 0):
            raise ParameterError(f"{name} must be finite and >= 0, got {v!r}")
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
