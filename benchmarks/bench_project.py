"""``project``: our z-buffer vs a numpy reference and Open3D on real KITTI frames; CLI throughput.

Run: ``.venv/bin/python benchmarks/bench_project.py`` (``make bench`` runs it with the others).

1. ``project_points`` on real KITTI object frames (000001: 120,268 points to 1242x375;
   000000: 115,384 points to 1224x370) against
   (a) monodepth2's ``generate_depth_map`` algorithm written with numpy (Python loop over the
       pixels hit by several points, as the original does), and a fully vectorised numpy
       z-buffer (``np.minimum.at``), the fastest plain-numpy variant;
   (b) Open3D's ``t.geometry.PointCloud.project_to_depth_image`` with the same transform
       (KITTI's P2 translation column folded into the extrinsics).
   Maps are compared for agreement too.
2. Batch throughput of ``sparsetools project`` on 200 frames (copies of a real frame with
   millimetre jitter), PNG writing included, with ``--workers 1`` and ``--workers 2``.

Skips part 1 and uses a synthetic frame for part 2 when ../shared/data/real is absent.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import compare, median_seconds

ROOT = Path(__file__).resolve().parent.parent
REAL = ROOT.parent / "shared" / "data" / "real" / "kitti-object-kuixu"
SIZES = {"000000": (1224, 370), "000001": (1242, 375)}


def monodepth2_numpy(points, M, width, height):
    """monodepth2 generate_depth_map: x >= 0, round - 1, last write, then min over duplicates."""
    velo = points[points[:, 0] >= 0].astype(np.float64)
    velo[:, 3] = 1.0
    pts = velo @ M.T
    pts[:, :2] /= pts[:, 2:3]
    x = np.round(pts[:, 0]).astype(np.int64) - 1
    y = np.round(pts[:, 1]).astype(np.int64) - 1
    ok = (x >= 0) & (y >= 0) & (x < width) & (y < height)
    x, y, z = x[ok], y[ok], pts[ok, 2]
    depth = np.zeros((height, width))
    depth[y, x] = z
    inds = y * width + x
    uniq, counts = np.unique(inds, return_counts=True)
    for dd in uniq[counts > 1]:
        sel = np.flatnonzero(inds == dd)
        depth[y[sel[0]], x[sel[0]]] = z[sel].min()
    depth[depth < 0] = 0
    return depth


def numpy_minimum_at(points, M, width, height, min_depth=0.1):
    """Vectorised numpy z-buffer: project, filter, np.minimum.at (order-independent)."""
    uvw = points[:, :3].astype(np.float64) @ M[:, :3].T + M[:, 3]
    z = uvw[:, 2]
    keep = z > min_depth
    uvw, z = uvw[keep], z[keep]
    u = np.rint(uvw[:, 0] / z).astype(np.int64)
    v = np.rint(uvw[:, 1] / z).astype(np.int64)
    ok = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    buf = np.full(width * height, np.inf)
    np.minimum.at(buf, v[ok] * width + u[ok], z[ok])
    return np.where(np.isfinite(buf), buf, 0).astype(np.float32).reshape(height, width)


def open3d_setup(points, calib):
    import open3d as o3d

    P = calib.P
    K = P[:, :3]
    # P = K [I | K^-1 p4]: fold the translation column into the extrinsics.
    shift = np.eye(4)
    shift[:3, 3] = np.linalg.solve(K, P[:, 3])
    extrinsics = shift @ calib.T_cam_from_sensor
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(points[:, :3])))
    K_t = o3d.core.Tensor(K)
    E_t = o3d.core.Tensor(extrinsics)
    W, H = calib.size

    def run():
        return pcd.project_to_depth_image(W, H, K_t, E_t, depth_scale=1.0, depth_max=1000.0)

    return run


def bench_frame(stem: str) -> None:
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.kitti import read_velodyne_bin
    from sparsetools.ops.projection import project_points

    points = read_velodyne_bin(REAL / "velodyne" / f"{stem}.bin")
    calib = load_calibration(REAL / "calib" / f"{stem}.txt", image_size=SIZES[stem])
    M = calib.projection
    W, H = calib.size
    project_points(points, calib)  # compile / load the numba cache outside the timing
    tag = f"{stem}: {points.shape[0]} pts -> {W}x{H}"

    def ours():
        return project_points(points, calib)

    def ours_md2():
        return project_points(points[points[:, 0] >= 0], calib, pixel_offset=-1)

    compare(
        f"{tag} vs monodepth2 (numpy+loop)",
        ours_md2,
        lambda: monodepth2_numpy(points, M, W, H),
        reference_name="md2",
        repeat=5,
    )
    compare(
        f"{tag} vs numpy minimum.at",
        ours,
        lambda: numpy_minimum_at(points, M, W, H),
        reference_name="numpy",
        repeat=15,
    )
    o3d_run = open3d_setup(points, calib)
    compare(
        f"{tag} vs Open3D project_to_depth_image", ours, o3d_run, reference_name="open3d", repeat=31
    )

    a = ours()
    md2 = monodepth2_numpy(points, M, W, H).astype(np.float32)
    print(
        f"  agreement: monodepth2 map == ours(-1 px, x >= 0): "
        f"{np.array_equal(md2, ours_md2())}; numpy minimum.at == ours: "
        f"{np.array_equal(numpy_minimum_at(points, M, W, H), a)}"
    )
    o3d_map = np.asarray(o3d_run().as_tensor().numpy())[:, :, 0]
    both = (o3d_map > 0) & (a > 0)
    same_pixels = np.mean((o3d_map > 0) == (a > 0))
    print(
        f"  Open3D: valid {np.count_nonzero(o3d_map)} vs ours {np.count_nonzero(a)}, "
        f"same validity on {100 * same_pixels:.4f} % of pixels, "
        f"max |diff| where both valid {np.abs(o3d_map[both] - a[both]).max():.2e} m"
    )


def part1() -> None:
    print(f"numba kernel single-threaded; machine has {os.cpu_count()} cores")
    for stem in ("000001", "000000"):
        bench_frame(stem)


def part2() -> None:
    exe = ROOT / ".venv" / "bin" / "sparsetools"
    cmd0 = [str(exe)] if exe.exists() else [sys.executable, "-m", "sparsetools.cli.main"]
    with tempfile.TemporaryDirectory(prefix="bench-project-") as tmp:
        tmp = Path(tmp)
        clouds = tmp / "velodyne"
        clouds.mkdir()
        if REAL.is_dir():
            base = np.fromfile(REAL / "velodyne" / "000001.bin", dtype="<f4").reshape(-1, 4)
            calib_file = REAL / "calib" / "000001.txt"
            size = "1242x375"
        else:
            from sparsetools.synth import generate_scene

            generate_scene(tmp / "scene", frames=1, underwater_frames=0)
            base = np.fromfile(tmp / "scene" / "velodyne" / "000000.bin", "<f4").reshape(-1, 4)
            calib_file = tmp / "scene" / "calib" / "000000.txt"
            size = "1242x375"
        rng = np.random.default_rng(0)
        for i in range(200):
            jitter = base.copy()
            jitter[:, :3] += rng.normal(0, 0.002, (base.shape[0], 3)).astype(np.float32)
            jitter.tofile(clouds / f"{i:06d}.bin")
        print(f"batch: 200 frames of {base.shape[0]} points -> {size} PNG")
        rates = {}
        for workers in (1, 2):
            out = tmp / f"out{workers}"
            cmd = [
                *cmd0,
                "-q",
                "project",
                str(clouds),
                "--calib",
                str(calib_file),
                "--image-size",
                size,
                "-o",
                str(out),
                "--workers",
                str(workers),
                "--json",
            ]
            t0 = time.perf_counter()
            res = subprocess.run(cmd, capture_output=True, text=True, check=True)
            wall = time.perf_counter() - t0
            summary = json.loads(res.stdout)
            assert summary["processed"] == 200, summary
            rates[workers] = 200 / wall
            print(
                f"  --workers {workers}: {wall:6.2f} s wall (process start included) "
                f"= {200 / wall:6.1f} frames/s; in-run {summary['frames_per_s']} frames/s"
            )
        print(f"  scaling 1 -> 2 workers: {rates[2] / rates[1]:.2f}x")
    # Per-frame cost breakdown of the serial path, to see where the time goes.
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.image import encode_depth_png
    from sparsetools.io.kitti import read_velodyne_bin
    from sparsetools.ops.projection import project_points

    if REAL.is_dir():
        path = REAL / "velodyne" / "000001.bin"
        calib = load_calibration(REAL / "calib" / "000001.txt", image_size=(1242, 375))
        pts = read_velodyne_bin(path)
        depth = project_points(pts, calib)
        t_read = median_seconds(lambda: read_velodyne_bin(path), repeat=15)
        t_proj = median_seconds(lambda: project_points(pts, calib), repeat=15)
        t_png = median_seconds(lambda: encode_depth_png(depth), repeat=15)
        print(
            f"  per frame: read {t_read * 1e3:.2f} ms, project {t_proj * 1e3:.2f} ms, "
            f"PNG encode {t_png * 1e3:.2f} ms"
        )


if __name__ == "__main__":
    if REAL.is_dir():
        part1()
    else:
        print(f"real KITTI frames not found at {REAL}: skipping the single-frame comparison")
    part2()
