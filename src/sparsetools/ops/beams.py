"""LiDAR rings: recover each point's laser and keep 1-32 beams of a 64-beam scan.

METHODS.md section 2. Ring 0 is the highest laser everywhere in this module.

Ring recovery
-------------
- :func:`scan_order_rings`: a raw KITTI HDL-64E ``.bin`` stores its points laser by laser,
  each laser one sweep in azimuth; a new laser starts where the azimuth jumps back by more
  than 90 deg. This is exact and is the primary method.
- :func:`elevation_rings`: the fallback for clouds whose order was lost (shuffled, merged).
  Every laser of a spinning LiDAR traces a cone ``z = r tan(a) + h`` (``r`` horizontal range,
  ``a`` beam angle, ``h`` the emitter's height offset), so points are assigned to the nearest
  cone: the cones of a :class:`SensorProfile` when one is given (exact on KITTI), otherwise
  cones estimated from the cloud itself (1-D k-means of offset-corrected elevation seeded at
  histogram peaks, then a few rounds of cone fitting).
- :func:`column_rings`: clouds that carry the ring in a column (nuScenes LIDAR_TOP).
- :func:`recover_rings`: scan order, validated (exactly ``n_lasers`` rings), with a logged
  fall back to elevation.

Selection (:func:`select_beams`)
--------------------------------
``horizon`` (default for N <= 4), ``uniform`` (default for N > 4), ``pl++`` (Pseudo-LiDAR++
``sparsify.py`` emulation) and explicit rings. Kept rows are bit-identical input rows.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError

__all__ = [
    "HORIZON_TARGETS_DEG",
    "PL_LINE_SPEC_4",
    "RING_METHODS",
    "SELECT_MODES",
    "BeamSelection",
    "RingTable",
    "SensorProfile",
    "column_rings",
    "cone_residual_deg",
    "elevation_rings",
    "fit_sensor_profile",
    "horizon_rings",
    "load_sensor_profile",
    "pl_line_spec",
    "pl_sparsify_index",
    "recover_rings",
    "recover_rings_with_method",
    "ring_elevations",
    "ring_table",
    "scan_order_rings",
    "select_beams",
    "uniform_rings",
]

log = logging.getLogger(__name__)

#: Elevations (deg) of the ``horizon`` selection: the centres of the Pseudo-LiDAR++ 4-beam
#: bands (0.4-deg bins 5, 7, 9, 11 below +2 deg). N = 1, 2, 3 take the first N. Beyond four,
#: targets continue downwards at the same 0.8-deg pitch (see :func:`horizon_rings`).
HORIZON_TARGETS_DEG = (-0.2, -1.0, -1.8, -2.6)
#: ``line_spec`` of Pseudo-LiDAR++'s published 4-beam simulation.
PL_LINE_SPEC_4 = (5, 7, 9, 11)
RING_METHODS = ("scan-order", "elevation", "column")
SELECT_MODES = ("horizon", "uniform", "pl++")

_HORIZON_PITCH_DEG = 0.8
_JUMP_DEG = 90.0
#: Points nearer than this (m) are left out of cone fits (1 / r blows up at the origin).
_MIN_FIT_RANGE = 1.0
#: Prior weight on cone offsets, as a variance of 1 / r (1/m^2) per point.
_RIDGE = 1e-7
#: Cone offsets estimated without a profile stay within this (m) of the common offset.
_OFFSET_BOUND = 0.5
_PROFILE_DIR = Path(__file__).resolve().parent.parent / "data"
_BUILTIN_PROFILES = {"hdl64e-kitti": "hdl64e_kitti.json"}


# -- input checks --------------------------------------------------------------------------------


def _check_points(points: np.ndarray, *, allow_empty: bool = False) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ParameterError(
            f"points must be (N, C>=3) with x, y, z first, got shape {points.shape}"
        )
    if points.dtype.kind not in "fiu":
        raise ParameterError(f"points must be numeric, got dtype {points.dtype}")
    if points.shape[0] == 0 and not allow_empty:
        raise ParameterError("the cloud has no points")
    if not np.all(np.isfinite(points[:, :3])):
        bad = int(np.count_nonzero(~np.isfinite(points[:, :3]).all(axis=1)))
        raise ParameterError(f"{bad} point(s) have NaN/Inf coordinates; drop them first")
    return points


def _check_n_lasers(n_lasers: int) -> int:
    if int(n_lasers) != n_lasers or n_lasers < 1 or n_lasers > 256:
        raise ParameterError(f"n_lasers must be an integer in 1..256, got {n_lasers}")
    return int(n_lasers)


def _check_ring(ring: np.ndarray, n_points: int, n_lasers: int) -> np.ndarray:
    ring = np.asarray(ring)
    if ring.shape != (n_points,):
        raise ParameterError(f"ring must have shape ({n_points},), got {ring.shape}")
    if ring.dtype.kind not in "iu":
        raise ParameterError(f"ring must hold integers, got dtype {ring.dtype}")
    if ring.size and (ring.min() < 0 or ring.max() >= n_lasers):
        raise ParameterError(
            f"ring values must lie in 0..{n_lasers - 1}, got {ring.min()}..{ring.max()} "
            "(wrong n_lasers?)"
        )
    return ring


def _polar(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xyz = points[:, :3].astype(np.float64)
    return np.hypot(xyz[:, 0], xyz[:, 1]), xyz[:, 2]


def _elevation_deg(points: np.ndarray) -> np.ndarray:
    r, z = _polar(points)
    return np.degrees(np.arctan2(z, r))


# -- sensor profile ------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorProfile:
    """Per-laser geometry of a spinning LiDAR, ring 0 = highest laser.

    Attributes
    ----------
    name : str
    elevation_deg : (L,) float64, degrees
        Apparent elevation ``atan2(z, r)`` of each laser as seen at long range: the median over
        points with horizontal range > ``far_range_m`` where there were enough of them, else
        the laser's cone evaluated at ``reference_range_m``. This is what ``horizon``
        selection compares with :data:`HORIZON_TARGETS_DEG`.
    beam_angle_deg : (L,) float64, degrees
        Slope angle ``a`` of the laser's cone ``z = r tan(a) + h``.
    z_offset_m : (L,) float64, metres
        Height ``h`` of the cone's apex above the sensor origin.
    far_range_m, reference_range_m : float, metres
    source : str
        How and from what the profile was measured.
    """

    name: str
    elevation_deg: np.ndarray
    beam_angle_deg: np.ndarray
    z_offset_m: np.ndarray
    far_range_m: float = 20.0
    reference_range_m: float = 30.0
    source: str = ""
    extra: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        arrays = {}
        for key in ("elevation_deg", "beam_angle_deg", "z_offset_m"):
            a = np.asarray(getattr(self, key), dtype=np.float64).reshape(-1)
            if not np.all(np.isfinite(a)):
                raise FormatError(f"sensor profile {self.name!r}: {key} holds non-finite values")
            arrays[key] = a
            object.__setattr__(self, key, a)
        sizes = {a.shape[0] for a in arrays.values()}
        if len(sizes) != 1 or 0 in sizes:
            raise FormatError(f"sensor profile {self.name!r}: per-laser lists differ in length")
        if np.any(np.diff(arrays["beam_angle_deg"]) >= 0):
            raise FormatError(
                f"sensor profile {self.name!r}: beam angles must decrease from ring 0 (highest)"
            )

    @property
    def n_lasers(self) -> int:
        return int(self.elevation_deg.shape[0])

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "n_lasers": self.n_lasers,
            "ring_order": "ring 0 = highest laser",
            "far_range_m": self.far_range_m,
            "reference_range_m": self.reference_range_m,
            "source": self.source,
            "elevation_deg": [round(float(v), 4) for v in self.elevation_deg],
            "beam_angle_deg": [round(float(v), 4) for v in self.beam_angle_deg],
            "z_offset_m": [round(float(v), 4) for v in self.z_offset_m],
            **self.extra,
        }


def load_sensor_profile(name_or_path: str | os.PathLike) -> SensorProfile:
    """A built-in profile by name (``hdl64e-kitti``) or a profile JSON file.

    Raises
    ------
    FormatError
        Unknown name, unreadable file or missing keys.
    """
    key = str(name_or_path)
    path = _PROFILE_DIR / _BUILTIN_PROFILES[key] if key in _BUILTIN_PROFILES else Path(key)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as exc:
        known = ", ".join(sorted(_BUILTIN_PROFILES))
        raise FormatError(
            f"{key}: no such sensor profile (built-in: {known}, or a JSON file)"
        ) from exc
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: cannot read the sensor profile ({exc})") from exc
    try:
        main = {k: data[k] for k in ("name", "elevation_deg", "beam_angle_deg", "z_offset_m")}
    except (KeyError, TypeError) as exc:
        raise FormatError(f"{path}: sensor profile lacks key {exc}") from exc
    extra = {
        k: v
        for k, v in data.items()
        if k not in (*main, "n_lasers", "ring_order", "far_range_m", "reference_range_m", "source")
    }
    try:
        return SensorProfile(
            **main,
            far_range_m=float(data.get("far_range_m", 20.0)),
            reference_range_m=float(data.get("reference_range_m", 30.0)),
            source=str(data.get("source", "")),
            extra=extra,
        )
    except FormatError:
        raise
    except (TypeError, ValueError) as exc:
        raise FormatError(f"{path}: sensor profile values are not numbers ({exc})") from exc


def _fit_cones(r, z, label, k, *, ridge=0.0, offset_prior=0.0, offset_bound=None):
    """Cone ``z = s r + h`` per label, fitted in angle: ``z / r = s + h / r``.

    Least squares on the angular residual (the metric points are assigned by). ``ridge`` > 0
    pulls ``h`` towards ``offset_prior`` with the weight of a spread of ``sqrt(ridge)`` in
    ``1 / r`` per point: a laser seen only at one range (ground ring) cannot separate its
    slope from its offset, and the prior keeps such a fit sane.

    Returns
    -------
    slope, offset : (k,) float64 (NaN where undetermined); count : (k,) int
        With ``offset_bound``, offsets are clipped to ``offset_prior +- offset_bound`` (and
        the slope re-fitted): a flat road is a "cone" too (slope 0, offset minus the sensor
        height) and would otherwise capture the ground returns of many lasers.
    """
    x = 1.0 / r
    y = z / r
    count = np.bincount(label, minlength=k)
    n = count.astype(np.float64)
    safe_n = np.maximum(n, 1.0)
    xbar = np.bincount(label, x, k) / safe_n
    ybar = np.bincount(label, y, k) / safe_n
    sxx = np.bincount(label, x * x, k) - n * xbar * xbar
    sxy = np.bincount(label, x * y, k) - n * xbar * ybar
    lam = ridge * n
    den = sxx + lam
    ok = (count >= 3) & (den > 1e-12 * np.maximum(n, 1.0))
    offset = np.where(ok, (sxy + lam * offset_prior) / np.where(ok, den, 1.0), np.nan)
    if offset_bound is not None:
        offset = np.clip(offset, offset_prior - offset_bound, offset_prior + offset_bound)
    slope = np.where(ok, ybar - offset * xbar, np.nan)
    return slope, offset, count


def fit_sensor_profile(
    clouds: list[np.ndarray],
    rings: list[np.ndarray],
    *,
    n_lasers: int = 64,
    name: str = "custom",
    far_range: float = 20.0,
    reference_range: float = 30.0,
    min_far_points: int = 20,
    source: str = "",
) -> SensorProfile:
    """Measure a :class:`SensorProfile` from clouds with known rings (e.g. scan order).

    Parameters
    ----------
    clouds : list of (N_i, C) float arrays, metres
    rings : list of (N_i,) int arrays
        Ring of every point, 0 = highest.
    far_range : float, metres
        Points beyond this horizontal range give the laser's apparent elevation (median).
    reference_range : float, metres
        Where lasers with fewer than ``min_far_points`` far points get their elevation from
        their fitted cone instead.

    Every laser needs at least 3 points over a spread of ranges (for the cone fit).
    """
    n_lasers = _check_n_lasers(n_lasers)
    if len(clouds) != len(rings) or not clouds:
        raise ParameterError("give one ring array per cloud (at least one cloud)")
    pts = np.vstack([_check_points(c)[:, :3].astype(np.float64) for c in clouds])
    ring = np.concatenate(
        [_check_ring(rg, c.shape[0], n_lasers) for c, rg in zip(clouds, rings, strict=True)]
    ).astype(np.intp)
    r, z = np.hypot(pts[:, 0], pts[:, 1]), pts[:, 2]
    fit = r >= _MIN_FIT_RANGE
    slope, offset, _ = _fit_cones(r[fit], z[fit], ring[fit], n_lasers)
    if not np.all(np.isfinite(slope)):
        missing = np.flatnonzero(~np.isfinite(slope))
        raise ParameterError(f"rings {missing[:8].tolist()} have too few points to fit a cone")
    far = r > far_range
    el = np.degrees(np.arctan2(z, r))
    far_med, n_far = _grouped_median(el[far], ring[far], n_lasers)
    cone_el = np.degrees(np.arctan2(reference_range * slope + offset, reference_range))
    use_far = n_far >= min_far_points
    elevation = np.where(use_far, far_med, cone_el)
    return SensorProfile(
        name=name,
        elevation_deg=elevation,
        beam_angle_deg=np.degrees(np.arctan(slope)),
        z_offset_m=offset,
        far_range_m=float(far_range),
        reference_range_m=float(reference_range),
        source=source,
        extra={
            "far_points": n_far.astype(int).tolist(),
            "elevation_from": ["far-median" if u else "cone" for u in use_far],
            "points": np.bincount(ring, minlength=n_lasers).astype(int).tolist(),
        },
    )


# -- ring recovery -------------------------------------------------------------------------------


def _grouped_median(values: np.ndarray, label: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Median of ``values`` per label 0..k-1 (NaN for empty labels), and the counts."""
    # A stable sort of small integer labels is a radix sort: group the values, then take each
    # group's median (a loop over the k <= 256 lasers, not over points).
    order = np.argsort(label.astype(np.int16), kind="stable")
    grouped = values[order]
    count = np.bincount(label, minlength=k)
    bounds = np.concatenate([[0], np.cumsum(count)])
    med = np.full(k, np.nan)
    for g in np.flatnonzero(count):
        med[g] = np.median(grouped[bounds[g] : bounds[g + 1]])
    return med, count


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
    points = _check_points(points, allow_empty=True)
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, np.int32)
    # float32 is ample for telling a ~0.2-deg step from a ~360-deg jump, and twice as fast.
    xy = points[:, :2].astype(np.float32)
    az = np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))
    step = np.diff(az)
    step = np.where(step > 180, step - 360, np.where(step < -180, step + 360, step))
    if np.count_nonzero(step < 0) > step.size // 2:  # the median step is negative
        az = -az
    first = None
    for cut in (0.0, 180.0):
        a = (az - cut) % 360.0
        ring = np.zeros(n, np.int32)
        np.cumsum(np.diff(a) < -_JUMP_DEG, out=ring[1:])
        if n_lasers is None or int(ring[-1]) + 1 == n_lasers:
            return ring
        if first is None:
            first = ring
    return first


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
    points = _check_points(points, allow_empty=True)
    n_lasers = _check_n_lasers(n_lasers)
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
        el = _elevation_deg(points)
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


def _generic_cones(
    r, z, k, *, min_range=3.0, bands=8, rounds=10, ridge=_RIDGE, bound=_OFFSET_BOUND
):
    """Estimate k laser cones from the cloud alone: (slope, offset) or None on failure."""
    use = r > min_range
    if np.count_nonzero(use) < 3 * k:
        use = r > _MIN_FIT_RANGE
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
        return _fit_cones(ru, zu, lab, k, ridge=ridge, offset_prior=prior, offset_bound=bound)

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
    points = _check_points(points)
    r, z = _polar(points)
    fit = r >= _MIN_FIT_RANGE
    if not fit.any():
        return float("inf")
    slope = np.tan(np.radians(profile.beam_angle_deg))
    offset = profile.z_offset_m
    if ring is None:
        k = _assign_nearest_cone(r[fit], z[fit], slope, offset)
    else:
        k = _check_ring(ring, points.shape[0], profile.n_lasers)[fit].astype(np.intp)
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
    points = _check_points(points)
    n_lasers = _check_n_lasers(n_lasers)
    r, z = _polar(points)
    fit = r >= _MIN_FIT_RANGE
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
            fs, fo, count = _fit_cones(
                r[fit], z[fit], label[fit], n_lasers, ridge=_RIDGE, offset_prior=offset0
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
    if method not in RING_METHODS:
        raise ParameterError(f"unknown ring method {method!r} (choose {', '.join(RING_METHODS)})")
    points = _check_points(points)
    n_lasers = _check_n_lasers(n_lasers)
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


# -- diagnostics ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class RingTable:
    """Per-ring diagnostics of a cloud (rings with at least one point).

    Attributes
    ----------
    ring : (K,) int
    points : (K,) int
    elevation_deg : (K,) float, median elevation over all the ring's points
    far_elevation_deg : (K,) float, median over points beyond ``far_range`` (NaN: none)
    far_points : (K,) int
    far_range : float, metres
    """

    ring: np.ndarray
    points: np.ndarray
    elevation_deg: np.ndarray
    far_elevation_deg: np.ndarray
    far_points: np.ndarray
    far_range: float = 20.0

    @property
    def n_rings(self) -> int:
        return int(self.ring.shape[0])

    @property
    def monotonic(self) -> bool:
        """Whether median elevation strictly decreases with ring index."""
        return bool(np.all(np.diff(self.elevation_deg) < 0))

    def format(self) -> str:
        """A plain-text table, one line per ring."""
        lines = [f"{'ring':>4} {'points':>7} {'elev_deg':>9} {'far_elev_deg':>12} {'far_pts':>7}"]
        for k, n, e, fe, fn in zip(
            self.ring,
            self.points,
            self.elevation_deg,
            self.far_elevation_deg,
            self.far_points,
            strict=True,
        ):
            far = "-" if np.isnan(fe) else f"{fe:.3f}"
            lines.append(f"{int(k):>4} {int(n):>7} {e:>9.3f} {far:>12} {int(fn):>7}")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {
            "rings": self.n_rings,
            "monotonic": self.monotonic,
            "far_range_m": self.far_range,
            "table": [
                {
                    "ring": int(k),
                    "points": int(n),
                    "elevation_deg": round(float(e), 4),
                    "far_elevation_deg": None if np.isnan(fe) else round(float(fe), 4),
                    "far_points": int(fn),
                }
                for k, n, e, fe, fn in zip(
                    self.ring,
                    self.points,
                    self.elevation_deg,
                    self.far_elevation_deg,
                    self.far_points,
                    strict=True,
                )
            ],
        }


def ring_table(points: np.ndarray, ring: np.ndarray, *, far_range: float = 20.0) -> RingTable:
    """Rings found, points per ring, median elevation per ring (all points and far points).

    Parameters
    ----------
    points : (N, C) float, metres
    ring : (N,) int
    far_range : float, metres
        Horizontal range beyond which a point counts as far.
    """
    points = _check_points(points, allow_empty=True)
    ring = np.asarray(ring)
    if ring.shape != (points.shape[0],) or (ring.size and ring.dtype.kind not in "iu"):
        raise ParameterError(f"ring must be ({points.shape[0]},) integers, got {ring.shape}")
    if ring.size and ring.min() < 0:
        raise ParameterError("ring values must be >= 0")
    k = int(ring.max()) + 1 if ring.size else 0
    ring = ring.astype(np.intp)
    r, z = _polar(points)
    el = np.degrees(np.arctan2(z, r))
    med, count = _grouped_median(el, ring, k)
    far = r > far_range
    far_med, far_count = _grouped_median(el[far], ring[far], k)
    present = np.flatnonzero(count > 0)
    return RingTable(
        ring=present,
        points=count[present],
        elevation_deg=med[present],
        far_elevation_deg=far_med[present],
        far_points=far_count[present],
        far_range=float(far_range),
    )


def ring_elevations(
    points: np.ndarray,
    ring: np.ndarray,
    *,
    n_lasers: int = 64,
    far_range: float = 20.0,
    min_far_points: int = 10,
) -> np.ndarray:
    """Apparent elevation of each laser (deg): median over far points, else over all points.

    Far points (horizontal range > ``far_range``) are used because at short range the
    emitters' height offset lifts the apparent elevation by a degree or more. Lasers with
    fewer than ``min_far_points`` far points (those aimed at the nearby ground) fall back to
    the median over all their points; lasers without points get NaN.

    Returns
    -------
    (n_lasers,) float64, degrees
    """
    points = _check_points(points, allow_empty=True)
    n_lasers = _check_n_lasers(n_lasers)
    ring = _check_ring(ring, points.shape[0], n_lasers).astype(np.intp)
    r, z = _polar(points)
    el = np.degrees(np.arctan2(z, r))
    far = r > far_range
    far_med, far_count = _grouped_median(el[far], ring[far], n_lasers)
    few = far_count < min_far_points
    if few.any():
        near = few[ring]
        all_med, _ = _grouped_median(el[near], ring[near], n_lasers)
        far_med = np.where(few, all_med, far_med)
    return far_med


# -- selection -----------------------------------------------------------------------------------


def horizon_rings(elevation_deg: np.ndarray, n: int) -> tuple[int, ...]:
    """The ``n`` rings whose elevation is nearest to the horizon targets.

    Targets: :data:`HORIZON_TARGETS_DEG` (-0.2, -1.0, -1.8, -2.6 deg) for n <= 4; for n > 4
    they continue downwards at the same 0.8-deg pitch (-3.4, -4.2, ...). Targets are served in
    order and each takes the nearest ring not taken yet (so two targets never share a laser on
    sensors with coarse spacing). Rings with NaN elevation are never chosen.

    Returns
    -------
    tuple of int, sorted (ring 0 = highest)
    """
    el = np.asarray(elevation_deg, dtype=np.float64)
    n = _check_n(n, int(np.count_nonzero(np.isfinite(el))))
    targets = HORIZON_TARGETS_DEG[0] - _HORIZON_PITCH_DEG * np.arange(n)
    free = np.isfinite(el)
    chosen = []
    for t in targets:  # n <= 64 targets
        dist = np.where(free, np.abs(el - t), np.inf)
        k = int(np.argmin(dist))
        chosen.append(k)
        free[k] = False
    return tuple(sorted(chosen))


def uniform_rings(n_lasers: int, n: int) -> tuple[int, ...]:
    """Every (n_lasers / n)-th ring from ring 0; ``n`` must divide ``n_lasers``."""
    n_lasers = _check_n_lasers(n_lasers)
    n = _check_n(n, n_lasers)
    if n_lasers % n:
        ok = ", ".join(str(d) for d in range(1, n_lasers + 1) if n_lasers % d == 0)
        raise ParameterError(
            f"uniform selection keeps every (L/N)-th ring, so N must divide L = {n_lasers}; "
            f"got N = {n} (choose {ok}, or --select horizon / --rings)"
        )
    return tuple(range(0, n_lasers, n_lasers // n))


def pl_line_spec(n: int, *, height: int = 64) -> tuple[int, ...]:
    """Default Pseudo-LiDAR++ bins for ``n`` beams.

    n <= 4: the first n of the published 4-beam ``line_spec`` 5 7 9 11; otherwise every
    (height / n)-th bin from 0 (the script's ``--slice``), which needs n to divide ``height``.
    """
    if int(n) != n or n < 1:
        raise ParameterError(f"N must be a positive integer, got {n}")
    if n <= 4:
        return PL_LINE_SPEC_4[: int(n)]
    if height % n:
        raise ParameterError(
            f"pl++ with N = {n} keeps every (H/N)-th 0.4-deg bin, so N must divide H = {height} "
            "(or give --line-spec)"
        )
    return tuple(range(0, height, height // int(n)))


def _check_n(n, available: int) -> int:
    if n is None or int(n) != n or n < 1:
        raise ParameterError(f"N (beams to keep) must be a positive integer, got {n}")
    if n > available:
        raise ParameterError(f"the cloud has only {available} rings, cannot keep {n} beams")
    return int(n)


def pl_sparsify_index(
    points: np.ndarray,
    *,
    projection: np.ndarray,
    image_size: tuple[int, int],
    line_spec: tuple[int, ...] = PL_LINE_SPEC_4,
    width: int = 1024,
    height: int = 64,
) -> np.ndarray:
    """Rows Pseudo-LiDAR++ ``sparsify.py`` keeps, in its output order.

    1. Pre-filters: projected pixel ``0 <= u < W_img``, ``0 <= v < H_img`` (continuous
       coordinates ``P2 R0 Tr X``), x > 2 m; then ``0 <= x < 120``, ``-50 <= y < 50``,
       ``-2.5 <= z < 1.5``.
    2. Bins, in float32 as the script computed them under NumPy 1.x:
       ``theta = 2 deg - asin(z / d)``, bin ``int(theta / (0.4 deg * 64 / height))``;
       ``phi = 45 deg - asin(y / r)``, bin ``int(phi / (90 deg / width))``; both clipped to
       the grid (``d``, ``r`` = 3-D and horizontal range, zeros replaced by 1e-6).
    3. One point per (theta, phi) cell, the LAST in input order (numpy's fancy assignment).
    4. Output: the cells of the ``line_spec`` rows, row by row in ``line_spec`` order, phi
       ascending inside a row.

    Parameters
    ----------
    points : (N, C) float, metres (Velodyne frame)
    projection : (3, 4) float
        ``calib.projection`` (``P2 @ R0_rect @ Tr_velo_to_cam`` for KITTI).
    image_size : (width, height) in pixels
    line_spec : tuple of int
        Rows (theta bins) to keep, each in 0..height-1, no repeats.
    width, height : int
        Azimuth and elevation bins (the published 4-beam command used 1024 and 64).

    Returns
    -------
    index : (M,) int64 into ``points``
    """
    points = _check_points(points, allow_empty=True)
    if int(width) != width or width < 1 or int(height) != height or height < 1:
        raise ParameterError(f"pl++ grid must be positive integers, got {width} x {height}")
    spec = tuple(int(s) for s in line_spec)
    if not spec:
        raise ParameterError("line_spec is empty")
    if len(set(spec)) != len(spec):
        raise ParameterError(f"line_spec repeats a bin: {spec}")
    if min(spec) < 0 or max(spec) >= height:
        raise ParameterError(f"line_spec bins must lie in 0..{height - 1}, got {spec}")
    img_w, img_h = image_size
    M = np.asarray(projection, dtype=np.float64)
    if M.shape != (3, 4):
        raise ParameterError(f"projection must be 3x4, got shape {M.shape}")
    xyz64 = points[:, :3].astype(np.float64)
    uvw = xyz64 @ M[:, :3].T + M[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = uvw[:, 0] / uvw[:, 2]
        v = uvw[:, 1] / uvw[:, 2]
    x, y, z = (points[:, i].astype(np.float32) for i in range(3))
    keep = (u < img_w) & (u >= 0) & (v < img_h) & (v >= 0) & (x > 2.0)
    keep &= (x < 120) & (x >= 0) & (y < 50) & (y >= -50) & (z < 1.5) & (z >= -2.5)
    idx = np.flatnonzero(keep)
    x, y, z = x[idx], y[idx], z[idx]
    d = np.sqrt(x * x + y * y + z * z)
    r = np.sqrt(x * x + y * y)
    tiny = np.float32(1e-6)
    d[d == 0] = tiny
    r[r == 0] = tiny
    f32 = np.float32
    dtheta = f32(np.radians(0.4 * 64.0 / height))
    dphi = f32(np.radians(90.0 / width))
    phi = f32(np.radians(45.0)) - np.arcsin(y / r)
    theta = f32(np.radians(2.0)) - np.arcsin(z / d)
    phi_bin = np.clip((phi / dphi).astype(np.int64), 0, width - 1)
    theta_bin = np.clip((theta / dtheta).astype(np.int64), 0, height - 1)
    # Last write wins: for every cell keep the point that comes last in input order.
    cell = theta_bin * width + phi_bin
    order = np.argsort(cell, kind="stable")
    cs = cell[order]
    last = np.ones(cs.shape[0], bool)
    last[:-1] = cs[1:] != cs[:-1]
    win_cell, win_idx = cs[last], idx[order[last]]
    row_rank = np.full(height, -1, np.int64)
    row_rank[list(spec)] = np.arange(len(spec))
    rank = row_rank[win_cell // width]
    sel = rank >= 0
    out_order = np.lexsort((win_cell[sel] % width, rank[sel]))
    return win_idx[sel][out_order].astype(np.int64)


@dataclass(frozen=True)
class BeamSelection:
    """What :func:`select_beams` kept.

    Attributes
    ----------
    points : (M, C) array
        Kept rows of the input, bit-identical, all columns (input order; pl++: its output
        order).
    index : (M,) int64
        Their row numbers in the input: ``points == input[index]``.
    rings : tuple of int
        Rings kept (empty for pl++, which keeps elevation bins, not lasers).
    select : str
        ``horizon``, ``uniform``, ``pl++`` or ``rings``.
    n_input : int
        Rows of the input.
    line_spec : tuple of int
        pl++ bins (empty otherwise).
    """

    points: np.ndarray
    index: np.ndarray
    rings: tuple[int, ...]
    select: str
    n_input: int
    line_spec: tuple[int, ...] = ()

    @property
    def mask(self) -> np.ndarray:
        """(n_input,) bool, True for kept rows."""
        m = np.zeros(self.n_input, bool)
        m[self.index] = True
        return m


def select_beams(
    points: np.ndarray,
    ring: np.ndarray | None = None,
    *,
    n: int | None = None,
    select: str | None = None,
    rings: tuple[int, ...] | None = None,
    n_lasers: int = 64,
    profile: SensorProfile | None = None,
    ring_elevation_deg: np.ndarray | None = None,
    far_range: float = 20.0,
    calib=None,
    line_spec: tuple[int, ...] | None = None,
    pl_width: int = 1024,
    pl_height: int = 64,
) -> BeamSelection:
    """Keep N beams of a scan.

    Parameters
    ----------
    points : (N, C) float, metres
    ring : (N,) int, optional
        Ring per point (0 = highest), e.g. from :func:`recover_rings`; not needed for pl++.
    n : int
        Beams to keep (optional when ``rings`` or ``line_spec`` says it).
    select : {"horizon", "uniform", "pl++"}, optional
        Default: ``horizon`` for n <= 4, ``uniform`` otherwise; ``rings`` overrides it.

        - ``horizon``: :func:`horizon_rings` on the lasers' elevations, taken from
          ``ring_elevation_deg``, else ``profile.elevation_deg``, else estimated from this
          cloud's far points (:func:`ring_elevations`; per-frame estimates may pick a
          neighbouring laser on another frame, so batches pin the rings once).
        - ``uniform``: :func:`uniform_rings` (N must divide ``n_lasers``).
        - ``pl++``: :func:`pl_sparsify_index`; needs ``calib`` with its image size.
    rings : tuple of int, optional
        Explicit rings to keep.
    n_lasers : int
        Lasers of the sensor (ring values must be below it).
    calib : Calibration, optional
        For pl++'s image-FOV pre-filter.
    line_spec : tuple of int, optional
        pl++ bins (default :func:`pl_line_spec`).
    pl_width, pl_height : int
        pl++ grid (W azimuth bins over 90 deg, H elevation bins of 0.4 * 64 / H deg).

    Returns
    -------
    BeamSelection

    Raises
    ------
    ParameterError
        Unknown mode, N that does not fit the mode or the cloud, rings out of range, NaN.
    """
    points = _check_points(points, allow_empty=True)
    n_lasers = _check_n_lasers(n_lasers)
    if select is not None and select not in SELECT_MODES:
        raise ParameterError(f"unknown selection {select!r} (choose {', '.join(SELECT_MODES)})")
    if rings is not None and select is not None:
        raise ParameterError("give either explicit rings or a selection mode, not both")
    if line_spec is not None and select not in (None, "pl++"):
        raise ParameterError("line_spec belongs to the pl++ selection")
    if line_spec is not None:
        select = "pl++"
        if n is not None and n != len(line_spec):
            raise ParameterError(f"N = {n} but line_spec lists {len(line_spec)} bins")
    if select == "pl++":
        if calib is None:
            raise ParameterError(
                "pl++ needs the calibration and image size (its image-FOV pre-filter)"
            )
        if line_spec is None:
            line_spec = pl_line_spec(_check_n(n, pl_height), height=pl_height)
        index = pl_sparsify_index(
            points,
            projection=calib.projection,
            image_size=calib.size,
            line_spec=tuple(line_spec),
            width=pl_width,
            height=pl_height,
        )
        return BeamSelection(points[index], index, (), "pl++", points.shape[0], tuple(line_spec))
    if ring is None:
        raise ParameterError(f"selection {select or 'by rings'} needs the ring of every point")
    ring = _check_ring(ring, points.shape[0], n_lasers)
    present = np.unique(ring)
    if rings is not None:
        chosen = tuple(sorted(int(k) for k in rings))
        if not chosen:
            raise ParameterError("no rings given")
        if len(set(chosen)) != len(chosen):
            raise ParameterError(f"rings repeat: {tuple(rings)}")
        if chosen[0] < 0 or chosen[-1] >= n_lasers:
            raise ParameterError(f"rings must lie in 0..{n_lasers - 1}, got {tuple(rings)}")
        if n is not None and n != len(chosen):
            raise ParameterError(f"N = {n} but {len(chosen)} rings were given")
        mode = "rings"
    else:
        n = _check_n(n, present.size)
        mode = select or ("horizon" if n <= 4 else "uniform")
        if mode == "uniform":
            chosen = uniform_rings(n_lasers, n)
        else:
            if ring_elevation_deg is not None:
                el = np.asarray(ring_elevation_deg, dtype=np.float64)
            elif profile is not None:
                el = profile.elevation_deg
            else:
                el = ring_elevations(points, ring, n_lasers=n_lasers, far_range=far_range)
            if el.shape != (n_lasers,):
                raise ParameterError(f"need one elevation per laser ({n_lasers}), got {el.shape}")
            chosen = horizon_rings(el, n)
    missing = sorted(set(chosen) - set(present.tolist()))
    if missing:
        log.warning("ring(s) %s have no points in this cloud", missing)
    index = np.flatnonzero(np.isin(ring, chosen)).astype(np.int64)
    return BeamSelection(points[index], index, chosen, mode, points.shape[0])
