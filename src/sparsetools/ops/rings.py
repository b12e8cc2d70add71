"""LiDAR rings: recover each point's laser (ring 0 = highest), and per-ring diagnostics.

METHODS.md section 2.

- :func:`scan_order_rings`: a raw KITTI HDL-64E ``.bin`` stores its points laser by laser,
  each laser one sweep in azimuth; a new laser starts where the azimuth jumps back by more
  than 90 deg. This is exact and is the primary method.
- :func:`elevation_rings`: the fallback for clouds whose order was lost (shuffled, merged).
  Points are assigned to the nearest cone ``z = r tan(a) + h``: the cones of a
  :class:`~sparsetools.ops.lidar_profile.SensorProfile` when one is given (exact on KITTI),
  otherwise cones estimated from the cloud itself (1-D k-means of offset-corrected elevation
  seeded at histogram peaks, then a few rounds of cone fitting).
- :func:`column_rings`: clouds that carry the ring in a column (nuScenes LIDAR_TOP).
- :func:`recover_rings`: scan order, validated (exactly ``n_lasers`` rings), with a logged
  fall back to elevation.
- :func:`ring_table`, :func:`ring_elevations`: per-ring statistics (:mod:`.ring_stats`,
  re-exported here).
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import FormatError, ParameterError
from ..validate import check_choice, check_int_range, check_non_negative
from .lidar_profile import (
    MIN_FIT_RANGE,
    OFFSET_BOUND,
    RIDGE,
    SensorProfile,
    check_lidar_points,
    check_n_lasers,
    check_ring_labels,
    elevation_deg,
    fit_cones,
    polar_coordinates,
)
from .ring_stats import RingTable, ring_elevations, ring_table

__all__ = [
    "RING_METHODS",
    "RingTable",
    "column_rings",
    "cone_residual_deg",
    "elevation_rings",
    "recover_rings",
    "recover_rings_with_method",
    "ring_elevations",
    "ring_table",
    "scan_order_rings",
]

log = logging.getLogger(__name__)

RING_METHODS = ("scan-order", "elevation", "column")
_JUMP_DEG = 90.0


# -- ring recovery -------------------------------------------------------------------------------


def scan_order_rings(points: np.ndarray, *, n_lasers: int | None = None) -> np.ndarray:
    """Rings from the storage order of a raw scan: a new ring where azimuth jumps back.

    The azimuth ``atan2(y, x)`` is measured in the sweep direction (found from the median
    step) from a cut angle: straight ahead first (KITTI: every laser's sweep starts near
    azimuth 0), then straight behind (sensors and simulators whose sweeps start at -180 deg).
    A step back of more than 90 deg starts a new ring.

    Parameters
    ----------
    points : (N, C) float, metres, in the file's order
    n_lasers : int, optional
        When given, the first cut that yields exactly this many rings is used; otherwise (or
        when none does) the front cut.

    Returns
    -------
    ring : (N,) int32
        0 for the first ring stored; with KITTI's order 0 is the highest laser.
    """
    points = check_lidar_points(points, allow_empty=True)
    if n_lasers is not None:
        check_n_lasers(n_lasers)
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, np.int32)
    # float32 is ample for telling a ~0.2-deg step from a ~360-deg jump, and twice as fast.
    xy = points[:, :2].astype(np.float32, copy=False)
    az = np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))
    step = np.diff(az)
    # Steps wrapped into [-180, 180] are negative for -180 <= step < 0 and 180 < step < 360.
    backwards = np.count_nonzero((step < 0) & (step >= -180)) + np.count_nonzero(
        (step > 180) & (step < 360)
    )
    if backwards > step.size // 2:  # the median step is negative
        az = -az
    first = None
    for cut in (0.0, 180.0):
        starts = np.flatnonzero(np.diff(_angle_from(az, cut)) < -_JUMP_DEG) + 1
        if n_lasers is None or starts.size + 1 == n_lasers or first is None:
            # Rings are runs of the scan: ring k spans starts[k-1]:starts[k].
            lengths = np.diff(starts, prepend=0, append=n)
            ring = np.repeat(np.arange(starts.size + 1, dtype=np.int32), lengths)
            if n_lasers is None or starts.size + 1 == n_lasers:
                return ring
            first = ring
    return first


def _angle_from(az: np.ndarray, cut: float) -> np.ndarray:
    """``(az - cut) % 360`` (float32 degrees, az in about [-180, 180]) without the slow
    remainder: for ``-360 < a < 0`` numpy's remainder is ``a + 360``, rounded alike."""
    a = az - np.float32(cut)
    beyond = a <= -360.0  # az a hair past -180 deg (float32 pi) with the back cut
    if beyond.any():
        a[beyond] = np.remainder(a[beyond], np.float32(360.0))
    np.add(a, np.float32(360.0), out=a, where=a < 0)
    return a


def column_rings(points: np.ndarray, *, n_lasers: int = 32, column: int = 4) -> np.ndarray:
    """Rings stored in a column of the cloud (nuScenes LIDAR_TOP: 5th float, 0..31).

    The column's numbering is flipped when its lowest value is the lowest laser (as in
    nuScenes, where 0 is the bottom laser), so that ring 0 is the highest here too. Rows keep
    their own column unchanged.

    Raises
    ------
    FormatError
        No such column, non-integer values or values outside 0..n_lasers-1.
    """
    points = check_lidar_points(points, allow_empty=True)
    n_lasers = check_n_lasers(n_lasers)
    column = check_int_range(column, "column", low=0)
    if points.shape[1] <= column:
        raise FormatError(
            f"the cloud has {points.shape[1]} columns: no ring column {column} "
            "(use --ring-method scan-order or elevation)"
        )
    col = points[:, column]
    if not np.all(np.isfinite(col)) or np.any(col != np.round(col)):
        raise FormatError(f"column {column} does not hold integer ring numbers")
    ring = col.astype(np.int64)
    if ring.size and (ring.min() < 0 or ring.max() >= n_lasers):
        raise FormatError(
            f"ring column holds {ring.min()}..{ring.max()}, expected 0..{n_lasers - 1} "
            "(wrong --lasers?)"
        )
    if ring.size:
        lo, hi = ring.min(), ring.max()
        el = elevation_deg(points)
        if lo != hi and np.median(el[ring == lo]) < np.median(el[ring == hi]):
            ring = (n_lasers - 1) - ring
    return ring.astype(np.int32)


def _assign_nearest_cone(r, z, slope, offset, *, chunk=1 << 15, ambiguity=False):
    """Cone nearest in angle ``|(z - h) / r - s|`` for every point (NaN cones never win).

    With ``ambiguity``, also the ratio of the nearest to the second-nearest distance
    (near 0: clear-cut; near 1: the point lies between two lasers).
    """
    valid = np.isfinite(slope) & np.isfinite(offset)
    s, h = slope[valid], offset[valid]
    ids = np.flatnonzero(valid)
    out = np.empty(r.shape[0], np.intp)
    ratio = np.zeros(r.shape[0]) if ambiguity else None
    rr = np.maximum(r, 1e-6)
    for i in range(0, r.shape[0], chunk):  # chunks of points bound the (chunk, L) temporary
        sl = slice(i, i + chunk)
        err = np.abs((z[sl, None] - h[None, :]) / rr[sl, None] - s[None, :])
        out[sl] = ids[np.argmin(err, axis=1)]
        if ambiguity and s.size > 1:
            two = np.partition(err, 1, axis=1)[:, :2]
            ratio[sl] = two[:, 0] / np.maximum(two[:, 1], 1e-15)
    return (out, ratio) if ambiguity else out


def _rank_by_slope(label, slope, k):
    order = np.argsort(-np.where(np.isfinite(slope), slope, -np.inf), kind="stable")
    rank = np.empty(k, np.intp)
    rank[order] = np.arange(k)
    return rank[label]


def _histogram_peak_centres(x: np.ndarray, k: int, width: float = 0.02) -> np.ndarray:
    lo, hi = float(x.min()), float(x.max())
    nbins = int(np.ceil((hi - lo) / width)) + 3
    counts = np.bincount(((x - lo) / width).astype(np.intp) + 1, minlength=nbins)
    smooth = np.convolve(counts, np.ones(5) / 5, mode="same")
    peak = np.flatnonzero((smooth[1:-1] >= smooth[:-2]) & (smooth[1:-1] > smooth[2:])) + 1
    top = peak[np.argsort(-smooth[peak], kind="stable")[:k]]
    centres = lo + (top - 0.5) * width
    if centres.size < k:  # fewer peaks than lasers: fill in with quantiles
        extra = np.quantile(x, (np.arange(k - centres.size) + 0.5) / (k - centres.size))
        centres = np.concatenate([centres, extra])
    return np.sort(centres)


def _kmeans_1d(x: np.ndarray, centres: np.ndarray, iterations: int = 100) -> np.ndarray:
    k = centres.size
    for _ in range(iterations):
        centres = np.sort(centres)
        label = np.searchsorted((centres[1:] + centres[:-1]) / 2, x)
        total = np.bincount(label, x, k)
        count = np.bincount(label, minlength=k)
        new = np.where(count > 0, total / np.maximum(count, 1), centres)
        if np.array_equal(new, centres):
            break
        centres = new
    return np.sort(centres)


def _best_offset(r, z, offsets):
    """Offset h making the histogram of atan2(z - h, r) sharpest (lowest entropy)."""
    best, best_h = np.inf, 0.0
    for h in offsets:  # a few dozen candidates, each one vectorised over the points
        e = np.degrees(np.arctan2(z - h, r))
        counts = np.bincount(((e - e.min()) / 0.05).astype(np.intp))
        p = counts[counts > 0] / e.size
        ent = -np.sum(p * np.log(p))
        if ent < best:
            best, best_h = ent, float(h)
    return best_h


def _generic_cones(r, z, k, *, min_range=3.0, bands=8, rounds=10, ridge=RIDGE, bound=OFFSET_BOUND):
    """Estimate k laser cones from the cloud alone: (slope, offset) or None on failure."""
    use = r > min_range
    if np.count_nonzero(use) < 3 * k:
        use = r > MIN_FIT_RANGE
    if np.count_nonzero(use) < 3 * k:
        return None
    ru, zu = r[use], z[use]
    # The emitters sit a few decimetres above the origin, so at short range one laser's raw
    # elevation spreads over a degree. Correcting for that offset (estimated per elevation band:
    # the HDL-64E's two blocks differ) separates the lasers well enough to seed the cones.
    e0 = np.degrees(np.arctan2(zu, ru))
    edges = np.quantile(e0, np.linspace(0, 1, bands + 1)[1:-1])
    band = np.searchsorted(edges, e0)
    offsets = np.linspace(-0.5, 0.5, 51)
    h_band = np.array(
        [
            _best_offset(ru[band == b], zu[band == b], offsets) if np.any(band == b) else 0.0
            for b in range(bands)
        ]
    )
    e = np.degrees(np.arctan2(zu - h_band[band], ru))
    centres = _kmeans_1d(e, _histogram_peak_centres(e, k))
    label = np.searchsorted((centres[1:] + centres[:-1]) / 2, e)

    def fit(lab):
        # Each cone's offset is pulled towards the offset of the band most of its points lie
        # in: a laser seen at one range only (a ring on the road) cannot fix it by itself.
        votes = np.bincount(lab * bands + band, minlength=k * bands).reshape(k, bands)
        prior = h_band[np.argmax(votes, axis=1)]
        return fit_cones(ru, zu, lab, k, ridge=ridge, offset_prior=prior, offset_bound=bound)

    # k-lines in the (r, z) plane with a repair step: cones that duplicate a neighbour, hold
    # almost no points or sit far off the common height are freed and re-seeded by splitting
    # the cone that fits its points worst.
    for _ in range(rounds):
        for _ in range(50):
            slope, offset, count = fit(label)
            new = _assign_nearest_cone(ru, zu, slope, offset)
            if np.array_equal(new, label):
                break
            label = new
        slope, offset, count = fit(label)
        finite = np.isfinite(offset)
        if not finite.any():
            return None
        h_med = np.median(offset[finite])
        bad = ~finite | (count < 0.05 * np.median(count)) | (np.abs(offset - h_med) > 1.0)
        order = np.argsort(-np.where(finite, slope, -np.inf), kind="stable")
        angle = np.degrees(np.arctan(slope[order]))
        dup = np.flatnonzero(
            (np.abs(np.diff(angle)) < 0.05) & (np.abs(np.diff(offset[order])) < 0.05)
        )
        free = list(np.flatnonzero(bad))
        for d in dup:  # a handful of pairs at most
            a, b = order[d], order[d + 1]
            if not (bad[a] or bad[b] or b in free):
                label[label == b] = a
                free.append(b)
        if not free:
            return (slope, offset) if np.all(np.isfinite(slope)) else None
        if bad.any():
            keep_s, keep_h = slope.copy(), offset.copy()
            keep_s[bad], keep_h[bad] = np.nan, np.nan
            moved = bad[label]
            label[moved] = _assign_nearest_cone(ru[moved], zu[moved], keep_s, keep_h)
        slope, offset, count = fit(label)
        resid = np.abs((zu - offset[label]) / ru - slope[label])
        spread = np.bincount(label, np.nan_to_num(resid), k) / np.maximum(count, 1)
        for f in free:
            worst = int(np.argmax(spread))
            spread[worst] = -1.0
            members = np.flatnonzero(label == worst)
            above = (zu[members] - offset[worst]) / ru[members] - slope[worst] > 0
            label[members[above]] = f
    return None


def cone_residual_deg(
    points: np.ndarray, profile: SensorProfile, ring: np.ndarray | None = None
) -> float:
    """How well a sensor profile fits a cloud: median angular distance (deg) of the points
    (beyond 1 m) to their laser's cone, or to the nearest cone when ``ring`` is None.

    About 0 for a scan of the profiled sensor (KITTI's cones are exact); tenths of a degree
    or more for another sensor.
    """
    points = check_lidar_points(points)
    r, z = polar_coordinates(points)
    fit = r >= MIN_FIT_RANGE
    if not fit.any():
        return float("inf")
    slope = np.tan(np.radians(profile.beam_angle_deg))
    offset = profile.z_offset_m
    if ring is None:
        k = _assign_nearest_cone(r[fit], z[fit], slope, offset)
    else:
        k = check_ring_labels(ring, points.shape[0], profile.n_lasers)[fit].astype(np.intp)
    resid = np.abs((z[fit] - offset[k]) / r[fit] - slope[k])
    return float(np.degrees(np.median(resid)))


def elevation_rings(
    points: np.ndarray,
    *,
    n_lasers: int = 64,
    profile: SensorProfile | None = None,
    refine: int = 3,
    profile_tolerance_deg: float | None = None,
) -> np.ndarray:
    """Rings from geometry alone (order-free): each point goes to the nearest laser cone.

    Every laser of a spinning LiDAR traces a cone ``z = r tan(a) + h``; a point belongs to
    the cone nearest in angle, ``|(z - h) / r - tan(a)|``.

    Parameters
    ----------
    points : (N, C) float, metres
    n_lasers : int
    profile : SensorProfile, optional
        Known cones (e.g. ``load_sensor_profile("hdl64e-kitti")``): points are assigned to
        them, then every cone with >= 50 points beyond 1 m is re-fitted to this cloud up to
        ``refine`` times (adapts to another unit of the same model); ring = profile index.
        Without a profile the cones are estimated from the cloud: histogram peaks and 1-D
        k-means of the offset-corrected elevation, then k-lines cone fitting (needs returns
        from every laser; offsets are kept within 0.5 m of the common one).

    Returns
    -------
    ring : (N,) int32, 0 = highest laser

    Raises
    ------
    FormatError
        Without a profile: the cloud does not show ``n_lasers`` separable lasers.

    A warning is logged when more than 1 % of the points lie almost as near to a second
    laser as to their own (wrong laser count, wrong profile, or a sensor whose lasers are not
    separable by elevation).
    """
    points = check_lidar_points(points)
    n_lasers = check_n_lasers(n_lasers)
    refine = check_int_range(refine, "refine", low=0)
    check_non_negative(profile_tolerance_deg, "profile_tolerance_deg", allow_none=True)
    r, z = polar_coordinates(points)
    fit = r >= MIN_FIT_RANGE
    if profile is not None and profile_tolerance_deg is not None:
        misfit = cone_residual_deg(points, profile)
        if misfit > profile_tolerance_deg:
            log.info(
                "sensor profile %s does not fit this cloud (median %.3f deg off its cones): "
                "estimating the lasers from the cloud",
                profile.name,
                misfit,
            )
            profile = None
    if profile is not None:
        if profile.n_lasers != n_lasers:
            raise ParameterError(
                f"profile {profile.name!r} has {profile.n_lasers} lasers, not {n_lasers}"
            )
        slope0 = np.tan(np.radians(profile.beam_angle_deg))
        offset0 = profile.z_offset_m
        slope, offset = slope0, offset0
        label = _assign_nearest_cone(r, z, slope, offset)
        for _ in range(refine):
            fs, fo, count = fit_cones(
                r[fit], z[fit], label[fit], n_lasers, ridge=RIDGE, offset_prior=offset0
            )
            keep = (count >= 50) & np.isfinite(fs)
            slope, offset = np.where(keep, fs, slope0), np.where(keep, fo, offset0)
            new = _assign_nearest_cone(r, z, slope, offset)
            if np.array_equal(new, label):
                break
            label = new
        ring = label
    else:
        if points.shape[0] < 3 * n_lasers:
            raise FormatError(
                f"{points.shape[0]} points are too few to find {n_lasers} lasers by elevation"
            )
        cones = _generic_cones(r, z, n_lasers)
        if cones is None:
            raise FormatError(
                f"cannot separate {n_lasers} lasers by elevation in this cloud (does it hold "
                f"{n_lasers} rings? set the laser count, or give a sensor profile)"
            )
        slope, offset = cones
        ring = _rank_by_slope(_assign_nearest_cone(r, z, slope, offset), slope, n_lasers)
        order = np.argsort(-slope, kind="stable")
        slope, offset = slope[order], offset[order]
    _, ratio = _assign_nearest_cone(r[fit], z[fit], slope, offset, ambiguity=True)
    unclear = float(np.mean(ratio > 0.3)) if ratio.size else 0.0
    if unclear > 0.01:
        log.warning(
            "rings by elevation are uncertain: %.1f %% of the points lie almost as near to a "
            "neighbouring laser (laser count, profile or sensor unsuited?)",
            100 * unclear,
        )
    return ring.astype(np.int32)


def recover_rings(
    points: np.ndarray,
    *,
    n_lasers: int = 64,
    method: str = "scan-order",
    profile: SensorProfile | None = None,
    column: int = 4,
) -> np.ndarray:
    """Each point's laser (ring 0 = highest).

    Parameters
    ----------
    points : (N, C) float, metres
        In the file's order for ``scan-order``.
    n_lasers : int
        Lasers of the sensor (64 for KITTI's HDL-64E, 32 for nuScenes).
    method : {"scan-order", "elevation", "column"}
        ``scan-order`` must give exactly ``n_lasers`` rings; otherwise a warning is logged
        and ``elevation`` is used (cropped-in-azimuth or shuffled clouds). ``column`` reads
        ``points[:, column]`` (see :func:`column_rings`).
    profile : SensorProfile, optional
        Used by ``elevation`` (see :func:`elevation_rings`).

    Returns
    -------
    ring : (N,) int32

    Raises
    ------
    ParameterError
        No points, NaN/Inf coordinates, unknown method.
    FormatError
        The cloud does not hold ``n_lasers`` recoverable rings.
    """
    ring, _ = recover_rings_with_method(
        points, n_lasers=n_lasers, method=method, profile=profile, column=column
    )
    return ring


def recover_rings_with_method(
    points: np.ndarray,
    *,
    n_lasers: int = 64,
    method: str = "scan-order",
    profile: SensorProfile | None = None,
    column: int = 4,
    profile_tolerance_deg: float | None = None,
) -> tuple[np.ndarray, str]:
    """:func:`recover_rings` that also says which method gave the rings (after a fallback).

    ``profile_tolerance_deg``: see :func:`elevation_rings`.
    """
    check_choice(method, "method", RING_METHODS)
    points = check_lidar_points(points)
    n_lasers = check_n_lasers(n_lasers)
    if method == "column":
        return column_rings(points, n_lasers=n_lasers, column=column), "column"
    if method == "scan-order":
        ring = scan_order_rings(points, n_lasers=n_lasers)
        found = int(ring[-1]) + 1
        if found == n_lasers:
            return ring, "scan-order"
        log.warning(
            "scan order gives %d rings, not %d (cloud cropped in azimuth, shuffled or merged?): "
            "recovering rings by elevation instead",
            found,
            n_lasers,
        )
    ring = elevation_rings(
        points, n_lasers=n_lasers, profile=profile, profile_tolerance_deg=profile_tolerance_deg
    )
    return ring, "elevation"
