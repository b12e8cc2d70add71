"""EffisDepth's ablations (Tables 2 and 3) on synthetic street videos (issue 15; not a test).

The same videos and datasets as the self-supervised acceptance run (data preparation:
benchmarks/_selfsup_data.py, all through the command line), one schedule for every row, then
`sparsetools eval --checkpoint RUN/best.pt DS --split test` on the test sequences:

Table 2 (4-beam LiDAR):

- M: camera only, self-supervised (evaluated with per-image median scaling);
- M + sparse loss: + EffisDepth's SILog sparse loss on the 4-beam points (unscaled from here on);
- M + L, SFE in depth: + ``--lidar-encoder sfe`` (the U-Net takes the image alone);
- M + L, SFE in depth and pose: + ``--pose-lidar-encoder sfe``.

Table 3: the last configuration with 1, 2, 3, 4 and 16 beams (``sparsetools beams --n``).

Every number is printed as measured, the paper's beside it (KITTI Eigen, 640x192, ResNet-50
from ImageNet, 20 epochs of 39,810 frames: a reference, not a target). Prints the machine load
and the wall time; ``--jobs 2`` (default) trains two rows at a time with one torch thread each
(the results do not depend on the thread count). Existing videos, datasets and finished runs
under ``--out`` are reused.

    .venv/bin/python benchmarks/acceptance_sfe.py --out out/acceptance_sfe
    .venv/bin/python benchmarks/acceptance_sfe.py --out out/acc_sfe_tiny --tiny   # a few minutes
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

from _selfsup_data import VideoSettings, prepare_datasets, sparsetools

REPO = Path(__file__).resolve().parent.parent
BEAMS = (1, 2, 3, 4, 16)

#: EffisDepth Table 2 (AbsRel, KITTI Eigen) and Table 3 (SFE in both networks, per beam count).
PAPER_TABLE2 = {"m": 0.110, "m_sparse": 0.105, "sfe_depth": 0.076, "sfe_both": 0.073}
PAPER_TABLE3 = {1: 0.091, 2: 0.087, 3: 0.084, 4: 0.073, 16: 0.064}
#: monodepth2 (M) in EffisDepth's Table 1 and METHODS.md section 8.
MONODEPTH2_ABS_REL = 0.115


@dataclass(frozen=True)
class Row:
    """One training run: its name, label, dataset key and the options that set it apart."""

    name: str
    label: str
    dataset: str
    options: tuple
    paper: float


SPARSE = ("--sparse-loss", "silog")
SFE_DEPTH = ("--lidar-encoder", "sfe")
SFE_POSE = ("--pose-lidar-encoder", "sfe")
TABLE2 = (
    Row("m", "M (camera only, median-scaled)", "n4", (), PAPER_TABLE2["m"]),
    Row("m_sparse", "M + sparse loss", "n4", SPARSE, PAPER_TABLE2["m_sparse"]),
    Row("sfe_depth", "M + L, SFE in depth", "n4", SPARSE + SFE_DEPTH, PAPER_TABLE2["sfe_depth"]),
    Row(
        "sfe_both",
        "M + L, SFE in depth and pose",
        "n4",
        SPARSE + SFE_DEPTH + SFE_POSE,
        PAPER_TABLE2["sfe_both"],
    ),
)
TABLE3 = tuple(
    Row(
        "sfe_both" if n == 4 else f"sfe_both_n{n}",
        f"{n}-beam",
        f"n{n}",
        SPARSE + SFE_DEPTH + SFE_POSE,
        PAPER_TABLE3[n],
    )
    for n in BEAMS
)


def schedule(args) -> list:
    """The options every row shares."""
    return [
        "--self-supervised", "--input", "rgb", "--width", args.width,
        "--pose-width", args.pose_width, "--batch-size", args.batch_size,
        "--epochs", args.epochs, "--lr", args.lr, "--lr-schedule", "cosine", "--seed", 0,
        "--pictures", 1, "--threads", args.threads,
    ]  # fmt: skip


def _epochs_done(run: Path) -> int:
    with open(run / "metrics.csv") as f:
        return sum(1 for r in csv.DictReader(f) if r["complete"] == "1")


def train_and_eval(row: Row, ds: Path, runs: Path, args) -> dict:
    run = runs / row.name
    started = time.perf_counter()
    if not (run / "last.pt").is_file():
        sparsetools("train", ds, "-o", run, *schedule(args), *row.options)
    elif _epochs_done(run) < args.epochs:
        sparsetools("train", ds, "-o", run, "--resume", "--epochs", args.epochs)
    with open(run / "metrics.csv") as f:
        history = list(csv.DictReader(f))
    res = json.loads(
        sparsetools(
            "eval", "--checkpoint", run / "best.pt", ds, "--split", "test", "--json", capture=True
        )
    )
    pose = res.get("pose") or {}
    params = _parameters(run / "best.pt")
    return {
        "name": row.name,
        "label": row.label,
        "paper": row.paper,
        "lidar_encoder": res.get("lidar_encoder", "none"),
        "median_scaling": res["median_scaling"],
        "ate": pose.get("ate_mean", float("nan")),
        "steps": int(history[-1]["step"]),
        "best_epoch": _best_epoch(history),
        "seconds": sum(float(r["seconds"]) for r in history),
        "wall": time.perf_counter() - started,
        "load": os.getloadavg()[0],
        "density": _density(ds, "test"),
        **params,
        **res["metrics"],
    }


def _parameters(checkpoint: Path) -> dict:
    """Trainable parameters of the depth and pose networks (BN statistics excluded)."""
    from sparsetools.train.checkpoint import (
        load_checkpoint,
        model_from_checkpoint,
        pose_from_checkpoint,
    )
    from sparsetools.train.sfe import count_parameters

    ckpt = load_checkpoint(checkpoint)
    depth, pose = model_from_checkpoint(ckpt), pose_from_checkpoint(ckpt)
    lidar = sum(count_parameters(m.lidar_branch) for m in (depth, pose) if m.lidar_branch)
    return {
        "params_depth": count_parameters(depth),
        "params_pose": count_parameters(pose),
        "params_lidar": lidar,
    }


def _density(ds: Path, split: str) -> float:
    """Mean share of valid sparse-depth pixels over a split (the manifest's density column)."""
    import pyarrow.parquet as pq

    rows = pq.read_table(ds / "manifest.parquet", columns=["split", "density"]).to_pylist()
    values = [r["density"] for r in rows if r["split"] == split]
    return sum(values) / len(values)


def _best_epoch(history: list[dict]) -> int:
    best = min(history, key=lambda r: float(r["rmse"]))
    return int(best["epoch"])


# -- report -----------------------------------------------------------------------------------------
def _change(value: float, base: float) -> str:
    return f"{100 * (value - base) / base:+.1f} %"


def _params(r: dict) -> int:
    return r["params_depth"] + r["params_pose"]


def table2(results: dict[str, dict]) -> str:
    base, m = results["m"]["abs_rel"], results["m"]
    lines = [
        "| model | params (depth + pose) | growth | AbsRel | vs M | RMSE m | δ<1.25 | ATE m "
        "| train s | paper AbsRel | paper vs M |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in TABLE2:
        r = results[row.name]
        lines.append(
            f"| {row.label} | {r['params_depth']:,} + {r['params_pose']:,} | "
            f"{_change(_params(r), _params(m))} | {r['abs_rel']:.3f} | "
            f"{_change(r['abs_rel'], base)} | {r['rmse']:.2f} | {r['delta1']:.3f} | "
            f"{r['ate']:.3f} | {r['seconds']:.0f} | {row.paper:.3f} | "
            f"{_change(row.paper, PAPER_TABLE2['m'])} |"
        )
    return "\n".join(lines)


def table3(results: dict[str, dict]) -> str:
    head = "| SFE in depth and pose | " + " | ".join(f"{n}-beam" for n in BEAMS) + " |"
    lines = [head, "|---|" + "---:|" * len(BEAMS)]
    rows = [results[r.name] for r in TABLE3]
    lines.append(
        "| valid pixels (test) | " + " | ".join(f"{100 * r['density']:.1f} %" for r in rows) + " |"
    )
    lines.append("| AbsRel (measured) | " + " | ".join(f"{r['abs_rel']:.3f}" for r in rows) + " |")
    lines.append("| RMSE m (measured) | " + " | ".join(f"{r['rmse']:.2f}" for r in rows) + " |")
    lines.append("| δ<1.25 (measured) | " + " | ".join(f"{r['delta1']:.3f}" for r in rows) + " |")
    lines.append("| AbsRel (paper) | " + " | ".join(f"{r.paper:.3f}" for r in TABLE3) + " |")
    return "\n".join(lines)


def checks(results: dict[str, dict]) -> list[tuple[bool, str]]:
    r = {k: v["abs_rel"] for k, v in results.items()}
    n = {b: r[row.name] for b, row in zip(BEAMS, TABLE3, strict=True)}
    return [
        (r["m_sparse"] < r["m"], "Table 2: + sparse loss < M"),
        (r["sfe_depth"] < r["m_sparse"], "Table 2: SFE in depth < sparse loss alone"),
        (r["sfe_both"] < r["sfe_depth"], "Table 2: SFE in depth and pose < SFE in depth"),
        (
            all(n[a] > n[b] for a, b in pairwise(BEAMS)),
            "Table 3: AbsRel falls with every added beam (1 > 2 > 3 > 4 > 16)",
        ),
        (n[16] < n[1], "Table 3: 16 beams < 1 beam"),
        (
            results["m"]["median_scaling"] and not results["m_sparse"]["median_scaling"],
            "protocol: median scaling only for the camera-only model",
        ),
    ]


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--out", type=Path, default=REPO / "out" / "acceptance_sfe")
    p.add_argument("--tiny", action="store_true", help="development size: a few minutes")
    p.add_argument("--jobs", type=int, default=2, help="rows trained at a time")
    p.add_argument("--only", nargs="*", default=None, help="train only these rows")
    dev = p.add_argument_group("development (the acceptance uses the defaults)")
    dev.add_argument("--sequences", type=int, default=None)
    dev.add_argument("--frames", type=int, default=None)
    dev.add_argument("--epochs", type=int, default=None)
    args = p.parse_args()
    if args.tiny:
        size, sequences, frames, epochs = (96, 32), 4, 6, 1
        split = "train=0.5,val=0.25,test=0.25"
    else:
        size, sequences, frames, epochs = (208, 64), 20, 30, 4
        split = "train=0.67,val=0.16,test=0.17"
    sequences = args.sequences or sequences
    frames = args.frames or frames
    args.epochs = args.epochs or epochs
    args.width, args.pose_width, args.batch_size, args.lr = 8, 16, 4, 1e-3
    args.threads = 1 if args.jobs > 1 else 2
    started = time.perf_counter()
    load0 = os.getloadavg()
    print(f"machine load (1, 5, 15 min): {load0}", flush=True)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    settings = VideoSettings(size, sequences, frames, split, workers=2, beams=BEAMS)
    datasets = prepare_datasets(out, settings, {f"n{n}": ("rgb", n) for n in BEAMS})
    t_data = time.perf_counter() - started
    print(f"data {t_data:.0f} s; machine load {os.getloadavg()}", flush=True)

    rows = {r.name: r for r in (*TABLE2, *TABLE3)}
    if args.only:
        rows = {k: v for k, v in rows.items() if k in args.only}
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = {
            name: pool.submit(train_and_eval, row, datasets[row.dataset], out / "runs", args)
            for name, row in rows.items()
        }
        results = {name: f.result() for name, f in futures.items()}
    (out / "results.json").write_text(json.dumps(results, indent=1))

    print("\nSchedule (every row): " + " ".join(map(str, schedule(args))))
    steps = sorted({r["steps"] for r in results.values()})
    print(f"steps per row: {steps}; image size {size[0]}x{size[1]}")
    if all(r.name in results for r in TABLE2):
        print("\nTable 2 (4-beam LiDAR; test split, best.pt)\n")
        print(table2(results))
    if all(r.name in results for r in TABLE3):
        print("\nTable 3 (SFE in depth and pose)\n")
        print(table3(results))
    print("\nper row: wall s (train + eval, with --jobs rows at a time), 1-min load at the end")
    for r in results.values():
        print(f"  {r['name']:<14} {r['wall']:7.0f} s  load {r['load']:.1f}")
    if len(results) == len(rows) and not args.only:
        print()
        for ok, text in checks(results):
            print(f"- {'PASS' if ok else 'FAIL'}: {text}")
    wall = time.perf_counter() - started
    print(f"\ndata {t_data:.0f} s; wall time {wall:.0f} s ({wall / 60:.1f} min)")
    print(f"machine load (1, 5, 15 min): at the start {load0}, at the end {os.getloadavg()}")


if __name__ == "__main__":
    main()
