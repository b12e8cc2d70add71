"""Keep 1-32 beams of a 64-beam scan (METHODS.md section 2); ring 0 is the highest laser.

Selection (:func:`select_beams`): ``horizon`` (default for N <= 4), ``uniform`` (default for
N > 4), ``pl++`` (Pseudo-LiDAR++ ``sparsify.py`` emulation) and explicit rings. Kept rows are
bit-identical input rows. Recovering the rings is :mod:`sparsetools.ops.rings`; the sensor
geometry is :mod:`sparsetools.ops.lidar_profile`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..validate import (
    check_choice,
    check_int_range,
    check_non_negative,
    check_nonempty,
    check_shape,
    check_values,
)
from .lidar_profile import (
    SensorProfile,
    check_lidar_points,
    check_n_lasers,
    check_ring_labels,
)
from .rings import (
    RING_METHODS,
    RingTable,
    column_rings,
    cone_residual_deg,
    elevation_rings,
    recover_rings,
    recover_rings_with_method,
    ring_elevations,
    ring_table,
    scan_order_rings,
)

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
    "horizon_rings",
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
SELECT_MODES = ("horizon", "uniform", "pl++")

_HORIZON_PITCH_DEG = 0.8


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
    check_shape(el, "(L)", "elevation_deg")
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
    n_lasers = check_n_lasers(n_lasers)
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
    n = check_int_range(n, "n", low=1)
    height = check_int_range(height, "height", low=1)
    if n <= 4:
        return PL_LINE_SPEC_4[:n]
    if height % n:
        raise ParameterError(
            f"pl++ with N = {n} keeps every (H/N)-th 0.4-deg bin, so N must divide H = {height} "
            "(or give --line-spec)"
        )
    return tuple(range(0, height, height // n))


#: Padding (deg) of the float32 bounds on each laser's elevation median: over 1000 times the
#: error of the float32 squares, square root and division behind them on any cloud that
#: passes the range guard of :func:`_elevation_bounds`.
_BOUND_PAD_DEG = 0.01
#: Stands in for the elevation of a laser that cannot be chosen (finite: it has points).
_NEVER_DEG = 1e300


def _horizon_elevations(
    points: np.ndarray, ring: np.ndarray, n: int, *, n_lasers: int, far_range: float
) -> np.ndarray:
    """What :func:`horizon_rings` needs of :func:`ring_elevations` for ``n`` beams.

    Exact elevations for every laser that can be chosen, :data:`_NEVER_DEG` for the other
    lasers with points, NaN for lasers without: :func:`horizon_rings` then chooses exactly as
    with every exact elevation, and only the contenders' points need float64 elevations.

    Each laser's exact elevation lies in a cheap interval ``[lo, hi]``
    (:func:`_elevation_bounds`), so its distance to a target lies in ``[d_min, d_max]``.
    Target ``j`` takes the nearest free laser, and at most ``j`` lasers are taken before it,
    so one of the ``j + 1`` lasers with the smallest ``d_max`` is free: the laser it takes
    has ``d_min`` at most the ``j + 1``-th smallest ``d_max``.
    """
    bounds = _elevation_bounds(points, ring, n_lasers=n_lasers, far_range=far_range)
    if bounds is None:
        return ring_elevations(points, ring, n_lasers=n_lasers, far_range=far_range)
    lo, hi = bounds
    has_points = np.isfinite(lo)
    n = min(int(n), int(np.count_nonzero(has_points)))
    contenders = np.zeros(n_lasers, bool)
    for j, target in enumerate(HORIZON_TARGETS_DEG[0] - _HORIZON_PITCH_DEG * np.arange(n)):
        d_min = np.where(has_points, np.maximum(np.maximum(lo - target, target - hi), 0.0), np.inf)
        d_max = np.where(has_points, np.maximum(np.abs(lo - target), np.abs(hi - target)), np.inf)
        contenders |= d_min <= np.partition(d_max, j)[j]
    rows = np.flatnonzero(contenders[ring])
    exact = ring_elevations(points[rows], ring[rows], n_lasers=n_lasers, far_range=far_range)
    return np.where(contenders, exact, np.where(has_points, _NEVER_DEG, np.nan))


def _elevation_bounds(
    points: np.ndarray, ring: np.ndarray, *, n_lasers: int, far_range: float, min_far: int = 10
) -> tuple[np.ndarray, np.ndarray] | None:
    """Degrees ``lo <= ring_elevations(...) <= hi`` per laser (NaN: no points), from float32.

    A median lies between the minimum and the maximum of its points, and the elevation
    ``atan(z / r)`` grows with ``z / r``: per laser, the float32 ``z / r`` range over the
    points its median may use (the points possibly beyond ``far_range`` when at least
    ``min_far`` are surely beyond it, else all) gives the bounds, padded by
    :data:`_BOUND_PAD_DEG`. None when the rings are not runs of the scan (elevation
    fallback) or float32 cannot be trusted (coordinates beyond 1e19 m or within 1e-15 m of
    the axis).
    """
    if ring.size == 0 or np.any(ring[1:] < ring[:-1]):
        return None
    x = points[:, 0].astype(np.float32, copy=False)
    y = points[:, 1].astype(np.float32, copy=False)
    r2 = x * x
    r2 += y * y
    if not (np.isfinite(r2).all() and r2.min() >= 1e-30):
        return None
    ratio = points[:, 2].astype(np.float32, copy=False) / np.sqrt(r2)
    limit = float(far_range) ** 2
    # Rings are runs: laser k holds rows edges[k]:edges[k + 1].
    edges = np.searchsorted(ring, np.arange(n_lasers + 1))
    present = np.flatnonzero(np.diff(edges))
    starts = edges[present]
    surely_far = r2 > np.float32(limit * (1.0 + 1e-5))
    maybe_far = r2 >= np.float32(limit * (1.0 - 1e-5))
    n_sure = np.zeros(n_lasers, np.intp)
    n_sure[present] = np.add.reduceat(surely_far, starts, dtype=np.intp)
    # the exact far count is >= min_far too: the median runs over far points, all maybe-far
    far = (n_sure >= min_far)[present]
    far_ratio = np.where(maybe_far, ratio, np.float32(np.nan))
    lo = np.full(n_lasers, np.nan)
    hi = np.full(n_lasers, np.nan)
    lo[present] = np.where(
        far, np.fmin.reduceat(far_ratio, starts), np.minimum.reduceat(ratio, starts)
    )
    hi[present] = np.where(
        far, np.fmax.reduceat(far_ratio, starts), np.maximum.reduceat(ratio, starts)
    )
    return np.degrees(np.arctan(lo)) - _BOUND_PAD_DEG, np.degrees(np.arctan(hi)) + _BOUND_PAD_DEG


def _check_n(n, available: int) -> int:
    """``n`` (beams to keep) as an int in 1..available."""
    n = check_int_range(n, "n", low=1)
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
    points = check_lidar_points(points, allow_empty=True)
    width = check_int_range(width, "width", low=1)
    height = check_int_range(height, "height", low=1)
    spec = tuple(int(s) for s in line_spec)
    check_nonempty(spec, "line_spec")
    if len(set(spec)) != len(spec):
        raise ParameterError(f"line_spec repeats a bin: {spec}")
    check_values(spec, "line_spec", low=0, high=height - 1)  # bins of the grid
    img_w, img_h = image_size
    M = np.asarray(projection, dtype=np.float64)
    check_shape(M, "(3, 4)", "projection")
    xyz64 = points[:, :3].astype(np.float64)
    uvw = xyz64 @ M[:, :3].T + M[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = uvw[:, 0] / uvw[:, 2]
        v = uvw[:, 1] / uvw[:, 2]
    x, y, z = (points[:, i].astype(np.float32, copy=False) for i in range(3))
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
    points = check_lidar_points(points, allow_empty=True)
    n_lasers = check_n_lasers(n_lasers)
    if select is not None:
        check_choice(select, "select", SELECT_MODES)
    check_non_negative(far_range, "far_range")
    pl_width = check_int_range(pl_width, "pl_width", low=1)
    pl_height = check_int_range(pl_height, "pl_height", low=1)
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
    ring = check_ring_labels(ring, points.shape[0], n_lasers)
    seen = np.zeros(n_lasers, bool)
    seen[ring] = True
    present = np.flatnonzero(seen)
    if rings is not None:
        chosen = tuple(sorted(int(k) for k in rings))
        check_nonempty(chosen, "rings")
        if len(set(chosen)) != len(chosen):
            raise ParameterError(f"rings repeat: {tuple(rings)}")
        check_values(chosen, "rings", low=0, high=n_lasers - 1)
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
                el = _horizon_elevations(points, ring, n, n_lasers=n_lasers, far_range=far_range)
            source = "profile" if ring_elevation_deg is None else "ring_elevation_deg"
            check_shape(el, f"({n_lasers})", source)  # one elevation per laser
            chosen = horizon_rings(el, n)
    missing = sorted(set(chosen) - set(present.tolist()))
    if missing:
        log.warning("ring(s) %s have no points in this cloud", missing)
    wanted = np.zeros(n_lasers, bool)
    wanted[list(chosen)] = True
    index = np.flatnonzero(wanted[ring]).astype(np.int64)
    return BeamSelection(points[index], index, chosen, mode, points.shape[0])
