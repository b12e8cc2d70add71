"""URL (``train --input rgbdu``) vs raw sparse input (``--input rgbd``) on synthetic streets:
the early-fusion U-Net fed the learned densifier's D_c and U, against the same network fed
the sparse LiDAR map. Not a test: a measurement for docs/train.md (issue 29 part 2).

Everything goes through the command line, one torch thread per command::

    sparsetools synth-scene -o SCENES/seqS --seed 100+S --frames F --image-size 192x64 \
        --underwater-frames 0
    sparsetools beams SCENES/seqS/velodyne --n N -o BEAMS/seqS
    sparsetools project BEAMS/seqS --calib SCENES/seqS/calib --image SCENES/seqS/image_2 \
        -o STAGE/sparse/seqS
    sparsetools dataset build -o DS --rgb STAGE/rgb --sparse STAGE/sparse --gt STAGE/gt \
        --splits train=0.5,val=0.25,test=0.25 --sparse-format png
    sparsetools train-densifier -o DENSIFIER --image-size 192x64 --tile-size 192x64 \
        --seed 7 --threads 1                       # another street than the dataset's
    sparsetools train DS -o RUNS/<name> --input rgbd|rgbdu [--url residual|gated \
        --densifier DENSIFIER] --width 8 --batch-size 4 --epochs 10 --lr 2e-3 \
        --lr-schedule cosine --seed K --threads 1 --pictures 0
    sparsetools eval --checkpoint RUNS/<name>/best.pt DS --split test --json

plus the densifier's D_c alone on the test split (no refinement), scored as ``eval`` scores.
Run (about 5 minutes of one core at the defaults)::

    .venv/bin/python benchmarks/acceptance_url.py --out out/acceptance_url [--seeds 0,1]
        [--beams 16] [--json benchmarks/results/acceptance_url.json]

Existing scenes, datasets, the densifier and finished runs under ``--out`` are reused.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
METRICS = ("rmse", "mae", "abs_rel", "delta1")
#: name -> extra ``train`` arguments (the densifier added where needed)
MODELS = {
    "rgbd": ["--input", "rgbd"],
    "rgbd + final layer": ["--input", "rgbd", "--final-layer"],
    "rgbdu residual": ["--input", "rgbdu", "--url", "residual"],
    "rgbdu gated": ["--input", "rgbdu", "--url", "gated"],
}


def sparsetools(*args, capture: bool = False) -> str:
    cmd = [sys.executable, "-m", "sparsetools.cli.main", "-q", *map(str, args)]
    print("$ sparsetools " + " ".join(map(str, args)), flush=True)
    res = subprocess.run(
        cmd,
        check=False,
        text=True,
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE if capture else subprocess.DEVNULL,
    )
    if res.returncode != 0:
        sys.exit(f"command failed ({res.returncode}): {' '.join(cmd)}\n{res.stderr}")
    return res.stdout if capture else ""


def load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def prepare(out: Path, args) -> Path:
    """The synthetic street dataset (``--beams`` LiDAR, 192x64) and its folders."""
    ds = out / f"dataset_{args.beams}beams"
    if (ds / "manifest.parquet").is_file():
        return ds
    stage = out / "stage"
    for s in range(args.sequences):
        seq, scene = f"seq{s:02d}", out / "scenes" / f"seq{s:02d}"
        if not (scene / "scene.json").is_file():
            sparsetools(
                "synth-scene",
                "-o",
                scene,
                "--seed",
                100 + s,
                "--frames",
                args.frames,
                "--image-size",
                "192x64",
                "--underwater-frames",
                0,
                "--overwrite",
            )
        cloud = scene / "velodyne"
        if args.beams != 64:
            thinned = out / "beams" / seq  # one count: the scans straight in the folder
            if not thinned.is_dir():
                sparsetools("beams", cloud, "--n", args.beams, "-o", thinned)
            cloud = thinned
        sparse = stage / "sparse" / seq
        sparsetools(
            "project", cloud, "--calib", scene / "calib", "--image", scene / "image_2", "-o", sparse
        )
        shutil.rmtree(sparse / "calib", ignore_errors=True)  # not depth maps
        for name, src in (("rgb", "image_2"), ("gt", "depth_gt")):
            shutil.copytree(scene / src, stage / name / seq, dirs_exist_ok=True)
    sparsetools(
        "dataset",
        "build",
        "-o",
        ds,
        "--rgb",
        stage / "rgb",
        "--sparse",
        stage / "sparse",
        "--gt",
        stage / "gt",
        "--source",
        f"lidar-{args.beams}beam",
        "--splits",
        "train=0.5,val=0.25,test=0.25",
        "--seed",
        0,
        "--sparse-format",
        "png",
    )
    return ds


def densifier_alone(ds: Path, densifier: Path) -> dict:
    """Test metrics of D_c itself, per image then averaged (``eval``'s protocol)."""
    from sparsetools.ops.metrics import aggregate_metrics, depth_metrics
    from sparsetools.train.data import DepthDataset
    from sparsetools.train.densifier import LearnedDensifier

    dn = LearnedDensifier(densifier)
    data = DepthDataset(ds, "test")
    rows = []
    for i in range(len(data)):
        item = data[i]
        coarse, _ = dn.densify(item["sparse"][0].numpy())
        rows.append(depth_metrics(coarse, item["gt"][0].numpy(), max_depth=80.0))
    return aggregate_metrics(rows)


def train_and_eval(ds: Path, run: Path, extra: list, densifier: Path, seed: int, args) -> dict:
    if extra[1] == "rgbdu":
        extra = [*extra, "--densifier", densifier]
    if not (run / "best.pt").is_file():
        t0 = time.perf_counter()
        sparsetools(
            "train",
            ds,
            "-o",
            run,
            *extra,
            "--width",
            8,
            "--batch-size",
            4,
            "--epochs",
            args.epochs,
            "--lr",
            2e-3,
            "--lr-schedule",
            "cosine",
            "--seed",
            seed,
            "--threads",
            1,
            "--pictures",
            0,
        )
        print(f"  trained in {time.perf_counter() - t0:.1f} s, load {load()}", flush=True)
    res = json.loads(
        sparsetools(
            "eval", "--checkpoint", run / "best.pt", ds, "--split", "test", "--json", capture=True
        )
    )
    return {k: res["metrics"][k] for k in METRICS}


def summary(values: list[float]) -> str:
    return f"{np.mean(values):.3f} ({min(values):.3f}-{max(values):.3f})"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO / "out" / "acceptance_url")
    p.add_argument("--seeds", default="0,1")
    p.add_argument("--beams", type=int, default=16)
    p.add_argument("--sequences", type=int, default=4)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    started, load_before = time.perf_counter(), load()

    ds = prepare(args.out, args)
    densifier = args.out / "densifier"
    if not (densifier / "densifier.pt").is_file():
        t0 = time.perf_counter()
        sparsetools(
            "train-densifier",
            "-o",
            densifier,
            "--image-size",
            "192x64",
            "--tile-size",
            "192x64",
            "--seed",
            7,
            "--threads",
            1,
            "--overwrite",
        )
        print(f"  densifier trained in {time.perf_counter() - t0:.1f} s", flush=True)
    results = {"densifier D_c alone": [densifier_alone(ds, densifier)]}
    for name, extra in MODELS.items():
        results[name] = [
            train_and_eval(
                ds,
                args.out / "runs" / f"{name.replace(' ', '_')}_s{seed}",
                extra,
                densifier,
                seed,
                args,
            )
            for seed in seeds
        ]
    print(f"\n{args.beams} beams, test split, seeds {args.seeds}: mean (min-max)")
    print("| model | " + " | ".join(METRICS) + " |")
    for name, rows in results.items():
        cells = [summary([r[k] for r in rows]) for k in METRICS]
        print(f"| {name} | " + " | ".join(cells) + " |")
    base = np.mean([r["mae"] for r in results["rgbd"]])
    for name in ("rgbdu residual", "rgbdu gated"):
        gain = 100 * (1 - np.mean([r["mae"] for r in results[name]]) / base)
        print(f"MAE of {name} vs rgbd: {gain:+.1f} % (the survey: about +25 % with SpaDe)")
    seconds, load_after = round(time.perf_counter() - started, 1), load()
    print(f"{seconds} s; load average before {load_before}, after {load_after}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        record = {
            "command": " ".join(["benchmarks/acceptance_url.py", *(argv or sys.argv[1:])]),
            "seconds": seconds,
            "load_before": load_before,
            "load_after": load_after,
            "results": results,
        }
        args.json.write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
