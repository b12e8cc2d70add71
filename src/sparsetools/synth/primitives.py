"""Oriented primitives (boxes, ellipsoids, upright cylinders), a BVH over them, ray casting.

A primitive is a shape centred at ``centre`` in its own frame, rotated into the world by
``rotation`` (``world = centre + rotation @ local``), with half extents ``half``: a box
``[-half, half]``, an ellipsoid with semi-axes ``half``, or a cylinder along local z of
radius ``half[0]`` and half height ``half[2]``. Each primitive also carries what the
renderer needs (surface kind, object id, base colour and LiDAR reflectance, moving flag).

:func:`build_bvh` builds a bounding-volume hierarchy (median splits) once per primitive set;
:func:`cast` finds the nearest hit over a ground plane and several BVHs (the static street
and the moving actors of one frame) in one compiled kernel per BVH.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError

__all__ = [
    "BVH",
    "HIT_GROUND",
    "HIT_NONE",
    "SHAPE_BOX",
    "SHAPE_CYLINDER",
    "SHAPE_ELLIPSOID",
    "Hits",
    "Primitives",
    "build_bvh",
    "cast",
    "rotate",
]

SHAPE_BOX, SHAPE_ELLIPSOID, SHAPE_CYLINDER = 0, 1, 2
HIT_NONE, HIT_GROUND = -1, -2
FACE_ELLIPSOID, FACE_CYLINDER_SIDE = 6, 7


def rotate(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 3) ``R @ v[i]`` for a (3, 3) ``R``, written out (exact, no BLAS reordering)."""
    v = np.asarray(v, dtype=np.float64)
    out = np.empty_like(v)
    for r in range(3):
        out[:, r] = R[r, 0] * v[:, 0] + R[r, 1] * v[:, 1] + R[r, 2] * v[:, 2]
    return out


@dataclass(frozen=True)
class Primitives:
    """A set of oriented primitives and their surface attributes.

    Attributes
    ----------
    centre : (P, 3) float64, metres
    rotation : (P, 3, 3) float64
        World from local (columns: local axes in world coordinates).
    half : (P, 3) float64, metres
        Half extents (box), semi-axes (ellipsoid), (radius, radius, half height) (cylinder).
    shape : (P,) int8
        :data:`SHAPE_BOX`, :data:`SHAPE_ELLIPSOID` or :data:`SHAPE_CYLINDER`.
    kind : (P,) int8
        Surface kind (index into the renderer's kind table).
    object_id : (P,) int64
        Physical object (the parts of one car share it).
    colour : (P, 3) float32
        Base albedo in [0, 1].
    reflectance : (P,) float32
        Base LiDAR reflectance in [0, 1].
    moving : (P,) bool
        Part of an object that moves in this frame.
    extra : (P, 4) float32
        Kind-specific surface parameters (buildings: window column spacing and floor height,
        metres, window width and height as fractions of them); zero otherwise.
    """

    centre: np.ndarray
    rotation: np.ndarray
    half: np.ndarray
    shape: np.ndarray
    kind: np.ndarray
    object_id: np.ndarray
    colour: np.ndarray
    reflectance: np.ndarray
    moving: np.ndarray
    extra: np.ndarray

    def __len__(self) -> int:
        return int(self.centre.shape[0])

    @classmethod
    def empty(cls) -> Primitives:
        return cls.from_rows([])

    @classmethod
    def from_rows(cls, rows: Sequence[tuple]) -> Primitives:
        """Build from rows ``(centre, rotation, half, shape, kind, object_id, colour, refl,
        moving[, extra])``."""
        n = len(rows)
        return cls(
            centre=np.array([r[0] for r in rows], dtype=np.float64).reshape(n, 3),
            rotation=np.array([r[1] for r in rows], dtype=np.float64).reshape(n, 3, 3),
            half=np.array([r[2] for r in rows], dtype=np.float64).reshape(n, 3),
            shape=np.array([r[3] for r in rows], dtype=np.int8).reshape(n),
            kind=np.array([r[4] for r in rows], dtype=np.int8).reshape(n),
            object_id=np.array([r[5] for r in rows], dtype=np.int64).reshape(n),
            colour=np.array([r[6] for r in rows], dtype=np.float32).reshape(n, 3),
            reflectance=np.array([r[7] for r in rows], dtype=np.float32).reshape(n),
            moving=np.array([r[8] for r in rows], dtype=bool).reshape(n),
            extra=np.array(
                [r[9] if len(r) > 9 else (0.0, 0.0, 0.0, 0.0) for r in rows], dtype=np.float32
            ).reshape(n, 4),
        )

    @classmethod
    def concat(cls, parts: Sequence[Primitives]) -> Primitives:
        return cls(
            **{
                name: np.concatenate([getattr(p, name) for p in parts])
                for name in cls.__dataclass_fields__
            }
        )

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World-axis bounding boxes ``(lo, hi)``, each (P, 3) float64, metres."""
        A = np.abs(self.rotation)
        h = self.half
        # |R| h bounds the rotated box; the margin keeps grazing rays inside the bound.
        reach = A[:, :, 0] * h[:, 0:1] + A[:, :, 1] * h[:, 1:2] + A[:, :, 2] * h[:, 2:3]
        reach = reach + 1e-9 * (1.0 + np.abs(self.centre))
        return self.centre - reach, self.centre + reach


@dataclass(frozen=True)
class BVH:
    """Bounding-volume hierarchy over a :class:`Primitives` set (arrays for the kernel).

    Attributes
    ----------
    node_lo, node_hi : (M, 3) float64
        Node bounding boxes, metres.
    node_left, node_right : (M,) int64
        Children of inner nodes (-1 for leaves).
    node_start, node_count : (M,) int64
        Leaves: primitives ``node_start .. node_start + node_count`` in BVH order.
    node_axis : (M,) int64
        Split axis of inner nodes (the left child holds the lower coordinates).
    order : (P,) int64
        Primitive index (in the original set) of each BVH position.
    centre, rotation, half, shape
        The primitives' geometry in BVH order.
    """

    node_lo: np.ndarray
    node_hi: np.ndarray
    node_left: np.ndarray
    node_right: np.ndarray
    node_start: np.ndarray
    node_count: np.ndarray
    node_axis: np.ndarray
    order: np.ndarray
    centre: np.ndarray
    rotation: np.ndarray
    half: np.ndarray
    shape: np.ndarray


def _area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    d = np.maximum(hi - lo, 0.0)
    return d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0]


def _sah_split(idx, lo, hi, mid) -> tuple[int, np.ndarray, float, int]:
    """Best (axis, indices sorted along it, cost, left count) by the surface-area heuristic:
    the cost of a split after the k-th primitive is area(left) * k + area(right) * (n - k)."""
    best = (0, idx, np.inf, idx.shape[0] // 2)
    n = idx.shape[0]
    for axis in range(3):
        sorted_idx = idx[np.argsort(mid[idx, axis], kind="stable")]
        l_lo = np.minimum.accumulate(lo[sorted_idx], axis=0)
        l_hi = np.maximum.accumulate(hi[sorted_idx], axis=0)
        r_lo = np.minimum.accumulate(lo[sorted_idx][::-1], axis=0)[::-1]
        r_hi = np.maximum.accumulate(hi[sorted_idx][::-1], axis=0)[::-1]
        k = np.arange(1, n)
        cost = _area(l_lo[:-1], l_hi[:-1]) * k + _area(r_lo[1:], r_hi[1:]) * (n - k)
        j = int(np.argmin(cost))
        if cost[j] < best[2]:
            best = (axis, sorted_idx, float(cost[j]), j + 1)
    return best


def _median_split(idx, lo, hi, mid) -> tuple[int, np.ndarray, float, int]:
    """Halve along the longest spread of the centres (cheap to build)."""
    spread = mid[idx].max(axis=0) - mid[idx].min(axis=0)
    axis = int(np.argmax(spread))
    return axis, idx[np.argsort(mid[idx, axis], kind="stable")], 0.0, idx.shape[0] // 2


def build_bvh(prims: Primitives, *, leaf_size: int = 2, split: str = "sah") -> BVH:
    """Bounding-volume hierarchy (stable sorts: the tree depends only on the input).

    Parameters
    ----------
    prims : Primitives
    leaf_size : int
        Nodes of at most this many primitives are leaves.
    split : {"sah", "median"}
        Surface-area heuristic (faster to trace; for the static street, built once) or
        median split (faster to build; for the actors, rebuilt every frame).
    """
    if leaf_size < 1:
        raise ParameterError(f"leaf_size must be >= 1, got {leaf_size}")
    if split not in ("sah", "median"):
        raise ParameterError(f"split must be 'sah' or 'median', got {split!r}")
    choose = _sah_split if split == "sah" else _median_split
    lo, hi = prims.bounds()
    mid = 0.5 * (lo + hi)
    n = len(prims)
    order = np.arange(n, dtype=np.int64)
    nodes: list[list] = []  # [lo, hi, left, right, start, count, axis]
    if n:
        nodes.append([None, None, -1, -1, 0, n, 0])
        todo = [0]
        while todo:
            k = todo.pop()
            start, count = nodes[k][4], nodes[k][5]
            idx = order[start : start + count]
            nodes[k][0] = lo[idx].min(axis=0)
            nodes[k][1] = hi[idx].max(axis=0)
            if count <= leaf_size:
                continue
            axis, sorted_idx, _, half = choose(idx, lo, hi, mid)
            order[start : start + count] = sorted_idx
            left, right = len(nodes), len(nodes) + 1
            nodes.append([None, None, -1, -1, start, half, 0])
            nodes.append([None, None, -1, -1, start + half, count - half, 0])
            nodes[k][2:] = [left, right, start, 0, axis]
            todo.extend([right, left])
    m = len(nodes)
    return BVH(
        node_lo=np.array([nd[0] for nd in nodes], dtype=np.float64).reshape(m, 3),
        node_hi=np.array([nd[1] for nd in nodes], dtype=np.float64).reshape(m, 3),
        node_left=np.array([nd[2] for nd in nodes], dtype=np.int64),
        node_right=np.array([nd[3] for nd in nodes], dtype=np.int64),
        node_start=np.array([nd[4] for nd in nodes], dtype=np.int64),
        node_count=np.array([nd[5] for nd in nodes], dtype=np.int64),
        node_axis=np.array([nd[6] for nd in nodes], dtype=np.int64),
        order=order,
        centre=np.ascontiguousarray(prims.centre[order]),
        rotation=np.ascontiguousarray(prims.rotation[order]),
        half=np.ascontiguousarray(prims.half[order]),
        shape=np.ascontiguousarray(prims.shape[order]),
    )


@dataclass(frozen=True)
class Hits:
    """Nearest hits of rays ``origin + t * directions``.

    Attributes
    ----------
    t : (N,) float64
        Ray parameter of the hit (``inf`` on a miss): metres along unit directions, camera
        depth for camera rays with unit camera z.
    index : (N,) int64
        Primitive index (into the concatenation of the casted sets, in the order given),
        :data:`HIT_GROUND` or :data:`HIT_NONE`.
    face : (N,) int8
        Box / cylinder-cap face ``2 * axis + (1 if the normal points to +axis)`` (local axes),
        6 ellipsoid, 7 cylinder side; the ground is 5; -1 on a miss.
    """

    t: np.ndarray
    index: np.ndarray
    face: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.index != HIT_NONE


def cast(
    origin: np.ndarray,
    directions: np.ndarray,
    bvhs: Sequence[BVH],
    *,
    ground: tuple[np.ndarray, float] | None = None,
    t_max: float = np.inf,
) -> Hits:
    """Cast rays from one origin against a ground plane and the primitives of ``bvhs``.

    Parameters
    ----------
    origin : (3,) float, metres
    directions : (N, 3) float
        Need not be unit length (``t`` is in units of their length).
    bvhs : sequence of BVH
        Hit indices count through the sets in this order (set 1 starts at ``len(set 0)``).
    ground : (normal (3,), offset), optional
        The plane ``normal . p = offset``, hit from the side ``normal`` points to.
    t_max : float
        Farther hits are ignored.

    Returns
    -------
    Hits
    """
    from ._video_kernels import cast_bvh, cast_plane

    origin = np.ascontiguousarray(origin, dtype=np.float64).reshape(3)
    d = np.ascontiguousarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ParameterError(f"directions must be (N, 3), got {d.shape}")
    if not np.all(np.isfinite(origin)):
        raise ParameterError("ray origin must be finite")
    n = d.shape[0]
    t = np.full(n, float(t_max))
    index = np.full(n, HIT_NONE, dtype=np.int64)
    face = np.full(n, -1, dtype=np.int8)
    if ground is not None:
        normal = np.ascontiguousarray(ground[0], dtype=np.float64).reshape(3)
        cast_plane(origin, d, normal, float(ground[1]), t, index, face, HIT_GROUND)
    offset = 0
    for bvh in bvhs:
        local = np.full(n, HIT_NONE, dtype=np.int64)
        cast_bvh(
            origin,
            d,
            bvh.node_lo,
            bvh.node_hi,
            bvh.node_left,
            bvh.node_right,
            bvh.node_start,
            bvh.node_count,
            bvh.node_axis,
            bvh.centre,
            bvh.rotation,
            bvh.half,
            bvh.shape,
            t,
            local,
            face,
        )
        won = local >= 0
        index[won] = bvh.order[local[won]] + offset
        offset += int(bvh.order.shape[0])
    t[index == HIT_NONE] = np.inf
    return Hits(t=t, index=index, face=face)
