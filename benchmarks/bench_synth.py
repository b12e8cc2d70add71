"""Video mode of synth-scene: the BVH ray-casting kernel vs a straightforward numpy caster,
and what a frame / a sequence costs.

Input: the static street of video seed 0, sequence 0 (about 900 oriented boxes, ellipsoids
and cylinders over 700 m), and the camera rays (pixel centres) of frame 0 at 416x128 from its
true pose. The reference loops over the primitives and intersects all rays with each in numpy
(local frame, slab test or quadratic), keeping the nearest: the same hits (checked below).
Then: one frame at 416x128 and at 1242x375 (camera with 2x2 anti-aliasing + centre ray, the
64 x 2000 ray LiDAR, shading), and a whole 30-frame 416x128 sequence, all single-threaded.
Run: ``python benchmarks/bench_synth.py``.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import compare, median_seconds


def numpy_cast(origin, dirs, prims, t_max):
    """Nearest hit per ray over all primitives, one primitive at a time (vectorised over rays)."""
    from sparsetools.synth.primitives import SHAPE_BOX, SHAPE_ELLIPSOID

    n = dirs.shape[0]
    best = np.full(n, t_max)
    index = np.full(n, -1)
    for p in range(len(prims)):
        R, c, e = prims.rotation[p], prims.centre[p], prims.half[p]
        o = R.T @ (origin - c)
        d = dirs @ R  # rows: R^T d
        if prims.shape[p] == SHAPE_BOX:
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-e - o) / d
                t2 = (e - o) / d
            t1 = np.where(np.isnan(t1), -np.inf, t1)
            t2 = np.where(np.isnan(t2), np.inf, t2)
            tn = np.minimum(t1, t2).max(axis=1)
            tf = np.maximum(t1, t2).min(axis=1)
            t = np.where((tn <= tf) & (tn > 1e-9), tn, np.inf)
        elif prims.shape[p] == SHAPE_ELLIPSOID:
            u, v = o / e, d / e
            a = (v * v).sum(axis=1)
            b = v @ u
            cc = u @ u - 1.0
            disc = b * b - a * cc
            t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
            t = np.where((t > 1e-9) & (cc >= 0), t, np.inf)
        else:
            a = d[:, 0] ** 2 + d[:, 1] ** 2
            b = o[0] * d[:, 0] + o[1] * d[:, 1]
            cc = o[0] ** 2 + o[1] ** 2 - e[0] ** 2
            disc = b * b - a * cc
            sq = np.sqrt(np.maximum(disc, 0))
            with np.errstate(divide="ignore", invalid="ignore"):
                s0, s1 = (-b - sq) / a, (-b + sq) / a
                z1, z2 = (-e[2] - o[2]) / d[:, 2], (e[2] - o[2]) / d[:, 2]
            tn = np.maximum(s0, np.minimum(z1, z2))
            tf = np.minimum(s1, np.maximum(z1, z2))
            t = np.where((disc >= 0) & (a > 0) & (tn <= tf) & (tn > 1e-9), tn, np.inf)
        closer = t < best
        best[closer] = t[closer]
        index[closer] = p
    return best, index


def main() -> None:
    from sparsetools.synth.primitives import cast, rotate
    from sparsetools.synth.video import VideoSimulator

    print(f"load average before: {os.getloadavg()}")
    sim = VideoSimulator(0, 0, n_frames=30, image_size=(416, 128))
    T = sim.T_scene_from_cam(0)
    dirs = rotate(T[:3, :3], sim.camera.rays(0.0, 0.0))
    bvh = sim._static_bvh
    prims = sim.street.primitives
    ours = cast(T[:3, 3], dirs, [bvh], t_max=400.0)
    ref_t, ref_i = numpy_cast(T[:3, 3], dirs, prims, 400.0)
    same = np.mean(ours.index == ref_i)
    hit = ref_i >= 0
    print(
        f"{len(prims)} primitives, {dirs.shape[0]} rays: same nearest primitive for "
        f"{same:.5f} of the rays, max |dt| {np.abs(ours.t[hit] - ref_t[hit]).max():.2e} m"
    )
    compare(
        "cast 53k camera rays, static street",
        lambda: cast(T[:3, 3], dirs, [bvh], t_max=400.0),
        lambda: numpy_cast(T[:3, 3], dirs, prims, 400.0),
        reference_name="numpy per primitive",
        repeat=3,
    )
    sim.frame(0)  # compiles / loads the kernels
    t416 = median_seconds(lambda: sim.frame(1), repeat=5)
    print(f"one 416x128 frame (camera + LiDAR + shading): {t416 * 1e3:.0f} ms")
    t0 = time.perf_counter()
    for _ in VideoSimulator(1, 0, n_frames=30, image_size=(416, 128)).frames():
        pass
    print(
        f"30-frame 416x128 sequence (seed 1, incl. street set-up): {time.perf_counter() - t0:.1f} s"
    )
    big = VideoSimulator(0, 0, n_frames=2, image_size=(1242, 375))
    t_big = median_seconds(lambda: big.frame(1), repeat=3)
    no_lidar = VideoSimulator(0, 0, n_frames=2, image_size=(1242, 375), lidar=False)
    t_cam = median_seconds(lambda: no_lidar.frame(1), repeat=3)
    print(f"one 1242x375 frame: {t_big:.2f} s ({t_cam:.2f} s without the LiDAR)")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
