"""Acceptance run of ``dataset kitti-raw --gt-method accumulated`` on the real 11-frame sequence.

Data: ../shared/data/real/kitti-raw-sequence-2011_09_26 (frames 0..10, no oxts: ICP poses, no
image_03: no stereo check), built into a KITTI raw tree (``<date>/<drive>/...``) in a
temporary folder, as tests/test_real_trees.py does.

1. The route, as a user runs it: ``sparsetools dataset kitti-raw RAW -o DS --gt-method
   accumulated --icp-min-range 20`` (K = 5, occlusion test on every scan including frame t's,
   moving-object test). Per frame: the ground truth's density (valid pixels of the 1242x375
   image; KITTI's annotated maps: 18-21 %), the window it had, the single scan's density.
2. Agreement with frame t's own scan (pixels both have, |depth difference|: median, 95th
   percentile, share beyond 1 m), for a few frames, with the route's own ICP poses (read back
   from ``DS/.sources/gt_accumulated/icp``):
   a. frame t held out (``hold_out_reference``: the other frames' points, occlusion test among
      them, no consistency test: frame t is not there to test against), against frame t's
      scan as projected and against it without its see-through points
      (:func:`sparsetools.ops.occlusion.filter_occluded`);
   b. frame t's scan split by rings: the even rings play frame t in every test (occlusion,
      including its own points, and moving objects: the route's settings), the odd rings are
      held out and compared with the other frames' pixels.

Run: ``PYTHONPATH=src .venv/bin/python benchmarks/acceptance_gt_routes.py [--frames 3,5,7]``
(about half a minute on 2 shared cores).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SEQ = REPO.parent / "shared" / "data" / "real" / "kitti-raw-sequence-2011_09_26"
DATE = "2011_09_26"
DRIVE = f"{DATE}_drive_0001_sync"


def raw_tree(root: Path) -> Path:
    date = root / DATE
    date.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(SEQ / name, date / name)
    for sub in ("velodyne_points", "image_02"):
        shutil.copytree(SEQ / sub, date / DRIVE / sub)
    return date


def agreement(depth: np.ndarray, reference: np.ndarray) -> str:
    both = (depth > 0) & (reference > 0)
    diff = np.abs(depth[both].astype(np.float64) - reference[both])
    if not diff.size:
        return "no common pixel"
    return (
        f"{diff.size:6d} px | median {np.median(diff) * 100:5.1f} cm | p95 "
        f"{np.percentile(diff, 95) * 100:6.1f} cm | > 1 m {np.mean(diff > 1.0):6.1%}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="3,5,7", help="frames of part 2 (comma-separated)")
    args = ap.parse_args()
    if not SEQ.is_dir():
        sys.exit(f"real sequence not found at {SEQ}")
    from click.testing import CliRunner

    from sparsetools.cli.main import cli
    from sparsetools.io.calib import read_kitti_raw_calib
    from sparsetools.io.image import read_depth_png
    from sparsetools.io.kitti import read_velodyne_bin
    from sparsetools.ops.accumulate import AccumulateSettings, accumulate_scans
    from sparsetools.ops.beams import recover_rings
    from sparsetools.ops.occlusion import filter_occluded
    from sparsetools.ops.projection import project_points
    from sparsetools.ops.registration import chain_poses

    print(f"load average (1, 5, 15 min): {os.getloadavg()}, {os.cpu_count()} CPUs")
    tmp = Path(tempfile.mkdtemp(prefix="gt_routes_"))
    try:
        date = raw_tree(tmp / "raw")
        ds = tmp / "ds"
        cmd = ["dataset", "kitti-raw", str(date), "-o", str(ds), "--gt-method", "accumulated",
               "--icp-min-range", "20", "--json", "-q"]  # fmt: skip
        t0 = time.perf_counter()
        r = CliRunner().invoke(cli, cmd)
        seconds = time.perf_counter() - t0
        if r.exit_code:
            sys.exit(r.output)
        summary = json.loads(r.stdout)
        print(f"\n1. sparsetools {' '.join(cmd[:2])} RAW -o DS {' '.join(cmd[5:9])}: "
              f"{seconds:.1f} s (ICP of 10 pairs, 11 frames accumulated, the dataset)")  # fmt: skip
        g = summary["gt"]
        print(f"   gt: {g['method']}, poses {g['pose_source']}, clipped windows "
              f"{g['clipped_windows']}, removed {g['removed']}, icp {g['icp']}")  # fmt: skip
        import pyarrow.parquet as pq

        rows = pq.read_table(ds / "manifest.parquet").to_pylist()
        calib = read_kitti_raw_calib(date)
        scans = {
            int(p.stem): read_velodyne_bin(p)
            for p in sorted((date / DRIVE / "velodyne_points" / "data").glob("*.bin"))
        }
        print("   frame  window      GT density   single scan   GT / single")
        dens = []
        for row in rows:
            n = int(row["id"].split("/")[-1])
            gt = read_depth_png(ds / row["gt_path"])
            single = project_points(scans[n], calib)
            d = float(np.mean(gt > 0))
            dens.append(d)
            window = json.loads(row["generation_params"])["sample"]["gt_window"]
            print(f"   {n:5d}  {window:10s}  {d:9.2%}   {np.mean(single > 0):10.2%}   "
                  f"{d / np.mean(single > 0):6.2f}")  # fmt: skip
        full = [d for row, d in zip(rows, dens, strict=True)
                if json.loads(row["generation_params"])["sample"]["gt_window"] == "t-5..t+5"]  # fmt: skip
        print(f"   mean density {np.mean(dens):.2%} (all 11), full windows: "
              f"{', '.join(f'{d:.2%}' for d in full)}")  # fmt: skip

        # 2. agreement with frame t's own scan, with the route's ICP poses
        pairs = []
        for k in range(1, 11):
            doc = json.loads((ds / ".sources" / "gt_accumulated" / "icp" / DRIVE /
                              f"{k:010d}.json").read_text())  # fmt: skip
            pairs.append(np.asarray(doc["T_target_from_source"], dtype=np.float64))
        print("\n2. agreement with frame t's own scan (pixels both have, |depth difference|)")
        route = AccumulateSettings(occlude_own=True)
        held = AccumulateSettings(consistency_rel=None)
        for t in (int(x) for x in args.frames.split(",")):
            lo, hi = max(0, t - 5), min(10, t + 5)
            window = [scans[k] for k in range(lo, hi + 1)]
            poses = chain_poses(pairs[lo:hi], reference=t - lo)
            own = project_points(scans[t], calib)
            own_clean, _ = filter_occluded(own, fx=calib.fx)
            res = accumulate_scans(window, poses, calib, reference=t - lo, settings=held,
                                   hold_out_reference=True)  # fmt: skip
            print(f"   frame {t} (window {lo}..{hi}), held out, occlusion among the others:")
            print(f"     vs its scan                         {agreement(res.depth, own)}")
            print(f"     vs its scan without see-through     {agreement(res.depth, own_clean)}")
            ring = recover_rings(scans[t])
            split = list(window)
            split[t - lo] = scans[t][ring % 2 == 0]
            r2 = accumulate_scans(split, poses, calib, reference=t - lo, settings=route)
            others = np.where(r2.source != t - lo, r2.depth, 0)
            odd = project_points(scans[t][ring % 2 == 1], calib)
            print(f"     ring split, route's tests, vs odd    {agreement(others, odd)}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nload average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
