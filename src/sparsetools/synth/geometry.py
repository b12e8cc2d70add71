"""Ray casting against a ground plane and axis-aligned boxes, vectorised over all rays.

The scene is the plane ``z = ground_z`` plus a list of axis-aligned boxes. Boxes are
grouped (consecutive boxes in the order given, ``group_size`` at a time) under a bounding
box each, a two-level hierarchy that lets the compiled kernel skip most boxes for most rays.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from ..errors import ParameterError

__all__ = ["HIT_GROUND", "HIT_NONE", "BoxSet", "RayHits", "cast_rays"]

#: ``RayHits.index`` of a ray that hit nothing.
HIT_NONE = -1
#: ``RayHits.index`` of a ray that hit the ground plane.
HIT_GROUND = -2


@dataclass(frozen=True)
class BoxSet:
    """Axis-aligned boxes with a precomputed grouping for the ray-casting kernel.

    Attributes
    ----------
    lo, hi : (B, 3) float64, metres
        Minimum and maximum corners.
    group_lo, group_hi : (G, 3) float64, metres
        Bounding boxes of the groups.
    group_start : (G + 1,) int64
        Group ``g`` holds boxes ``group_start[g]:group_start[g + 1]``.
    """

    lo: np.ndarray
    hi: np.ndarray
    group_lo: np.ndarray
    group_hi: np.ndarray
    group_start: np.ndarray

    @classmethod
    def from_corners(
        cls, lo: np.ndarray, hi: np.ndarray, *, group_size: int = 6, group_key=None
    ) -> BoxSet:
        """Group boxes that are consecutive in the given order (and share ``group_key``).

        Parameters
        ----------
        lo, hi : (B, 3) array, metres
            Box corners; ``hi >= lo`` component-wise.
        group_size : int
            Most boxes per group.
        group_key : (B,) int array, optional
            A new group starts wherever the key changes (e.g. street side and object kind),
            so groups stay compact.
        """
        lo = np.ascontiguousarray(lo, dtype=np.float64).reshape(-1, 3)
        hi = np.ascontiguousarray(hi, dtype=np.float64).reshape(-1, 3)
        if lo.shape != hi.shape:
            raise ParameterError(f"box corners differ in shape: {lo.shape} vs {hi.shape}")
        if np.any(hi < lo):
            raise ParameterError("every box needs hi >= lo")
        if group_size < 1:
            raise ParameterError(f"group_size must be >= 1, got {group_size}")
        n = lo.shape[0]
        key = np.zeros(n, dtype=np.int64) if group_key is None else np.asarray(group_key)
        starts = [0]
        for i in range(1, n):
            if key[i] != key[i - 1] or i - starts[-1] >= group_size:
                starts.append(i)
        group_start = np.array([*starts, n] if n else [0], dtype=np.int64)
        g_lo = np.array([lo[a:b].min(axis=0) for a, b in pairwise(group_start)]).reshape(-1, 3)
        g_hi = np.array([hi[a:b].max(axis=0) for a, b in pairwise(group_start)]).reshape(-1, 3)
        return cls(lo, hi, g_lo, g_hi, group_start)

    def __len__(self) -> int:
        return int(self.lo.shape[0])


@dataclass(frozen=True)
class RayHits:
    """Nearest hits of a bundle of rays ``origin + t * directions``.

    Attributes
    ----------
    t : (N,) float64
        Ray parameter of the hit (metres along unit directions; camera z for directions
        with unit z); ``inf`` on a miss.
    index : (N,) int32
        Box index, :data:`HIT_GROUND` or :data:`HIT_NONE`.
    face : (N,) int8
        ``2 * axis + 1`` when the surface normal points to ``+axis``, ``2 * axis`` when it
        points to ``-axis``; -1 on a miss. The ground is face 5 (normal +z).
    points : (N, 3) float64, metres
        Hit points (NaN on a miss).
    """

    t: np.ndarray
    index: np.ndarray
    face: np.ndarray
    points: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool: the ray hit something."""
        return self.index != HIT_NONE

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) float32 unit surface normals (zero on a miss)."""
        n = np.zeros((self.face.shape[0], 3), dtype=np.float32)
        ok = self.face >= 0
        axis = self.face[ok] // 2
        sign = np.where(self.face[ok] % 2 == 1, 1.0, -1.0).astype(np.float32)
        n[np.nonzero(ok)[0], axis] = sign
        return n

    @property
    def uv(self) -> np.ndarray:
        """(N, 2) float64 texture coordinates in metres: the two hit coordinates along the face.

        Faces normal to x use (y, z), normal to y (x, z), normal to z (x, y).
        """
        uv = np.full((self.face.shape[0], 2), np.nan)
        axis = np.where(self.face >= 0, self.face // 2, -1)
        p = self.points
        for a, (i, j) in enumerate(((1, 2), (0, 2), (0, 1))):
            m = axis == a
            uv[m, 0] = p[m, i]
            uv[m, 1] = p[m, j]
        return uv


def cast_rays(
    origin: np.ndarray,
    directions: np.ndarray,
    boxes: BoxSet,
    *,
    t_max: float = np.inf,
    ground_z: float | None = 0.0,
) -> RayHits:
    """Cast rays from one origin against the ground plane and ``boxes``; keep the nearest hit.

    Parameters
    ----------
    origin : (3,) array, metres
        Common origin of all rays (a pinhole camera, a spinning LiDAR, a radar).
    directions : (N, 3) array
        Ray directions; need not be unit length (``t`` is in units of their length).
    boxes : BoxSet
    t_max : float
        Hits beyond this ray parameter are ignored (sensor range).
    ground_z : float or None
        Height of the ground plane ``z = ground_z``; None for no ground.

    Returns
    -------
    RayHits
    """
    from ._kernels import cast_boxes

    origin = np.ascontiguousarray(origin, dtype=np.float64).reshape(3)
    d = np.ascontiguousarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ParameterError(f"directions must be (N, 3), got {d.shape}")
    if not np.all(np.isfinite(origin)):
        raise ParameterError("ray origin must be finite")
    n = d.shape[0]
    t = np.empty(n, dtype=np.float64)
    index = np.empty(n, dtype=np.int32)
    face = np.empty(n, dtype=np.int8)
    cast_boxes(
        origin,
        d,
        float(t_max),
        ground_z is not None,
        0.0 if ground_z is None else float(ground_z),
        boxes.lo,
        boxes.hi,
        boxes.group_lo,
        boxes.group_hi,
        boxes.group_start,
        t,
        index,
        face,
    )
    points = origin + d * np.where(np.isfinite(t), t, np.nan)[:, None]
    return RayHits(t=t, index=index, face=face, points=points)
