"""Accumulated depth: the LiDAR scans of frames t-k..t+k merged into frame t's camera view.

KITTI's depth ground truth (Uhrig et al., 3DV 2017) accumulates 11 scans (+-5 frames) and
removes the points a single view cannot see; :func:`accumulate_scans` does the same from
each frame's pose (``T_world_from_velo``, 4x4, e.g. the synthetic scenes' poses, KITTI oxts,
or :func:`sparsetools.ops.registration.chain_poses` of ICP results):

1. Every scan k is moved into frame t's Velodyne frame,
   ``T_velo_t_from_velo_k = inv(T_world_from_velo[t]) @ T_world_from_velo[k]`` (frame t's
   own scan stays bit-identical), and projected with the calibration exactly as
   :func:`sparsetools.ops.projection.project_points` does (``rint`` pixel, ``pixel_offset``,
   ``min_depth < depth <= max_depth``).
2. Points of the OTHER scans are then dropped, in this order, when
   - ``masked``: they land inside ``moving_mask`` (an (H, W) bool mask of frame t's image,
     e.g. detected vehicles; frame t's own points there are kept: they were measured at t);
   - ``inconsistent`` (moving objects, misregistration): frame t's own scan measured
     something in the window around the point's pixel and the point is nearer than all of
     it, ``depth * (1 + consistency_rel) < F_own`` (F_own: the minimum depth of frame t's
     own points in the window): frame t's laser saw through the place where the point claims
     a surface, so that surface has moved away since;
   - ``occluded``: they lie behind the local foreground of frame t's view,
     ``depth > (1 + occlusion_rel) * F``, with F the minimum depth of the foreground points
     in the window (``occlusion_foreground``: frame t's own points and the other scans'
     points that passed the tests above, or frame t's own scan only).
   With ``occlude_own`` frame t's own points take the occlusion test too (their see-through
   points, :mod:`sparsetools.ops.occlusion`); otherwise they are all kept.
   The window radius follows the point's depth, ``r = clip(rint(fx * footprint_m / depth),
   min_radius_px, max_radius_px)``: a window of about ``2 * footprint_m`` metres. With a
   fixed pixel window a tilted surface occludes itself far away (along a road seen from
   1.65 m, the depth changes by a factor 1 + rel within ``fx * h * rel / z`` rows); with a
   metric window it never does as long as ``footprint_m < h * rel`` (0.165 m for the
   defaults and KITTI's camera height), out to ``fx * h * rel`` (119 m) where the 1-px
   minimum radius takes over. ``min_radius_px = max_radius_px = (w - 1) / 2`` gives a
   fixed w x w window instead.
3. The remaining points and frame t's own points go through one z-buffer (nearest point
   wins, ties as in :func:`sparsetools.ops.projection.project_points_with_index`); each
   pixel records which scan its point came from.

Everything is vectorised (numpy, OpenCV's min filter, the numba z-buffer of
``ops.projection``); no Python loop over points.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..calibration import Calibration
from ..errors import ParameterError
from ..validate import (
    check_all_finite,
    check_choice,
    check_dtype,
    check_flag,
    check_instance,
    check_int_range,
    check_non_negative,
    check_nonempty,
    check_ordered,
    check_points,
    check_positive,
    check_shape,
)
from .occlusion import OcclusionSettings, occluded_points, occlusion_radius, window_minimum
from .projection import project_points, project_points_with_index, rigid_inverse

__all__ = [
    "OCCLUSION_FOREGROUNDS",
    "AccumulateSettings",
    "AccumulationResult",
    "RemovalCounts",
    "accumulate_scans",
]

OCCLUSION_FOREGROUNDS = ("all", "own")

# Per-point outcome codes (reasons are tested in this order; masked and inconsistent apply to
# the other scans only, occluded to frame t's own points too with ``occlude_own``).
(
    _KEPT,
    _NON_FINITE,
    _BEHIND,
    _TOO_FAR,
    _OUTSIDE,
    _MASKED,
    _INCONSISTENT,
    _OCCLUDED,
    _HELD_OUT,
) = range(9)
_N_CODES = 9


@dataclass(frozen=True)
class AccumulateSettings:
    """Options of :func:`accumulate_scans`.

    Attributes
    ----------
    min_depth : float, metres
        Points with camera depth <= ``min_depth`` are "behind the camera" (default 0.1).
    max_depth : float, metres, optional
        Points farther than this are dropped (default: no limit).
    pixel_offset : int
        As in :func:`sparsetools.ops.projection.project_points` (0, or -1 for monodepth2).
    occlusion_rel : float, optional
        Relative depth margin of the occlusion test (default 0.1); None: no occlusion test.
    occlusion_foreground : {"all", "own"}
        Foreground of the occlusion test: frame t's own points and every other scan's points
        that passed the mask and consistency tests (default: dense, so thin occluders are
        found), or frame t's own scan only.
    consistency_rel : float, optional
        Relative margin of the consistency (moving-object) test (default 0.1); None: off.
    footprint_m : float, metres
        Half size of the test window in metres (default 0.1; keep it below camera height x
        ``occlusion_rel`` so that the road does not occlude itself).
    min_radius_px, max_radius_px : int
        Bounds of the window radius in pixels (default 1 and 8).
    occlude_own : bool
        Apply the occlusion test to frame t's own points too (default False): drops its
        see-through points, as KITTI-grade ground truth needs (:mod:`sparsetools.ops.occlusion`).
    """

    min_depth: float = 0.1
    max_depth: float | None = None
    pixel_offset: int = 0
    occlusion_rel: float | None = 0.1
    occlusion_foreground: str = "all"
    consistency_rel: float | None = 0.1
    footprint_m: float = 0.1
    min_radius_px: int = 1
    max_radius_px: int = 8
    # Recorded by batch runs only when set, so folders of earlier versions resume.
    occlude_own: bool = field(default=False, metadata={"omit_default": True})

    def __post_init__(self) -> None:
        check_flag(self.occlude_own, "occlude_own")
        lo = check_non_negative(self.min_depth, "min_depth")
        hi = check_positive(self.max_depth, "max_depth", allow_none=True)
        check_ordered(lo, hi, "min_depth", "max_depth")
        check_non_negative(self.occlusion_rel, "occlusion_rel", allow_none=True)
        check_non_negative(self.consistency_rel, "consistency_rel", allow_none=True)
        check_choice(self.occlusion_foreground, "occlusion_foreground", OCCLUSION_FOREGROUNDS)
        check_positive(self.footprint_m, "footprint_m")
        check_int_range(self.pixel_offset, "pixel_offset")
        lo_r = check_int_range(self.min_radius_px, "min_radius_px", low=0, high=64)
        check_int_range(self.max_radius_px, "max_radius_px", low=lo_r, high=64)


@dataclass(frozen=True)
class RemovalCounts:
    """What happened to the points of one scan (or of all of them).

    Attributes
    ----------
    points : int
        Points given.
    non_finite : int
        NaN / Inf coordinates.
    behind_camera : int
        Depth <= ``min_depth``.
    beyond_max_depth : int
        Depth > ``max_depth``.
    outside_image : int
        Pixel outside the image.
    masked : int
        Inside ``moving_mask`` (other scans only).
    inconsistent : int
        Nearer than everything frame t's own scan measured around it (other scans only).
    occluded : int
        Behind the local foreground of frame t's view (other scans only).
    held_out : int
        Frame t's own points in the image when ``hold_out_reference`` (not drawn, not used).
    kept : int
        Points that entered the z-buffer (several may share a pixel; the nearest wins).
    """

    points: int
    non_finite: int
    behind_camera: int
    beyond_max_depth: int
    outside_image: int
    masked: int
    occluded: int
    inconsistent: int
    held_out: int
    kept: int

    @classmethod
    def _from_codes(cls, histogram: np.ndarray) -> RemovalCounts:
        h = [int(x) for x in histogram]
        return cls(
            points=sum(h),
            non_finite=h[_NON_FINITE],
            behind_camera=h[_BEHIND],
            beyond_max_depth=h[_TOO_FAR],
            outside_image=h[_OUTSIDE],
            masked=h[_MASKED],
            occluded=h[_OCCLUDED],
            inconsistent=h[_INCONSISTENT],
            held_out=h[_HELD_OUT],
            kept=h[_KEPT],
        )


@dataclass(frozen=True)
class AccumulationResult:
    """Frame t's accumulated depth map.

    Attributes
    ----------
    depth : (H, W) float32, metres
        Nearest kept point per pixel, 0 = empty.
    source : (H, W) int16
        Position in ``scans`` of the scan whose point won the pixel, -1 = empty.
    counts : RemovalCounts
        Totals over all scans.
    counts_per_scan : tuple of RemovalCounts
        One per scan, in the order of ``scans``.
    reference : int
        Position of frame t in ``scans``.
    """

    depth: np.ndarray
    source: np.ndarray
    counts: RemovalCounts
    counts_per_scan: tuple[RemovalCounts, ...]
    reference: int

    @property
    def density(self) -> float:
        """Fraction of pixels with a depth, 0..1."""
        return float(np.count_nonzero(self.depth > 0)) / max(self.depth.size, 1)


def _check_inputs(scans, poses, calib, reference, moving_mask):
    check_instance(calib, "calib", Calibration)
    width, height = calib.size
    check_nonempty(scans, "scans")
    poses = np.asarray(poses, dtype=np.float64)
    check_shape(poses, f"({len(scans)}, 4, 4)", "T_world_from_velo")  # one pose per scan
    check_all_finite(poses, "T_world_from_velo")
    if not np.allclose(poses[:, 3], (0, 0, 0, 1)):
        raise ParameterError(
            "poses must be rigid 4x4 transforms (last row 0 0 0 1)", param="T_world_from_velo"
        )
    reference = check_int_range(reference, "reference", low=0, high=len(scans) - 1)
    checked = []
    for k, pts in enumerate(scans):
        p = np.asarray(pts)
        check_points(p, f"scans[{k}]")
        checked.append(p)
    if moving_mask is not None:
        moving_mask = np.asarray(moving_mask)
        check_shape(moving_mask, f"({height}, {width})", "moving_mask")
        check_dtype(moving_mask, "moving_mask", (np.bool_,))
    return checked, poses, int(reference), moving_mask, width, height


def accumulate_scans(
    scans: Sequence[np.ndarray],
    T_world_from_velo: np.ndarray | Sequence[np.ndarray],
    calib: Calibration,
    *,
    reference: int,
    settings: AccumulateSettings | None = None,
    moving_mask: np.ndarray | None = None,
    hold_out_reference: bool = False,
) -> AccumulationResult:
    """Merge several LiDAR scans into frame ``reference``'s depth map (module docstring).

    Parameters
    ----------
    scans : sequence of (N_k, C) float, metres
        Velodyne-frame scans (x, y, z first), e.g. frames t-5..t+5.
    T_world_from_velo : (n, 4, 4) float
        Pose of each scan's Velodyne in a common world frame.
    calib : Calibration
        Velodyne-to-camera calibration of frame t with its image size.
    reference : int
        Position of frame t in ``scans``.
    settings : AccumulateSettings, optional
    moving_mask : (H, W) bool, optional
        Pixels of frame t's image whose points from OTHER scans are dropped (moving objects).
    hold_out_reference : bool
        Leave frame t's own scan out of the map and out of every test (to compare the other
        scans with it afterwards). Needs ``occlusion_foreground="all"`` and
        ``consistency_rel=None``.

    Returns
    -------
    AccumulationResult

    Raises
    ------
    ParameterError
        Bad shapes, poses, settings, mask or reference.
    """
    s = AccumulateSettings() if settings is None else settings
    check_instance(s, "settings", AccumulateSettings)
    scans, poses, reference, moving_mask, width, height = _check_inputs(
        scans, T_world_from_velo, calib, reference, moving_mask
    )
    if hold_out_reference and (s.occlusion_foreground == "own" or s.consistency_rel is not None):
        raise ParameterError(
            "hold_out_reference leaves frame t's own scan out, so the tests cannot use it: "
            "set occlusion_foreground='all' and consistency_rel=None"
        )
    max_depth = np.inf if s.max_depth is None else float(s.max_depth)
    T_ref_from_world = rigid_inverse(poses[reference])

    # 1. Every point in frame t's Velodyne frame, float64, with its scan number.
    moved, owner = [], []
    for k, pts in enumerate(scans):
        xyz = pts[:, :3].astype(np.float64)
        if k != reference:
            xyz = _transform(T_ref_from_world @ poses[k], xyz)
        moved.append(xyz)
        owner.append(np.full(xyz.shape[0], k, np.int32))
    xyz = np.concatenate(moved) if moved else np.zeros((0, 3))
    owner = np.concatenate(owner)
    n = xyz.shape[0]

    # Projection written term by term in the order of ops.projection's kernel, so every point
    # lands in the pixel (and passes the same tests) that project_points gives it.
    M = np.ascontiguousarray(calib.projection, dtype=np.float64)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    code = np.full(n, _KEPT, np.uint8)
    finite = np.isfinite(xyz).all(axis=1)
    code[~finite] = _NON_FINITE
    with np.errstate(invalid="ignore", divide="ignore"):
        w = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + M[2, 3]
        behind = finite & ~((w > s.min_depth) & (np.float32(w) > 0))
        code[behind] = _BEHIND
        too_far = finite & ~behind & ~(w <= max_depth)
        code[too_far] = _TOO_FAR
        fu = np.rint((M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + M[0, 3]) / w) + s.pixel_offset
        fv = np.rint((M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + M[1, 3]) / w) + s.pixel_offset
        inside = (fu >= 0) & (fu < width) & (fv >= 0) & (fv < height)
    code[(code == _KEPT) & ~inside] = _OUTSIDE
    cand = code == _KEPT
    iu = np.where(cand, fu, 0).astype(np.int64)
    iv = np.where(cand, fv, 0).astype(np.int64)
    own = owner == reference
    if hold_out_reference:
        code[own & cand] = _HELD_OUT
        usable_own = np.zeros(n, bool)
    else:
        usable_own = own & cand
    other = cand & ~own

    # 2. Filters on the other scans' points.
    if moving_mask is not None:
        hit = other & moving_mask[iv, iu]
        code[hit] = _MASKED
        other &= ~hit
    window = OcclusionSettings(
        rel=0.0 if s.occlusion_rel is None else s.occlusion_rel, footprint_m=s.footprint_m,
        min_radius_px=s.min_radius_px, max_radius_px=s.max_radius_px,
    )  # fmt: skip
    idx_other = np.flatnonzero(other)
    zo = w[idx_other]
    ro = occlusion_radius(zo, fx=calib.fx, settings=window)
    vo, uo = iv[idx_other], iu[idx_other]
    own_map = None
    if s.consistency_rel is not None or s.occlusion_foreground == "own":
        own_map = _zbuffer(xyz[usable_own], calib, s)
    if s.consistency_rel is not None and idx_other.size:
        near = window_minimum(own_map, ro, vo, uo)
        # An empty window (+inf) means frame t measured nothing there: nothing to contradict.
        bad = np.isfinite(near) & (zo * (1.0 + s.consistency_rel) < near)
        code[idx_other[bad]] = _INCONSISTENT
    test_own = s.occlude_own and bool(usable_own.any())
    if s.occlusion_rel is not None and (idx_other.size or test_own):
        if s.occlusion_foreground == "own":
            fg_map = own_map
        else:
            # Moving points found above must not hide the static background behind them.
            fg_map = _zbuffer(xyz[usable_own | (code == _KEPT) & other], calib, s)
        if idx_other.size:
            fg = window_minimum(fg_map, ro, vo, uo)
            hidden = (code[idx_other] == _KEPT) & (zo > (1.0 + s.occlusion_rel) * fg)
            code[idx_other[hidden]] = _OCCLUDED
        if test_own:
            # Frame t's see-through points: its LiDAR saw background past a foreground edge
            # that the camera cannot see past (ops.occlusion).
            idx_own = np.flatnonzero(usable_own)
            hidden = occluded_points(iu[idx_own], iv[idx_own], w[idx_own], fg_map,
                                     fx=calib.fx, settings=window)  # fmt: skip
            code[idx_own[hidden]] = _OCCLUDED

    # 3. One z-buffer over the kept points.
    kept = np.flatnonzero(code == _KEPT)
    depth, index = project_points_with_index(
        xyz[kept],
        calib,
        min_depth=s.min_depth,
        max_depth=s.max_depth,
        pixel_offset=s.pixel_offset,
    )
    source = np.full(depth.shape, -1, np.int16)
    hit = index >= 0
    source[hit] = owner[kept][index[hit]]
    hist = np.bincount(owner.astype(np.int64) * _N_CODES + code, minlength=len(scans) * _N_CODES)
    per_scan = tuple(
        RemovalCounts._from_codes(hist[k * _N_CODES : (k + 1) * _N_CODES])
        for k in range(len(scans))
    )
    total = RemovalCounts._from_codes(hist.reshape(len(scans), _N_CODES).sum(axis=0))
    return AccumulationResult(
        depth=depth, source=source, counts=total, counts_per_scan=per_scan, reference=reference
    )


def _transform(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """``R xyz + t`` column by column, without BLAS: numpy's (N, 3) @ (3, 3) product goes
    through OpenBLAS, whose threads made it ~20x slower on a busy 2-core machine."""
    out = np.empty_like(xyz)
    for i in range(3):
        out[:, i] = T[i, 0] * xyz[:, 0] + T[i, 1] * xyz[:, 1] + T[i, 2] * xyz[:, 2] + T[i, 3]
    return out


def _zbuffer(xyz: np.ndarray, calib: Calibration, s: AccumulateSettings) -> np.ndarray:
    return project_points(
        xyz, calib, min_depth=s.min_depth, max_depth=s.max_depth, pixel_offset=s.pixel_offset
    )
