"""Compiled ray-casting kernel (numba). Imported lazily by :mod:`sparsetools.synth.geometry`.

Kept in its own module so ``import sparsetools.synth`` does not import numba, and so numba's
on-disk cache (``cache=True``) can key the kernel by this file.
"""

from __future__ import annotations

import numba
import numpy as np

#: Stand-in for 1/0 along an axis the ray does not move on: finite, so that 0 * it stays 0.
_BIG = 1e300


@numba.njit(cache=True, nogil=True, error_model="numpy")
def cast_boxes(
    origin: np.ndarray,
    dirs: np.ndarray,
    t_max: float,
    has_ground: bool,
    ground_z: float,
    lo: np.ndarray,
    hi: np.ndarray,
    group_lo: np.ndarray,
    group_hi: np.ndarray,
    group_start: np.ndarray,
    out_t: np.ndarray,
    out_hit: np.ndarray,
    out_face: np.ndarray,
) -> None:
    """Nearest hit of each ray with a ground plane and axis-aligned boxes (slab method).

    Rays are ``origin + t * dirs[i]``, ``0 < t <= t_max``. Boxes are grouped: a group's
    bounding box is tested first and its members ``group_start[g]:group_start[g+1]`` only
    when the group can still beat the current nearest hit.

    Writes ``out_t[i]`` (ray parameter, ``inf`` on a miss), ``out_hit[i]`` (box index,
    -2 ground, -1 miss) and ``out_face[i]`` (2 * axis + (1 if the normal points to +axis)).
    """
    n = dirs.shape[0]
    n_groups = group_lo.shape[0]
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    for i in range(n):
        dx = dirs[i, 0]
        dy = dirs[i, 1]
        dz = dirs[i, 2]
        ix = 1.0 / dx if dx != 0.0 else _BIG
        iy = 1.0 / dy if dy != 0.0 else _BIG
        iz = 1.0 / dz if dz != 0.0 else _BIG
        best = t_max
        hit = -1
        face = -1
        if has_ground and dz < 0.0:
            tg = (ground_z - oz) * iz
            if 0.0 < tg <= best:
                best = tg
                hit = -2
                face = 5
        for g in range(n_groups):
            t1 = (group_lo[g, 0] - ox) * ix
            t2 = (group_hi[g, 0] - ox) * ix
            tn = min(t1, t2)
            tf = max(t1, t2)
            t1 = (group_lo[g, 1] - oy) * iy
            t2 = (group_hi[g, 1] - oy) * iy
            tn = max(tn, min(t1, t2))
            tf = min(tf, max(t1, t2))
            t1 = (group_lo[g, 2] - oz) * iz
            t2 = (group_hi[g, 2] - oz) * iz
            tn = max(tn, min(t1, t2))
            tf = min(tf, max(t1, t2))
            if tn > tf or tf <= 0.0 or tn >= best:
                continue
            for b in range(group_start[g], group_start[g + 1]):
                t1 = (lo[b, 0] - ox) * ix
                t2 = (hi[b, 0] - ox) * ix
                tn = min(t1, t2)
                tf = max(t1, t2)
                axis = 0
                t1 = (lo[b, 1] - oy) * iy
                t2 = (hi[b, 1] - oy) * iy
                a = min(t1, t2)
                if a > tn:
                    tn = a
                    axis = 1
                tf = min(tf, max(t1, t2))
                t1 = (lo[b, 2] - oz) * iz
                t2 = (hi[b, 2] - oz) * iz
                a = min(t1, t2)
                if a > tn:
                    tn = a
                    axis = 2
                tf = min(tf, max(t1, t2))
                # Rays starting inside a box (tn < 0) see no entry face: skip them.
                if tn <= tf and tn > 1e-9 and tn < best:
                    best = tn
                    hit = b
                    d_axis = dx if axis == 0 else (dy if axis == 1 else dz)
                    face = 2 * axis + (1 if d_axis < 0.0 else 0)
        if hit == -1:
            out_t[i] = np.inf
        else:
            out_t[i] = best
        out_hit[i] = hit
        out_face[i] = face
