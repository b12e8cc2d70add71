"""Per-ring diagnostics of a cloud whose rings are known: the ring table and the lasers'
apparent elevations (METHODS.md section 2). Ring recovery itself is :mod:`.rings`, which
re-exports these.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..validate import check_dtype, check_int_range, check_non_negative, check_shape, check_values
from .lidar_profile import (
    check_lidar_points,
    check_n_lasers,
    check_ring_labels,
    grouped_median,
    polar_coordinates,
)

__all__ = ["RingTable", "ring_elevations", "ring_table"]


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
    points = check_lidar_points(points, allow_empty=True)
    check_non_negative(far_range, "far_range")
    ring = np.asarray(ring)
    check_shape(ring, f"({points.shape[0]})", "ring")
    if ring.size:
        check_dtype(ring, "ring", "iu")
        check_values(ring, "ring", low=0)
    k = int(ring.max()) + 1 if ring.size else 0
    ring = ring.astype(np.intp)
    r, z = polar_coordinates(points)
    el = np.degrees(np.arctan2(z, r))
    med, count = grouped_median(el, ring, k)
    far = r > far_range
    far_med, far_count = grouped_median(el[far], ring[far], k)
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
    points = check_lidar_points(points, allow_empty=True)
    n_lasers = check_n_lasers(n_lasers)
    ring = check_ring_labels(ring, points.shape[0], n_lasers)
    check_non_negative(far_range, "far_range")
    check_int_range(min_far_points, "min_far_points", low=0)
    # Elevations of the points that are needed only (far points, and every point of the
    # lasers with too few of them), each computed exactly as over the whole cloud.
    far, r = _far_points(points, far_range)
    el = np.degrees(np.arctan2(points[far, 2].astype(np.float64), r))
    far_med, far_count = grouped_median(el, ring[far].astype(np.intp), n_lasers)
    few = far_count < min_far_points
    if few.any():
        near = np.flatnonzero(few[ring])
        r, z = polar_coordinates(points[near])
        all_med, _ = grouped_median(
            np.degrees(np.arctan2(z, r)), ring[near].astype(np.intp), n_lasers
        )
        far_med = np.where(few, all_med, far_med)
    return far_med


def _far_points(points: np.ndarray, far_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows with horizontal range ``r = hypot(x, y) > far_range`` (float64), in order, and
    their r.

    A float32 ``x^2 + y^2`` (within a few float32 epsilons of the true square) first drops
    the points that are clearly nearer; the exact float64 test decides the rest.
    """
    far_range = float(far_range)
    if far_range * far_range > 1e-30:  # a bound that float32 squares cannot underflow past
        x = points[:, 0].astype(np.float32)
        y = points[:, 1].astype(np.float32)
        r2 = x * x
        r2 += y * y
        rows = np.flatnonzero(r2 >= np.float32(far_range * far_range * (1.0 - 1e-5)))
    else:
        rows = np.arange(points.shape[0])
    xy = points[rows, :2].astype(np.float64)
    r = np.hypot(xy[:, 0], xy[:, 1])
    far = r > far_range
    return rows[far], r[far]
