"""A small probe of RNW's priors-based regularization (PBR): night self-supervised training
with and without PBR, and PBR without the coordinate input I_p, two seeds each.

Data: the datasets of ``benchmarks/acceptance_claims.py`` (its ``rnw_night`` claim makes them:
12 synthetic street videos x 20 frames at 208x64, split by sequence 8 / 2 / 2): the night
frames with 4-beam LiDAR (``dataset_night4``) to train on, and the day dataset
(``dataset_day4``) whose ground truth of the training split serves as PBR's reference depths
(the same streets by day: the most favourable reference there is, closer to the test frames
than RNW's day-model predictions on other day sequences).

Models (each ``sparsetools train --self-supervised --input rgb --mcie --sbm``, width 8, pose
width 16, batch 4, lr 1e-3 cosine, ``--epochs`` epochs, one torch thread, run one after the
other): ``night`` (no PBR), ``night_pbr`` (``--pbr DAY``), ``night_pbr_no_ip`` (``--pbr DAY
--no-pbr-coordinates``). Evaluation: ``sparsetools eval`` of ``best.pt`` on the night test
split, per-image median-scaled (camera-only models). One torch thread throughout
(``OMP_NUM_THREADS=1``); every run records the load average (``os.getloadavg``) at its start
and end.

Run::

    .venv/bin/python benchmarks/probe_pbr.py --data out/acceptance_claims --out out/probe_pbr
    .venv/bin/python benchmarks/probe_pbr.py --out out/probe_pbr --table   # the table only

Resumable: a finished run's result (``OUT/results/<model>_seed<k>.json``) is kept; all of them
go to ``benchmarks/results/probe_pbr.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
MODELS = {
    "night": (),
    "night_pbr": ("--pbr", "{day}"),
    "night_pbr_no_ip": ("--pbr", "{day}", "--no-pbr-coordinates"),
}
LABELS = {
    "night": "night, MCIE + SBM",
    "night_pbr": "+ PBR (xi 0.01)",
    "night_pbr_no_ip": "+ PBR without I_p",
}
METRICS = ("abs_rel", "sq_rel", "rmse", "delta1")
#: Every run's record, kept with the repository (docs/selfsup.md quotes it).
RECORD = REPO / "benchmarks" / "results" / "probe_pbr.json"


def sparsetools(*args) -> str:
    cmd = [sys.executable, "-m", "sparsetools.cli.main", "-q", *map(str, args)]
    print("$ sparsetools " + " ".join(map(str, args)), flush=True)
    # one torch thread, eval included (OMP_NUM_THREADS caps torch's default)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    res = subprocess.run(cmd, check=False, text=True, capture_output=True, env=env)
    if res.returncode != 0:
        sys.exit(f"command failed ({res.returncode}): {' '.join(cmd)}\n{res.stderr}")
    return res.stdout


def run_one(name: str, seed: int, night: Path, day: Path, out: Path, epochs: int) -> dict:
    done = out / "results" / f"{name}_seed{seed}.json"
    if done.is_file():
        return json.loads(done.read_text())
    run = out / "runs" / name / f"seed{seed}"
    load_start = os.getloadavg()
    t0 = time.perf_counter()
    options = [o.format(day=day) for o in MODELS[name]]
    sparsetools(
        "train", night, "-o", run, "--self-supervised", "--input", "rgb", "--mcie", "--sbm",
        "--width", 8, "--pose-width", 16, "--batch-size", 4, "--epochs", epochs, "--lr", 1e-3,
        "--lr-schedule", "cosine", "--seed", seed, "--pictures", 0, "--threads", 1, *options,
    )  # fmt: skip
    train_s = time.perf_counter() - t0
    res = json.loads(
        sparsetools("eval", "--checkpoint", run / "best.pt", night, "--split", "test", "--json")
    )
    record = {
        "model": name,
        "seed": seed,
        "epochs": epochs,
        "metrics": {k: res["metrics"][k] for k in METRICS},
        "median_scaling": res["median_scaling"],
        "seconds": round(time.perf_counter() - t0, 1),
        "train_seconds": round(train_s, 1),
        "load_start": [round(v, 2) for v in load_start],
        "load_end": [round(v, 2) for v in os.getloadavg()],
    }
    done.parent.mkdir(parents=True, exist_ok=True)
    done.write_text(json.dumps(record, indent=1))
    return record


def table(out: Path) -> str:
    lines = [
        "| model | seeds | AbsRel | Sq Rel (m) | RMSE (m) | δ<1.25 | Sq Rel vs PBR |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    records = {}
    for name in MODELS:
        records[name] = [
            json.loads(p.read_text()) for p in sorted((out / "results").glob(f"{name}_seed*.json"))
        ]
    pbr_sq = [r["metrics"]["sq_rel"] for r in records["night_pbr"]]
    for name, recs in records.items():
        if not recs:
            continue
        cells = []
        for k in METRICS:
            v = [r["metrics"][k] for r in recs]
            cells.append(f"{np.mean(v):.3f} ({min(v):.3f}-{max(v):.3f})")
        sq = np.mean([r["metrics"]["sq_rel"] for r in recs])
        rel = f"{100 * (sq / np.mean(pbr_sq) - 1):+.1f} %" if pbr_sq else ""
        lines.append(f"| {LABELS[name]} | {len(recs)} | " + " | ".join(cells) + f" | {rel} |")
    lines.append("")
    for name, recs in records.items():
        for r in recs:
            lines.append(
                f"- {name} seed {r['seed']}: {r['seconds']} s (train {r['train_seconds']} s), "
                f"load {r['load_start'][0]} at the start, {r['load_end'][0]} at the end"
            )
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--data", type=Path, default=REPO / "out" / "acceptance_claims")
    p.add_argument("--out", type=Path, default=REPO / "out" / "probe_pbr")
    p.add_argument("--seeds", default="0,1")
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--table", action="store_true", help="only print the table of the results")
    args = p.parse_args()
    if not args.table:
        night, day = args.data / "dataset_night4", args.data / "dataset_day4"
        for ds in (night, day):
            if not (ds / "manifest.parquet").is_file():
                sys.exit(
                    f"{ds} is missing: make the data with "
                    "`benchmarks/acceptance_claims.py --claims rnw_night` first"
                )
        records = [
            run_one(name, seed, night, day, args.out, args.epochs)
            for seed in map(int, args.seeds.split(","))
            for name in MODELS
        ]
        RECORD.parent.mkdir(parents=True, exist_ok=True)
        RECORD.write_text(json.dumps({"command": sys.argv, "runs": records}, indent=1) + "\n")
    print(table(args.out))


if __name__ == "__main__":
    main()
