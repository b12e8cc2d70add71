"""Geometry of a spinning LiDAR: per-laser cones and the sensor profile that holds them.

Every laser of a spinning LiDAR traces a cone ``z = r tan(a) + h`` (``r`` horizontal range,
``a`` beam angle, ``h`` the emitter's height offset). A :class:`SensorProfile` holds the
cones and apparent elevations of every laser (ring 0 = highest); :func:`fit_sensor_profile`
measures one from clouds with known rings. Reading profiles from files is
:func:`sparsetools.io.sensor_profile.load_sensor_profile`. Shared input checks of the ring and
beam kernels live here too.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..errors import FormatError, ParameterError
from ..validate import (
    check_dtype,
    check_int_range,
    check_non_negative,
    check_nonempty,
    check_points,
    check_same_shape,
    check_shape,
    check_values,
)

__all__ = [
    "MIN_FIT_RANGE",
    "OFFSET_BOUND",
    "RIDGE",
    "SensorProfile",
    "check_lidar_points",
    "check_n_lasers",
    "check_ring_labels",
    "elevation_deg",
    "fit_cones",
    "fit_sensor_profile",
    "grouped_median",
    "polar_coordinates",
]

log = logging.getLogger(__name__)

#: Points nearer than this (m) are left out of cone fits (1 / r blows up at the origin).
MIN_FIT_RANGE = 1.0
#: Prior weight on cone offsets, as a variance of 1 / r (1/m^2) per point.
RIDGE = 1e-7
#: Cone offsets estimated without a profile stay within this (m) of the common offset.
OFFSET_BOUND = 0.5


# -- input checks --------------------------------------------------------------------------------


def check_lidar_points(
    points: np.ndarray, *, allow_empty: bool = False, name: str = "points"
) -> np.ndarray:
    """``points`` as an array: (N, C>=3), real numbers, x, y, z finite."""
    points = np.asarray(points)
    check_points(points, name, nonempty=not allow_empty)
    if not _finite_xyz(points):  # the ring and beam fits have no use for such points
        bad = int(np.count_nonzero(~np.isfinite(points[:, :3]).all(axis=1)))
        raise ParameterError(
            f"{bad} point(s) have NaN/Inf coordinates; drop them first", param=name
        )
    return points


def _finite_xyz(points: np.ndarray) -> bool:
    """Whether x, y, z are finite everywhere (one fast pass in the common case)."""
    if points.dtype.kind != "f":
        return True
    if points.flags.c_contiguous:
        # NaN and Inf anywhere propagate into one pairwise sum over the whole block (every
        # column, a few times faster than isfinite over the strided x, y, z); only a cloud
        # with a non-finite other column or a sum that overflows takes the exact test.
        with np.errstate(over="ignore", invalid="ignore"):
            if np.isfinite(points.sum()):
                return True
    return bool(np.all(np.isfinite(points[:, :3])))


def check_n_lasers(n_lasers: int) -> int:
    return check_int_range(n_lasers, "n_lasers", low=1, high=256)


def check_ring_labels(ring: np.ndarray, n_points: int, n_lasers: int) -> np.ndarray:
    """``ring`` as an array: one integer in 0..n_lasers-1 per point."""
    ring = np.asarray(ring)
    check_shape(ring, f"({n_points})", "ring")
    check_dtype(ring, "ring", "iu")
    check_values(ring, "ring", low=0, high=n_lasers - 1)  # one of the n_lasers lasers
    return ring


def polar_coordinates(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal range ``hypot(x, y)`` and height ``z`` of (N, C>=3) points, float64 metres."""
    check_shape(points, "(N, C)", "points")
    xyz = points[:, :3].astype(np.float64)
    return np.hypot(xyz[:, 0], xyz[:, 1]), xyz[:, 2]


def elevation_deg(points: np.ndarray) -> np.ndarray:
    """Elevation angle of each point seen from the sensor, degrees."""
    r, z = polar_coordinates(points)
    return np.degrees(np.arctan2(z, r))


# -- sensor profile ------------------------------------------------------------------------------


def grouped_median(values: np.ndarray, label: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Median of ``values`` per label 0..k-1 (NaN for empty labels), and the counts.

    ``values`` must be finite (``numpy.median`` of each group, without its NaN check).
    """
    check_same_shape(values, label, "values", "label")
    count = np.bincount(label, minlength=k)
    if label.size > 1 and np.all(label[1:] >= label[:-1]):
        grouped = values  # rings in scan order come grouped already
    else:
        # A stable sort of small integer labels is a radix sort: group the values, then take
        # each group's median (a loop over the k <= 256 lasers, not over points).
        grouped = values[np.argsort(label.astype(np.int16), kind="stable")]
    bounds = np.concatenate([[0], np.cumsum(count)])
    med = np.full(k, np.nan)
    for g in np.flatnonzero(count):
        med[g] = _median(grouped[bounds[g] : bounds[g + 1]])
    return med, count


def _median(segment: np.ndarray) -> float:
    """``numpy.median`` of a finite 1-D array, without its per-call overhead."""
    n = segment.shape[0]
    half = n // 2
    if n % 2:
        return float(np.partition(segment, half)[half])
    part = np.partition(segment, (half - 1, half))
    # numpy.median averages the two middle values as mean() does: (a + b) / 2.
    return float((part[half - 1] + part[half]) / 2.0)


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


def fit_cones(r, z, label, k, *, ridge=0.0, offset_prior=0.0, offset_bound=None):
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
    n_lasers = check_n_lasers(n_lasers)
    check_non_negative(far_range, "far_range")
    check_non_negative(reference_range, "reference_range")
    check_int_range(min_far_points, "min_far_points", low=0)
    check_nonempty(clouds, "clouds")
    if len(clouds) != len(rings):
        raise ParameterError(
            f"give one ring array per cloud: {len(clouds)} clouds, {len(rings)} ring arrays",
            param="rings",
        )
    pts = np.vstack([check_lidar_points(c)[:, :3].astype(np.float64) for c in clouds])
    ring = np.concatenate(
        [check_ring_labels(rg, c.shape[0], n_lasers) for c, rg in zip(clouds, rings, strict=True)]
    ).astype(np.intp)
    r, z = np.hypot(pts[:, 0], pts[:, 1]), pts[:, 2]
    fit = r >= MIN_FIT_RANGE
    slope, offset, _ = fit_cones(r[fit], z[fit], ring[fit], n_lasers)
    if not np.all(np.isfinite(slope)):
        missing = np.flatnonzero(~np.isfinite(slope))
        raise ParameterError(f"rings {missing[:8].tolist()} have too few points to fit a cone")
    far = r > far_range
    el = np.degrees(np.arctan2(z, r))
    far_med, n_far = grouped_median(el[far], ring[far], n_lasers)
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
