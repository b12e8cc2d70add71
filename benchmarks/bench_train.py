"""`sparsetools train` throughput at width 32 on 192x64 images: this tree against version 0.2.0.

Run: ``.venv/bin/python benchmarks/bench_train.py [--repeat 2] [--epochs 2]`` (4-8 minutes on
2 loaded cores). Issue 18's goal: >= 2x the samples/s of the code it was measured on.

1. A dataset as docs/train.md builds it: 2 street sequences of 20 frames at 192x64
   (``synth-scene``), a 16-beam LiDAR (``beams``, ``project``), ``dataset build`` with
   train/val/test = 0.5/0.25/0.25 (20 training and 20 validation samples here).
2. The reference is the package as committed in ``REFERENCE_COMMIT`` (version 0.2.0, before
   issue 18), extracted with ``git archive`` into a temporary folder; "ours" is this checkout.
   Both run the same command line in fresh processes, alternating (ours, reference, ours, ...)
   so that a change of the machine's load hits both alike::

       sparsetools train DS -o RUN --width 32 --batch-size 8 --epochs E --input rgbd [--threads N]

3. For the default thread count (no ``--threads``: 0.2.0 takes every core, this version the
   CPUs it may use, fixed per machine, ``sparsetools.train.runtime.default_threads``), and for 1 and 2 threads, it
   prints the medians of
   - end to end: training samples (samples x epochs) per second of the whole process (start,
     imports, data, training, validation, checkpoints, pictures), what a user waits for;
   - train phase: ``samples_per_s`` of the last epoch in metrics.csv (the training steps only);
   and the ratios ours / reference, with the machine's load. The last scenario repeats the
   default with one busy process beside the runs (one of the 2 cores taken).

GPU: ``--device cuda`` is not measured here (no GPU on this machine).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import load

ROOT = Path(__file__).resolve().parent.parent
#: Version 0.2.0, the code issue 18 measured (``git log``: "version 0.2.0: output records...").
REFERENCE_COMMIT = "716c998"
#: (thread setting, busy processes): None = the command's own default; busy = pure-Python
#: loops started beside the runs, one core each (issue 18's "busy machine": torch's one thread
#: per core then waits for the descheduled thread at every operation).
SCENARIOS = ((None, 0), (1, 0), (2, 0), (None, 1))
GOAL = 2.0


def cli(*args, env=None, capture=False) -> str:
    cmd = [sys.executable, "-m", "sparsetools.cli.main", "-q", *map(str, args)]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if r.returncode != 0:
        sys.exit(f"failed ({r.returncode}): {' '.join(cmd)}\n{r.stderr[-2000:]}")
    return r.stdout if capture else ""


def build_dataset(root: Path) -> Path:
    """docs/train.md's worked example with 2 sequences of 20 frames at 192x64."""
    ds = root / "ds16"
    if (ds / "manifest.parquet").is_file():
        return ds
    for s in range(2):
        seq = f"seq0{s}"
        scene = root / "scenes" / seq
        cli("synth-scene", "-o", scene, "--seed", s, "--frames", 20, "--image-size", "192x64",
            "--underwater-frames", 0)  # fmt: skip
        cli("beams", scene / "velodyne", "--n", 16, "-o", root / "beams16" / seq)
        cli("project", root / "beams16" / seq, "--calib", scene / "calib", "--image",
            scene / "image_2", "-o", root / "sparse16" / seq)  # fmt: skip
        shutil.rmtree(root / "sparse16" / seq / "calib", ignore_errors=True)
        shutil.copytree(scene / "image_2", root / "rgb" / seq)
        shutil.copytree(scene / "depth_gt", root / "gt" / seq)
    cli("dataset", "build", "-o", ds, "--rgb", root / "rgb", "--sparse", root / "sparse16",
        "--gt", root / "gt", "--splits", "train=0.5,val=0.25,test=0.25")  # fmt: skip
    return ds


def reference_tree(root: Path) -> Path | None:
    """``src`` of REFERENCE_COMMIT under ``root`` (None when git or the commit is missing)."""
    try:
        archive = subprocess.run(
            ["git", "-C", str(ROOT), "archive", REFERENCE_COMMIT, "src"],
            capture_output=True,
            check=True,
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(root)], input=archive, check=True)
    except (OSError, subprocess.CalledProcessError) as exc:
        print(f"no reference: git archive {REFERENCE_COMMIT} failed ({exc})")
        return None
    return root / "src"


def training_samples(ds: Path) -> int:
    import pyarrow.parquet as pq

    return (
        pq.read_table(ds / "manifest.parquet", columns=["split"])
        .column(0)
        .to_pylist()
        .count("train")
    )


def one_run(ds: Path, run: Path, *, src: Path, threads, epochs: int, width: int) -> dict:
    """Wall time and train-phase samples/s of one `sparsetools train` process."""
    shutil.rmtree(run, ignore_errors=True)
    env = {**os.environ, "PYTHONPATH": str(src)}  # before the checkout's own .pth entry
    args = ["train", ds, "-o", run, "--width", width, "--batch-size", 8, "--epochs", epochs,
            "--input", "rgbd", "--pictures", 3, "--json"]  # fmt: skip
    if threads is not None:
        args += ["--threads", threads]
    t0 = time.perf_counter()
    summary = json.loads(cli(*args, env=env, capture=True))
    wall = time.perf_counter() - t0
    with open(run / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    return {
        "wall": wall,
        "end_to_end": training_samples(ds) * len(rows) / wall,
        "train_phase": float(rows[-1]["samples_per_s"]),
        "threads": summary.get("threads"),
    }


def _alternate(trees: dict, ds: Path, tmp: Path, threads, args) -> list[tuple[str, dict]]:
    """``args.repeat`` runs of each tree, alternating (ours, reference, ours, ...)."""
    out = []
    for _ in range(args.repeat):
        for name, src in trees.items():
            run = one_run(
                ds,
                tmp / f"run_{name}",
                src=src,
                threads=threads,
                epochs=args.epochs,
                width=args.width,
            )
            out.append((name, run))
    return out


def main(argv=None) -> list[dict] | None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=2, help="runs of each (median)")
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--width", type=int, default=32)
    p.add_argument("--data", type=Path, help="keep the dataset here (reused when present)")
    p.add_argument("--busy-only", action="store_true", help="only the scenario with a busy core")
    p.add_argument("--ours", type=Path, default=ROOT / "src", help="the package tree to time")
    args, _ = p.parse_known_args(argv)
    print(
        f"train throughput, width {args.width}, 192x64, batch 8, {args.epochs} epoch(s); {load()}"
    )
    with tempfile.TemporaryDirectory(prefix="bench_train_") as tmp:
        tmp = Path(tmp)
        data_root = args.data or tmp / "data"
        data_root.mkdir(parents=True, exist_ok=True)
        ds = build_dataset(data_root)
        ref_src = reference_tree(tmp)
        if ref_src is None:
            return None
        trees = {"ours": args.ours, "ref": ref_src}
        results = []
        for threads, busy in SCENARIOS:
            if args.busy_only and not busy:
                continue
            got: dict[str, list[dict]] = {k: [] for k in trees}
            burners = [
                subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)
            ]
            try:
                pairs = _alternate(trees, ds, tmp, threads, args)
            finally:
                for b in burners:
                    b.kill()
                    b.wait()
            for name, r in pairs:
                got[name].append(r)
            med = {
                name: {
                    k: statistics.median(r[k] for r in runs)
                    for k in ("end_to_end", "train_phase", "wall")
                }
                for name, runs in got.items()
            }
            label = "default" if threads is None else f"{threads} thread(s)"
            label += f", {busy} busy" if busy else ""
            chosen = got["ours"][-1]["threads"]
            e2e = med["ours"]["end_to_end"] / med["ref"]["end_to_end"]
            phase = med["ours"]["train_phase"] / med["ref"]["train_phase"]
            verdict = f" (goal >= {GOAL:g}x: {'met' if e2e >= GOAL else 'NOT met'})"
            print(
                f"--threads {label:<11} ours {med['ours']['end_to_end']:5.2f} samples/s end to end"
                f" ({med['ours']['wall']:5.1f} s), {med['ours']['train_phase']:5.2f} train phase"
                f" | reference {med['ref']['end_to_end']:5.2f} ({med['ref']['wall']:5.1f} s),"
                f" {med['ref']['train_phase']:5.2f} | ratio {e2e:4.2f}x end to end{verdict},"
                f" {phase:4.2f}x train phase | ours used {chosen} thread(s) | {load()}",
                flush=True,
            )
            results.append(
                {"threads": threads, "busy": busy, "ratio_end_to_end": e2e, "ratio_train": phase}
            )
    return results


if __name__ == "__main__":
    main()
