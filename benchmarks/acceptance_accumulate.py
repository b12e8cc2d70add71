"""Acceptance run of accumulation and densification on the real 11-frame KITTI sequence.

Data: ../shared/data/real/kitti-raw-sequence-2011_09_26 (frames 0..10, Velodyne scans, left
colour images, the date's calibration; no oxts) and, for the density of KITTI's annotated
ground truth, the three maps of ../shared/data/real/kitti-depth-gt-metric3d (another drive).

1. Poses by ICP between consecutive scans (``icp_pose``, Open3D point-to-plane), fitness and
   inlier RMSE per pair, for all points and for points beyond 20 m (the car drives in dense
   traffic: the near points are mostly vehicles moving with it); a direct registration of
   frames 0 and 10 checks the chained result. Poses relative to frame 5 (``chain_poses``).
2. Density of frame 5's single projected scan, of the accumulation of frames 0..10 into it,
   and of the annotated KITTI maps.
3. Agreement of the OTHER frames' accumulated points with frame 5's own scan on the pixels
   both have (median and 95th percentile of |depth difference|):
   a. frame 5 held out completely (``hold_out_reference``: occlusion test among the other
      scans only, no consistency test), with and without the occlusion test, and with the
      all-points ICP poses;
   b. frame 5's scan split by rings: the even rings act as frame t's own scan for every
      test (occlusion and moving objects), the odd rings are held out and compared.
4. IP-Basic (paper version) on the real frame: from the odd rings against the even rings
   (same instant: no pose, no motion), and from the whole scan against 3a's accumulated map
   of the other frames (a KITTI-like semi-dense reference, not KITTI's own ground truth; it
   holds the moving traffic of the other instants).

Run: ``.venv/bin/python benchmarks/acceptance_accumulate.py [--docs]`` (about a minute on 2
cores). ``--docs`` writes docs/img/accumulate_kitti.png, accumulate_sources.png and
densify_kitti.png.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault(
    "OPENBLAS_NUM_THREADS", "1"
)  # see bench_densify.py (Open3D keeps its threads)

import numpy as np

REPO = Path(__file__).resolve().parent.parent
REAL = REPO.parent / "shared" / "data" / "real"
SEQ = REAL / "kitti-raw-sequence-2011_09_26"
GT = REAL / "kitti-depth-gt-metric3d"
IMG = REPO / "docs" / "img"
T_REF = 5


def load():
    from sparsetools.io.calib import read_kitti_raw_calib
    from sparsetools.io.image import read_image
    from sparsetools.io.kitti import read_velodyne_bin

    stems = [f"{i:010d}" for i in range(11)]
    scans = [read_velodyne_bin(SEQ / "velodyne_points" / "data" / f"{s}.bin") for s in stems]
    image = read_image(SEQ / "image_02" / "data" / f"{stems[T_REF]}.png")
    return scans, image, read_kitti_raw_calib(SEQ)


def register(scans, **kw):
    from sparsetools.ops.registration import chain_poses, icp_pose

    t0 = time.perf_counter()
    pairs = [icp_pose(scans[k + 1], scans[k], **kw) for k in range(len(scans) - 1)]
    seconds = time.perf_counter() - t0
    poses = chain_poses([p.T_target_from_source for p in pairs], reference=T_REF)
    return pairs, poses, seconds


def yaw_deg(T):
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def agreement(depth, reference):
    both = (depth > 0) & (reference > 0)
    diff = np.abs(depth[both].astype(np.float64) - reference[both])
    return {
        "pixels": int(both.sum()),
        "median": float(np.median(diff)),
        "p95": float(np.percentile(diff, 95)),
        "over_1m": float(np.mean(diff > 1.0)),
    }


def fmt(a):
    return (
        f"{a['pixels']:6d} px | median {a['median'] * 100:5.1f} cm | p95 {a['p95'] * 100:6.1f} cm "
        f"| > 1 m {a['over_1m']:.2%}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--docs", action="store_true", help="write the docs/img pictures")
    ap.add_argument(
        "--learned",
        help="densifier.pt checkpoint(s) of train-densifier, comma-separated (one per seed): "
        "also compare `densify --method learned` with IP-Basic on the real frame",
    )
    args, _ = ap.parse_known_args()
    if not SEQ.is_dir():
        sys.exit(f"real sequence not found at {SEQ}")

    from sparsetools.io.image import read_depth_png
    from sparsetools.ops.accumulate import AccumulateSettings, accumulate_scans
    from sparsetools.ops.beams import recover_rings
    from sparsetools.ops.densify import ip_basic
    from sparsetools.ops.metrics import depth_metrics
    from sparsetools.ops.projection import project_points
    from sparsetools.ops.registration import icp_pose

    print(f"load average (1, 5, 15 min): {os.getloadavg()}, {os.cpu_count()} CPUs")
    scans, image, calib = load()
    print(
        f"{len(scans)} scans, {np.mean([s.shape[0] for s in scans]):.0f} points each; {calib.size}"
    )

    # 1. poses
    all_pairs, all_poses, t_all = register(scans)
    far_pairs, poses, t_far = register(scans, min_range=20.0)
    print("\nICP between consecutive scans (point-to-plane, voxel 0.2 m, distance 0.5 m):")
    print(
        "pair     all points: dx m   yaw deg  fitness  RMSE m | beyond 20 m: dx m   yaw deg  fitness  RMSE m"
    )
    for k, (a, f) in enumerate(zip(all_pairs, far_pairs, strict=True)):
        Ta, Tf = a.T_target_from_source, f.T_target_from_source
        print(
            f"{k:2d}<-{k + 1:<2d}            {Ta[0, 3]:6.3f}  {yaw_deg(Ta):7.3f}  {a.fitness:7.3f}  "
            f"{a.inlier_rmse:6.3f} |              {Tf[0, 3]:6.3f}  {yaw_deg(Tf):7.3f}  "
            f"{f.fitness:7.3f}  {f.inlier_rmse:6.3f}"
        )
    direct = icp_pose(scans[10], scans[0], min_range=20.0)
    chained = np.linalg.inv(poses[0]) @ poses[10]
    print(
        f"frames 0<-10: chained (beyond 20 m) x {chained[0, 3]:.3f} m, all points chained "
        f"x {(np.linalg.inv(all_poses[0]) @ all_poses[10])[0, 3]:.3f} m, direct ICP x "
        f"{direct.T_target_from_source[0, 3]:.3f} m (fitness {direct.fitness:.3f}, RMSE "
        f"{direct.inlier_rmse:.3f} m); |chained - direct| "
        f"{np.linalg.norm(chained[:3, 3] - direct.T_target_from_source[:3, 3]) * 100:.1f} cm"
    )
    print(f"ICP time: {t_all:.1f} s (all points), {t_far:.1f} s (beyond 20 m) for 10 pairs")

    # 2. density
    single = project_points(scans[T_REF], calib)
    t0 = time.perf_counter()
    acc = accumulate_scans(scans, poses, calib, reference=T_REF)
    t_acc = time.perf_counter() - t0
    gt_density = [
        float(np.mean(read_depth_png(p) > 0)) for p in sorted((GT / "depth").glob("*.png"))
    ]
    print(
        f"\ndensity of frame {T_REF}'s map: single scan {np.mean(single > 0):.2%}, accumulated "
        f"+-5 frames {acc.density:.2%} ({t_acc * 1e3:.0f} ms); annotated KITTI GT maps "
        f"{', '.join(f'{d:.2%}' for d in gt_density)}"
    )
    rows = np.nonzero(single.any(axis=1))[0]
    band = slice(rows[0], rows[-1] + 1)
    print(
        f"  inside the rows the single scan covers ({rows[0]}..{rows[-1]}): single "
        f"{np.mean(single[band] > 0):.2%}, accumulated {np.mean(acc.depth[band] > 0):.2%}"
    )
    print(f"  removals: {acc.counts}")
    per = ", ".join(
        f"{k - T_REF:+d}: {np.count_nonzero(acc.source == k)}" for k in range(len(scans))
    )
    print(f"  pixels won per frame offset: {per}")

    # 3a. frame 5 held out
    held = AccumulateSettings(consistency_rel=None)
    print(f"\nagreement of the other frames' points with frame {T_REF}'s own scan (held out):")
    out = {}
    for name, s, P in (
        ("occlusion test (all), ICP beyond 20 m", held, poses),
        (
            "no filter, ICP beyond 20 m",
            AccumulateSettings(occlusion_rel=None, consistency_rel=None),
            poses,
        ),
        ("occlusion test (all), ICP all points", held, all_poses),
    ):
        r = accumulate_scans(scans, P, calib, reference=T_REF, settings=s, hold_out_reference=True)
        out[name] = r
        print(f"  {name:<40} density {r.density:6.2%} | {fmt(agreement(r.depth, single))}")
    others = out["occlusion test (all), ICP beyond 20 m"]

    # 3b. ring split: even rings are frame t's scan for the tests, odd rings are held out
    ring = recover_rings(scans[T_REF])
    even, odd = scans[T_REF][ring % 2 == 0], scans[T_REF][ring % 2 == 1]
    split_scans = [*scans[:T_REF], even, *scans[T_REF + 1 :]]
    r = accumulate_scans(split_scans, poses, calib, reference=T_REF)
    odd_map = project_points(odd, calib)
    from_others = np.where(r.source != T_REF, r.depth, 0)
    print(
        f"  ring split, all tests on the even rings, vs the odd rings:   "
        f"{fmt(agreement(from_others, odd_map))}"
    )
    print(f"    removals of the other frames: {r.counts}")
    r_off = accumulate_scans(
        split_scans,
        poses,
        calib,
        reference=T_REF,
        settings=AccumulateSettings(occlusion_rel=None, consistency_rel=None),
    )
    off_others = np.where(r_off.source != T_REF, r_off.depth, 0)
    print(
        f"  ring split, no filters:                                     {fmt(agreement(off_others, odd_map))}"
    )

    # 4. IP-Basic on the real frame
    import cv2

    cv2.setNumThreads(1)
    dense = ip_basic(single)
    t0 = time.perf_counter()
    for _ in range(10):
        ip_basic(single)
    t_ip = (time.perf_counter() - t0) / 10
    print(
        f"\nIP-Basic (fast, extrapolated, Gaussian) on frame {T_REF}, {t_ip * 1e3:.1f} ms on one "
        "core; paper (KITTI test GT, 64 beams): RMSE 1288 mm, MAE 303 mm, iRMSE 3.75, iMAE 1.29"
    )
    even_map = project_points(even, calib)
    for name, inp, ref in (
        ("odd rings (32 beams) -> even rings, same instant", odd_map, even_map),
        ("64 beams -> held-out accumulation of frames 0-4, 6-10", single, others.depth),
    ):
        pred = ip_basic(inp).depth
        ref = np.where(ref < 80, ref, 0)
        m = depth_metrics(pred, np.where(pred > 0, ref, 0), max_depth=80.0)
        both = (pred > 0) & (ref > 0)
        cover = np.count_nonzero(both) / max(np.count_nonzero(ref > 0), 1)
        med = float(np.median(np.abs(pred[both] - ref[both])))
        print(
            f"  {name:<54} {m['n_pixels']:6d} px (coverage {cover:.1%}): RMSE "
            f"{m['rmse'] * 1e3:5.0f} mm, MAE {m['mae'] * 1e3:4.0f} mm, median {med * 1e3:3.0f} mm, "
            f"iRMSE {m['irmse']:5.2f}, iMAE {m['imae']:4.2f} 1/km"
        )
    if args.learned:
        learned_rows(args.learned.split(","), single, odd_map, even_map, others.depth)
    dense_acc = ip_basic(acc.depth)
    print(f"load average (1, 5, 15 min): {os.getloadavg()}")

    if args.docs:
        pictures(image, single, acc, dense, dense_acc)


def learned_rows(checkpoints, single, odd_map, even_map, held_out) -> None:
    """The learned densifier (issue 29) on the same real inputs and references as IP-Basic
    above: RMSE / MAE on the pixels it fills and on those IP-Basic fills too, and the mean
    predicted sigma = exp(U / 2) beside the mean absolute error (a calibrated U gives
    MAE / sigma near sqrt(2 / pi) = 0.80)."""
    from sparsetools.ops.densify import ip_basic
    from sparsetools.ops.metrics import depth_metrics
    from sparsetools.train.densifier import LearnedDensifier

    cases = (
        ("odd rings (32 beams) -> even rings", odd_map, even_map),
        ("64 beams -> held-out accumulation", single, held_out),
    )
    print("\nlearned densifier (densify --method learned) on the same frame, one thread:")
    for ckpt in checkpoints:
        model = LearnedDensifier(ckpt)
        for name, inp, ref in cases:
            ref = np.where(ref < 80, ref, 0)
            t0 = time.perf_counter()
            pred, u = model.densify(inp)
            seconds = time.perf_counter() - t0
            both_ip = ip_basic(inp).depth > 0
            line = []
            for where, label in ((pred > 0, "all it fills"), ((pred > 0) & both_ip, "IP-Basic's")):
                m = depth_metrics(np.where(where, pred, 0), np.where(where, ref, 0), max_depth=80.0)
                line.append(f"{label}: {m['n_pixels']} px RMSE {m['rmse'] * 1e3:5.0f} mm MAE "
                            f"{m['mae'] * 1e3:4.0f} mm")  # fmt: skip
            ok = (pred > 0) & (ref > 0)
            mae = float(np.mean(np.abs(pred[ok] - ref[ok])))
            sigma = float(np.mean(np.exp(u[ok] / 2.0)))
            print(f"  {Path(ckpt).parent.name} {name:<36} {' | '.join(line)} | mean sigma "
                  f"{sigma * 1e3:5.0f} mm, MAE / sigma {mae / sigma:4.2f} | {seconds:.2f} s")  # fmt: skip


def pictures(image, single, acc, dense, dense_acc):
    import cv2

    from sparsetools.ops.colormap import colorize_depth, overlay_depth, side_by_side
    from sparsetools.ops.viz import colorbar, label_panel

    half = (image.shape[1] // 2, image.shape[0] // 2)
    font = 0.6  # legible at half resolution

    def small(depth):
        # Nearest point of each 2x2 block (a min over the non-empty pixels): halving the
        # picture keeps every point.
        d = np.where(depth > 0, depth, np.inf).astype(np.float32)
        d = cv2.erode(d, np.ones((2, 2), np.uint8), anchor=(0, 0))[::2, ::2]
        return np.where(np.isfinite(d), d, 0).astype(np.float32)[: half[1], : half[0]]

    def nearest(depth):
        return cv2.resize(depth, half, interpolation=cv2.INTER_NEAREST)

    def stack(panels):
        out = side_by_side(panels, vertical=True)
        return side_by_side([out, colorbar(out.shape[1], max_depth=80.0)], vertical=True)

    rgb = cv2.resize(image, half, interpolation=cv2.INTER_AREA)
    panels = [
        label_panel(overlay_depth(rgb, small(single), dilate=1), text, scale=font)
        for text, single in (
            (f"frame 5: one scan, {np.mean(single > 0):.1%} of pixels", single),
            (f"frames 0-10 accumulated: {acc.density:.1%}", acc.depth),
        )
    ]
    panels.append(
        label_panel(colorize_depth(nearest(dense.depth)), "IP-Basic of the one scan", scale=font)
    )
    cv2.imwrite(str(IMG / "accumulate_kitti.png"), stack(panels)[:, :, ::-1])
    # Which frame each accumulated pixel came from.
    src = acc.source[::2, ::2][: half[1], : half[0]]
    colours = cv2.applyColorMap(
        np.where(src >= 0, (src * 25).astype(np.uint8), 0), cv2.COLORMAP_JET
    )[:, :, ::-1]
    view = (rgb * 0.45).astype(np.uint8)
    view[src >= 0] = colours[src >= 0]
    text = "source frame: blue 0, green 5, red 10"
    cv2.imwrite(
        str(IMG / "accumulate_sources.png"), label_panel(view, text, scale=font)[:, :, ::-1]
    )
    dense_panels = [
        label_panel(colorize_depth(nearest(d)), text, scale=font)
        for d, text in (
            (dense.depth, "IP-Basic of one scan"),
            (dense_acc.depth, "IP-Basic of the accumulated map"),
        )
    ]
    cv2.imwrite(str(IMG / "densify_kitti.png"), stack(dense_panels)[:, :, ::-1])
    print(f"wrote {IMG}/accumulate_kitti.png, accumulate_sources.png, densify_kitti.png")


if __name__ == "__main__":
    main()
