"""Compiled ray casting against oriented primitives in a BVH (numba).

Imported lazily by :mod:`sparsetools.synth.primitives` so ``import sparsetools.synth`` does not
import numba. Primitives are boxes, ellipsoids and z-cylinders in their own local frame
(``world = centre + R @ local``); rays are transformed into that frame, where each shape is
axis-aligned and centred, so the ray parameter ``t`` is the same in both frames.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: Stand-in for 1/0 along an axis the ray does not move on: finite, so that 0 * it stays 0.
_BIG = 1e300
#: Hits closer than this (in units of the ray direction) are ignored: no self-intersection.
_T_MIN = 1e-9

SHAPE_BOX, SHAPE_ELLIPSOID, SHAPE_CYLINDER = 0, 1, 2
#: Face codes: 0..5 box / cylinder cap faces (2 * axis + (1 if the normal points to +axis)),
#: 6 ellipsoid surface, 7 cylinder side.
FACE_ELLIPSOID, FACE_CYLINDER_SIDE = 6, 7


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _hit_primitive(ox, oy, oz, dx, dy, dz, centre, rotation, half, p, shape, best):
    """Entry parameter and face of one ray with primitive ``p``; (inf, -1) on a miss."""
    # Local frame: local = R^T (world - c).
    px = ox - centre[p, 0]
    py = oy - centre[p, 1]
    pz = oz - centre[p, 2]
    r00 = rotation[p, 0, 0]
    r01 = rotation[p, 0, 1]
    r02 = rotation[p, 0, 2]
    r10 = rotation[p, 1, 0]
    r11 = rotation[p, 1, 1]
    r12 = rotation[p, 1, 2]
    r20 = rotation[p, 2, 0]
    r21 = rotation[p, 2, 1]
    r22 = rotation[p, 2, 2]
    lox = r00 * px + r10 * py + r20 * pz
    loy = r01 * px + r11 * py + r21 * pz
    loz = r02 * px + r12 * py + r22 * pz
    ldx = r00 * dx + r10 * dy + r20 * dz
    ldy = r01 * dx + r11 * dy + r21 * dz
    ldz = r02 * dx + r12 * dy + r22 * dz
    e0 = half[p, 0]
    e1 = half[p, 1]
    e2 = half[p, 2]
    if shape == SHAPE_BOX:
        ix = 1.0 / ldx if ldx != 0.0 else _BIG
        iy = 1.0 / ldy if ldy != 0.0 else _BIG
        iz = 1.0 / ldz if ldz != 0.0 else _BIG
        t1 = (-e0 - lox) * ix
        t2 = (e0 - lox) * ix
        tn = min(t1, t2)
        tf = max(t1, t2)
        axis = 0
        t1 = (-e1 - loy) * iy
        t2 = (e1 - loy) * iy
        a = min(t1, t2)
        if a > tn:
            tn = a
            axis = 1
        tf = min(tf, max(t1, t2))
        t1 = (-e2 - loz) * iz
        t2 = (e2 - loz) * iz
        a = min(t1, t2)
        if a > tn:
            tn = a
            axis = 2
        tf = min(tf, max(t1, t2))
        if tn <= tf and tn > _T_MIN and tn < best:
            d_axis = ldx if axis == 0 else (ldy if axis == 1 else ldz)
            return tn, 2 * axis + (1 if d_axis < 0.0 else 0)
        return np.inf, -1
    if shape == SHAPE_ELLIPSOID:
        ux = lox / e0
        uy = loy / e1
        uz = loz / e2
        vx = ldx / e0
        vy = ldy / e1
        vz = ldz / e2
        qa = vx * vx + vy * vy + vz * vz
        qb = ux * vx + uy * vy + uz * vz
        qc = ux * ux + uy * uy + uz * uz - 1.0
        disc = qb * qb - qa * qc
        if qa == 0.0 or disc < 0.0 or qc < 0.0:
            return np.inf, -1
        t = (-qb - math.sqrt(disc)) / qa
        if t > _T_MIN and t < best:
            return t, FACE_ELLIPSOID
        return np.inf, -1
    # Cylinder along local z: radius e0, half height e2.
    r = e0
    qa = ldx * ldx + ldy * ldy
    qb = lox * ldx + loy * ldy
    qc = lox * lox + loy * loy - r * r
    if qa == 0.0:
        if qc > 0.0:
            return np.inf, -1
        ts0 = -np.inf
        ts1 = np.inf
    else:
        disc = qb * qb - qa * qc
        if disc < 0.0:
            return np.inf, -1
        sq = math.sqrt(disc)
        ts0 = (-qb - sq) / qa
        ts1 = (-qb + sq) / qa
    iz = 1.0 / ldz if ldz != 0.0 else _BIG
    t1 = (-e2 - loz) * iz
    t2 = (e2 - loz) * iz
    tz0 = min(t1, t2)
    tz1 = max(t1, t2)
    tn = max(ts0, tz0)
    tf = min(ts1, tz1)
    if tn <= tf and tn > _T_MIN and tn < best:
        if ts0 >= tz0:
            return tn, FACE_CYLINDER_SIDE
        return tn, 4 + (1 if ldz < 0.0 else 0)
    return np.inf, -1


@numba.njit(cache=True, nogil=True, error_model="numpy")
def cast_bvh(
    origin,
    dirs,
    node_lo,
    node_hi,
    node_left,
    node_right,
    node_start,
    node_count,
    node_axis,
    centre,
    rotation,
    half,
    shape,
    out_t,
    out_index,
    out_face,
):
    """Nearest primitive hit of each ray ``origin + t * dirs[i]``, closer than ``out_t[i]``.

    ``out_t`` holds the current nearest hit (or the range limit) on entry; where a primitive
    is hit closer, ``out_t``, ``out_index`` (primitive index in BVH order) and ``out_face``
    are overwritten. Nodes: leaves have ``node_count > 0`` and hold primitives
    ``node_start .. node_start + node_count``; inner nodes have children ``node_left`` (lower
    coordinates along ``node_axis``) and ``node_right``, visited nearer child first. Node 0 is
    the root (no nodes = nothing to hit).
    """
    n = dirs.shape[0]
    if node_lo.shape[0] == 0:
        return
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    stack = np.empty(128, dtype=np.int64)
    for i in range(n):
        dx = dirs[i, 0]
        dy = dirs[i, 1]
        dz = dirs[i, 2]
        ix = 1.0 / dx if dx != 0.0 else _BIG
        iy = 1.0 / dy if dy != 0.0 else _BIG
        iz = 1.0 / dz if dz != 0.0 else _BIG
        best = out_t[i]
        hit = out_index[i]
        face = out_face[i]
        stack[0] = 0
        top = 1
        while top > 0:
            top -= 1
            k = stack[top]
            t1 = (node_lo[k, 0] - ox) * ix
            t2 = (node_hi[k, 0] - ox) * ix
            tn = min(t1, t2)
            tf = max(t1, t2)
            t1 = (node_lo[k, 1] - oy) * iy
            t2 = (node_hi[k, 1] - oy) * iy
            tn = max(tn, min(t1, t2))
            tf = min(tf, max(t1, t2))
            t1 = (node_lo[k, 2] - oz) * iz
            t2 = (node_hi[k, 2] - oz) * iz
            tn = max(tn, min(t1, t2))
            tf = min(tf, max(t1, t2))
            if tn > tf or tf <= 0.0 or tn >= best:
                continue
            if node_count[k] > 0:
                for p in range(node_start[k], node_start[k] + node_count[k]):
                    t, f = _hit_primitive(
                        ox, oy, oz, dx, dy, dz, centre, rotation, half, p, shape[p], best
                    )
                    if f >= 0:
                        best = t
                        hit = p
                        face = f
            else:
                a = node_axis[k]
                d_axis = dx if a == 0 else (dy if a == 1 else dz)
                # Pushed last = popped first: the child on the side the ray comes from.
                if d_axis > 0.0:
                    stack[top] = node_right[k]
                    stack[top + 1] = node_left[k]
                else:
                    stack[top] = node_left[k]
                    stack[top + 1] = node_right[k]
                top += 2
        out_t[i] = best
        out_index[i] = hit
        out_face[i] = face


@numba.njit(cache=True, nogil=True, error_model="numpy")
def cast_plane(origin, dirs, normal, offset, out_t, out_index, out_face, plane_index):
    """Hits of rays with the plane ``normal . p = offset`` seen from above (``normal . d < 0``).

    Overwrites ``out_t``/``out_index``/``out_face`` where the plane is closer; the index is
    ``plane_index`` and the face 5 (the up face).
    """
    height = normal[0] * origin[0] + normal[1] * origin[1] + normal[2] * origin[2] - offset
    for i in range(dirs.shape[0]):
        dn = normal[0] * dirs[i, 0] + normal[1] * dirs[i, 1] + normal[2] * dirs[i, 2]
        if dn < 0.0 and height > 0.0:
            t = -height / dn
            if t > _T_MIN and t < out_t[i]:
                out_t[i] = t
                out_index[i] = plane_index
                out_face[i] = 5


@numba.njit(cache=True, nogil=True, error_model="numpy")
def hit_geometry(
    origin, dirs, t, index, face, centre, rotation, half, ground_normal, points, normals, local
):
    """Hit point (world), unit normal (world) and local hit point of each ray.

    ``index`` >= 0: a primitive (``centre``/``rotation``/``half`` in the caller's order);
    -2: the ground (normal ``ground_normal``); -1: a miss (point NaN, normal and local 0).
    """
    for i in range(dirs.shape[0]):
        k = index[i]
        if k == -1:
            for a in range(3):
                points[i, a] = np.nan
                normals[i, a] = 0.0
                local[i, a] = 0.0
            continue
        for a in range(3):
            points[i, a] = origin[a] + dirs[i, a] * t[i]
        if k < 0:
            for a in range(3):
                normals[i, a] = ground_normal[a]
                local[i, a] = 0.0
            continue
        qx = points[i, 0] - centre[k, 0]
        qy = points[i, 1] - centre[k, 1]
        qz = points[i, 2] - centre[k, 2]
        lx = rotation[k, 0, 0] * qx + rotation[k, 1, 0] * qy + rotation[k, 2, 0] * qz
        ly = rotation[k, 0, 1] * qx + rotation[k, 1, 1] * qy + rotation[k, 2, 1] * qz
        lz = rotation[k, 0, 2] * qx + rotation[k, 1, 2] * qy + rotation[k, 2, 2] * qz
        local[i, 0] = lx
        local[i, 1] = ly
        local[i, 2] = lz
        f = face[i]
        nx = 0.0
        ny = 0.0
        nz = 0.0
        if f < 6:
            s = 1.0 if f % 2 == 1 else -1.0
            if f // 2 == 0:
                nx = s
            elif f // 2 == 1:
                ny = s
            else:
                nz = s
        elif f == FACE_ELLIPSOID:
            nx = lx / (half[k, 0] * half[k, 0])
            ny = ly / (half[k, 1] * half[k, 1])
            nz = lz / (half[k, 2] * half[k, 2])
        else:
            nx = lx
            ny = ly
        length = math.sqrt(nx * nx + ny * ny + nz * nz)
        if length > 0.0:
            nx /= length
            ny /= length
            nz /= length
        for a in range(3):
            normals[i, a] = rotation[k, a, 0] * nx + rotation[k, a, 1] * ny + rotation[k, a, 2] * nz


@numba.njit(cache=True, nogil=True, error_model="numpy")
def value_noise(tile, u, v, cells, amps, footprint, out):
    """``out[i] = sum_j amps[j] w_j(i) noise(tile, u[i], v[i], cells[j])``.

    The noise is the periodic lattice ``tile`` at ``cells[j]`` metres spacing, interpolated
    with smoothstep weights (C1); ``w_j = clip((cells[j] / footprint[i] - 1) / 2, 0, 1)``
    fades octaves finer than the ray's footprint (``footprint[i] <= 0``: no fading).
    """
    size = tile.shape[0]
    for i in range(u.shape[0]):
        acc = 0.0
        fp = footprint[i]
        for j in range(cells.shape[0]):
            cell = cells[j]
            w = 1.0
            if fp > 0.0:
                w = (cell / fp - 1.0) * 0.5
                if w <= 0.0:
                    continue
                if w > 1.0:
                    w = 1.0
            x = u[i] / cell
            y = v[i] / cell
            fx = math.floor(x)
            fy = math.floor(y)
            a = x - fx
            b = y - fy
            a = a * a * (3.0 - 2.0 * a)
            b = b * b * (3.0 - 2.0 * b)
            i0 = int(fx) % size
            j0 = int(fy) % size
            i1 = (i0 + 1) % size
            j1 = (j0 + 1) % size
            top = tile[j0, i0] * (1.0 - a) + tile[j0, i1] * a
            bottom = tile[j1, i0] * (1.0 - a) + tile[j1, i1] * a
            acc += amps[j] * w * (top * (1.0 - b) + bottom * b)
        out[i] = acc
