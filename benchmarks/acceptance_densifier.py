"""Learned densifier (``densify --method learned``) vs IP-Basic on synthetic streets, and the
calibration of its uncertainty U. Not a test: a measurement for docs/densify.md.

Run (one torch and one OpenCV thread; about 3 minutes at the defaults on one core)::

    .venv/bin/python benchmarks/acceptance_densifier.py [--seeds 0,1] [--steps 300]
        [--train-frames 12] [--test-frames 3] [--corrupt 0] [--json out.json]

1. For each training seed: ``--train-frames`` street frames of the street of that seed
   (1242x375, :func:`~sparsetools.train.densifier_train.simulate_frames`), then
   :func:`~sparsetools.train.densifier_train.fit_densifier` with the command's defaults
   (``train-densifier --sim-frames 12 --steps 300 --threads 1 [--corrupt P]``).
2. Test frames from another street (seed 1000, never trained on), thinned to 64, 16 and 4
   beams as in training. Evaluated as benchmarks/bench_densify.py does: pixels with truth
   below 80 m, at or below the topmost 64-beam return of their column. RMSE and MAE in
   metres against the exact depth, on the pixels each method fills (its coverage beside it:
   IP-Basic leaves the holes wider than its kernels empty, the learned densifier fills every
   pixel) and on the pixels both fill.
3. Calibration of U: over every evaluated pixel of every beam count, the mean absolute error
   of ``D_c`` per bin of predicted sigma = exp(U / 2); a calibrated U gives MAE / sigma close
   to sqrt(2 / pi) = 0.80 in every bin.
4. The time of one 1242x375 frame (IP-Basic fill + network, one thread, median of 5) and the
   load average of the machine before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import median_seconds

TEST_SEED = 1000
BEAMS = (64, 16, 4)
MAX_DEPTH = 80.0
SIGMA_EDGES = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 1e3)


def _metrics(pred: np.ndarray, gt: np.ndarray, where: np.ndarray) -> dict:
    e = pred[where].astype(np.float64) - gt[where]
    return {"rmse": float(np.sqrt(np.mean(e * e))), "mae": float(np.mean(np.abs(e)))}


def evaluate(model, frames) -> tuple[dict, dict]:
    """Per beam count: learned / IP-Basic metrics (own pixels, common pixels), coverage; and
    the (pred, log_var, gt) of every evaluated pixel, for the calibration."""
    import torch

    from sparsetools.train.densifier import classical_base

    rows, calib = {}, {"pred": [], "log_var": [], "gt": []}
    for n in BEAMS:
        acc = {k: [] for k in ("learned", "ip-basic", "learned_common", "ip-basic_common")}
        cover = {"learned": [], "ip-basic": []}
        for f in frames:
            full = f.sparse[64]
            top = np.argmax(full > 0, axis=0)
            region = np.arange(full.shape[0])[:, None] >= top[None, :]
            gt = np.where(region, f.gt, 0)
            ev = (gt > 0) & (gt < MAX_DEPTH)
            sparse = f.sparse[n]
            ip = classical_base(sparse)
            with torch.inference_mode():
                d, u = model(torch.from_numpy(sparse)[None, None], torch.from_numpy(ip)[None, None])
            d, u = d[0, 0].numpy(), u[0, 0].numpy()
            common = ev & (ip > 0) & (d > 0)
            for name, pred in (("learned", d), ("ip-basic", ip)):
                own = ev & (pred > 0)
                acc[name].append(_metrics(pred, gt, own))
                acc[f"{name}_common"].append(_metrics(pred, gt, common))
                cover[name].append(own.sum() / ev.sum())
            calib["pred"].append(d[ev])
            calib["log_var"].append(u[ev])
            calib["gt"].append(gt[ev])
        rows[n] = {
            k: {m: float(np.mean([x[m] for x in v])) for m in ("rmse", "mae")}
            for k, v in acc.items()
        }
        rows[n]["coverage"] = {k: float(np.mean(v)) for k, v in cover.items()}
    return rows, {k: np.concatenate(v) for k, v in calib.items()}


def main() -> None:
    import cv2
    import torch

    from sparsetools.ops.uncertainty import calibration_bins
    from sparsetools.train.densifier_train import (
        DensifierTrainConfig,
        fit_densifier,
        simulate_frames,
    )

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1", help="training seeds (comma-separated)")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--train-frames", type=int, default=12)
    ap.add_argument("--test-frames", type=int, default=3)
    ap.add_argument("--corrupt", type=float, default=0.0, help="train-densifier --corrupt")
    ap.add_argument("--json", type=Path, help="also write the numbers here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    load_before = os.getloadavg()
    print(f"load average (1, 5, 15 min) before: {load_before}, {os.cpu_count()} CPUs")
    test = simulate_frames(TEST_SEED, args.test_frames, width=1242, height=375, beams=BEAMS)
    results, calib_all = {}, {"pred": [], "log_var": [], "gt": []}
    timing = None
    for seed in [int(s) for s in args.seeds.split(",")]:
        t0 = time.perf_counter()
        cfg = DensifierTrainConfig(steps=args.steps, sim_frames=args.train_frames, seed=seed,
                                   corrupt=args.corrupt, threads=1)  # fmt: skip
        frames = simulate_frames(seed, cfg.sim_frames, width=1242, height=375,
                                 beams=cfg.beam_counts)  # fmt: skip
        model, history = fit_densifier(cfg, frames)
        train_s = time.perf_counter() - t0
        rows, calib = evaluate(model, test)
        results[seed] = {"rows": rows, "train_seconds": train_s, "last": history[-1]}
        for k in calib_all:
            calib_all[k].append(calib[k])
        print(f"seed {seed}: trained in {train_s:.0f} s (last L1 {history[-1]['l1']:.2f} m)")
        if timing is None:
            from sparsetools.train.densifier import classical_base

            sparse = test[0].sparse[64]

            def once(sparse=sparse, model=model):
                base = torch.from_numpy(classical_base(sparse))[None, None]
                with torch.inference_mode():
                    model(torch.from_numpy(sparse)[None, None], base)

            timing = median_seconds(once, repeat=5)
    print(f"\none 1242x375 frame, IP-Basic fill + network, one thread: {timing:.3f} s")
    seeds = list(results)
    print(f"\nRMSE / MAE (m) vs exact depth, test street seed {TEST_SEED}, {args.test_frames} "
          f"frames; mean (min-max) over training seeds {seeds}")  # fmt: skip
    header = ("beams", "method", "coverage", "RMSE own", "MAE own", "RMSE common", "MAE common")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    table = []
    for n in BEAMS:
        for name in ("ip-basic", "learned"):
            vals = [results[s]["rows"][n] for s in seeds]

            def cell(key, metric, vals=vals):
                xs = [v[key][metric] for v in vals]
                return f"{np.mean(xs):.3f} ({min(xs):.3f}-{max(xs):.3f})"

            cov = np.mean([v["coverage"][name] for v in vals])
            line = [str(n), name, f"{cov:.1%}", cell(name, "rmse"), cell(name, "mae"),
                    cell(f"{name}_common", "rmse"), cell(f"{name}_common", "mae")]  # fmt: skip
            table.append(line)
            print("| " + " | ".join(line) + " |")
    bins = calibration_bins(
        np.concatenate(calib_all["pred"]),
        np.concatenate(calib_all["log_var"]),
        np.concatenate(calib_all["gt"]),
        edges=np.array(SIGMA_EDGES),
    )
    print("\ncalibration of U (all beam counts and seeds): MAE per bin of predicted sigma")
    print("| sigma bin (m) | pixels | mean sigma (m) | MAE (m) | RMSE (m) | MAE / sigma |")
    print("|---|---|---|---|---|---|")
    for r in bins.rows():
        if not r["count"]:
            continue
        print(f"| {r['low']:g}-{r['high']:g} | {r['count']} | {r['sigma']:.3f} | {r['mae']:.3f} "
              f"| {r['rmse']:.3f} | {r['mae_per_sigma']:.2f} |")  # fmt: skip
    load_after = os.getloadavg()
    print(f"\nload average (1, 5, 15 min) after: {load_after}")
    if args.json:
        args.json.write_text(json.dumps({
            "results": {str(k): v for k, v in results.items()}, "table": table,
            "calibration": bins.rows(), "seconds_per_frame": timing,
            "load_before": load_before, "load_after": load_after}, indent=1, default=str))  # fmt: skip


if __name__ == "__main__":
    main()
