"""``--filter-occluded``: what the occlusion test removes from single-scan LiDAR, and its speed.

Run: ``.venv/bin/python benchmarks/bench_occlusion.py [--frames 6] [--seeds 0 1]`` (``make bench``
runs it with the defaults).

1. Accuracy against exact depth. Synthetic streets (``synth-scene``, 1242x375, KITTI geometry:
   the Velodyne sits 0.27 m behind and 0.08 m above the camera, so it sees background past
   foreground edges) for each seed; every frame's 64-beam scan is projected as ``project``
   does, then filtered with :func:`sparsetools.ops.occlusion.filter_occluded` (defaults: rel
   0.1, footprint 0.1 m). Against the exact depth of the same pixels: delta1 (max(d/g, g/d) <
   1.25), RMSE and AbsRel of the map before and after, the fraction of pixels removed, and how
   many of the removed pixels were wrong (relative error > 10 %) and how many wrong pixels are
   left. Mean and spread (min..max) over the seeds.
2. Speed. The kernel on the real KITTI frame 000001 (1242x375, ../shared/data/real) against a
   straightforward reference of the same rule (a Python loop over the pixels, a window slice
   and its minimum per pixel), checked equal, medians of interleaved runs.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import interleaved, load

ROOT = Path(__file__).resolve().parent.parent
KITTI = ROOT.parent / "shared" / "data" / "real" / "kitti-object-kuixu"
WRONG = 0.10  # relative error above which a pixel counts as wrong


def reference_filter(depth: np.ndarray, fx: float) -> np.ndarray:
    """The rule written plainly: each pixel, its window, its minimum (defaults of the kernel)."""
    removed = np.zeros(depth.shape, bool)
    for v, u in zip(*np.nonzero(depth > 0), strict=True):
        z = float(depth[v, u])
        r = int(min(max(round(fx * 0.1 / z), 1), 8))
        win = depth[max(v - r, 0) : v + r + 1, max(u - r, 0) : u + r + 1]
        removed[v, u] = z > 1.1 * float(win[win > 0].min())
    return removed


def errors(depth: np.ndarray, gt: np.ndarray) -> dict:
    m = (depth > 0) & (gt > 0)
    d, g = depth[m].astype(np.float64), gt[m].astype(np.float64)
    ratio = np.maximum(d / g, g / d)
    return {
        "pixels": int(m.sum()),
        "delta1": float(np.mean(ratio < 1.25)),
        "rmse": float(np.sqrt(np.mean((d - g) ** 2))),
        "absrel": float(np.mean(np.abs(d - g) / g)),
        "wrong": int(np.sum(np.abs(d - g) / g > WRONG)),
    }


def accuracy(seed: int, frames: int, workdir: Path) -> dict:
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.image import read_depth_png
    from sparsetools.io.kitti import read_velodyne_bin
    from sparsetools.ops.occlusion import filter_occluded
    from sparsetools.ops.projection import project_points

    scene = workdir / f"seed{seed}"
    subprocess.run(
        [sys.executable, "-m", "sparsetools.cli.main", "synth-scene", "-o", str(scene), "--seed",
         str(seed), "--frames", str(frames), "--underwater-frames", "0"],
        check=True, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    before, after, removed_n, removed_wrong, n_pixels = [], [], 0, 0, 0
    for scan in sorted((scene / "velodyne").glob("*.bin")):
        calib = load_calibration(scene / "calib" / f"{scan.stem}.txt", camera=2)
        gt = read_depth_png(scene / "depth_gt" / f"{scan.stem}.png")
        calib = calib.with_size(gt.shape[1], gt.shape[0])
        depth = project_points(read_velodyne_bin(scan), calib)
        filtered, removed = filter_occluded(depth, fx=calib.fx)
        b, a = errors(depth, gt), errors(filtered, gt)
        before.append(b)
        after.append(a)
        rm = removed & (gt > 0)
        removed_n += int(rm.sum())
        removed_wrong += int(np.sum(np.abs(depth[rm] - gt[rm]) / gt[rm] > WRONG))
        n_pixels += b["pixels"]

    def pooled(rows, key):
        return float(np.average([r[key] for r in rows], weights=[r["pixels"] for r in rows]))

    return {
        "delta1_before": pooled(before, "delta1"), "delta1_after": pooled(after, "delta1"),
        "rmse_before": float(np.sqrt(pooled([{**r, "m": r["rmse"] ** 2} for r in before], "m"))),
        "rmse_after": float(np.sqrt(pooled([{**r, "m": r["rmse"] ** 2} for r in after], "m"))),
        "absrel_before": pooled(before, "absrel"), "absrel_after": pooled(after, "absrel"),
        "removed_pct": 100.0 * removed_n / max(n_pixels, 1),
        "removed_wrong_pct": 100.0 * removed_wrong / max(removed_n, 1),
        "wrong_before": sum(r["wrong"] for r in before),
        "wrong_after": sum(r["wrong"] for r in after),
    }  # fmt: skip


def speed() -> None:
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.kitti import read_velodyne_bin
    from sparsetools.ops.occlusion import filter_occluded
    from sparsetools.ops.projection import project_points

    scan = KITTI / "velodyne" / "000001.bin"
    if not scan.is_file():
        print(f"speed: real KITTI frame not found at {scan}: skipped")
        return
    calib = load_calibration(KITTI / "calib" / "000001.txt", camera=2).with_size(1242, 375)
    depth = project_points(read_velodyne_bin(scan), calib)
    ours = filter_occluded(depth, fx=calib.fx)[1]
    assert np.array_equal(ours, reference_filter(depth, calib.fx)), "kernel != reference"
    t = interleaved({"ours": lambda: filter_occluded(depth, fx=calib.fx),
                     "reference": lambda: reference_filter(depth, calib.fx)}, repeat=5)  # fmt: skip
    print(f"speed, real KITTI 000001 ({int((depth > 0).sum())} points in the map; {load()})")
    print(f"  filter_occluded  ours {t['ours'] * 1e3:8.2f} ms | reference (pixel loop) "
          f"{t['reference'] * 1e3:8.1f} ms | ratio {t['reference'] / t['ours']:6.1f}x")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    args = ap.parse_args()
    print(f"accuracy, synthetic streets 1242x375, {args.frames} frames x seeds {args.seeds} "
          f"({load()})")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        rows = [accuracy(s, args.frames, Path(tmp)) for s in args.seeds]
    for key in rows[0]:
        vals = np.array([r[key] for r in rows], float)
        print(f"  {key:<18} mean {vals.mean():10.4f}   spread {vals.min():.4f}..{vals.max():.4f}")
    speed()


if __name__ == "__main__":
    main()
