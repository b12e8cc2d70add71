"""Acceptance run of `sparsetools train` / `eval` on a synthetic dataset (not part of `make test`).

What it checks (issue 8, METHODS.md section 6):

1. camera + LiDAR (rgbd) beats camera only (rgb) by a wide margin on RMSE and AbsRel
   (UltraDepth's finding);
2. with sparser LiDAR the model gets worse: 16 beams beat 4 beams beat 1 beam (EffisDepth
   Table 3's trend);
3. training is deterministic on CPU: two runs with the same seed give the same metrics.

Everything goes through the command line, as a user would run it::

    sparsetools synth-scene -o SCENES/seqS --seed S --frames F --image-size 192x64 --underwater-frames 0
    sparsetools beams SCENES/seqS/velodyne --n 1,4,16 -o BEAMS/seqS
    sparsetools project BEAMS/seqS/nN --calib SCENES/seqS/calib --image SCENES/seqS/image_2 \
        -o STAGE/sparseN/seqS
    sparsetools dataset build -o DS_N --rgb STAGE/rgb --sparse STAGE/sparseN --gt STAGE/gt \
        --splits train=0.67,val=0.16,test=0.17
    sparsetools train DS_N -o RUNS/<name> --input rgb|rgbd ...
    sparsetools eval --checkpoint RUNS/<name>/best.pt DS_N --split test --json

Run (about 15-25 minutes on 2 CPU cores)::

    .venv/bin/python benchmarks/acceptance_train.py --out out/acceptance_train [--docs]

``--docs`` also writes docs/img/train_curves.png, train_predictions.png and
train_compare.png. Existing scenes, datasets and finished runs under ``--out`` are reused.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
BEAMS = (1, 4, 16)


def sparsetools(*args, capture: bool = False) -> str:
    cmd = [sys.executable, "-m", "sparsetools.cli.main", "-q", *map(str, args)]
    print("$ sparsetools " + " ".join(map(str, args)), flush=True)
    res = subprocess.run(
        cmd,
        check=False,
        text=True,
        stdout=subprocess.PIPE if capture else subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    if res.returncode != 0:
        sys.exit(f"command failed ({res.returncode}): {' '.join(cmd)}\n{res.stderr}")
    return res.stdout if capture else ""


def link_tree(src: Path, dst: Path) -> None:
    """dst/<name> -> src/<name> symlinks for every file of src (flat)."""
    dst.mkdir(parents=True, exist_ok=True)
    for f in sorted(src.iterdir()):
        if f.is_file() and not (dst / f.name).exists():
            os.symlink(f.resolve(), dst / f.name)


def prepare(out: Path, args) -> dict[str, Path]:
    scenes, beams, stage = out / "scenes", out / "beams", out / "stage"
    w, h = args.size
    for s in range(args.sequences):
        seq = f"seq{s:02d}"
        scene = scenes / seq
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
                f"{w}x{h}",
                "--underwater-frames",
                0,
                "--overwrite",
            )
        if not all((beams / seq / f"n{n}").is_dir() for n in BEAMS):
            sparsetools(
                "beams", scene / "velodyne", "--n", ",".join(map(str, BEAMS)), "-o", beams / seq
            )
        link_tree(scene / "image_2", stage / "rgb" / seq)
        link_tree(scene / "depth_gt", stage / "gt" / seq)
        sources = {n: beams / seq / f"n{n}" for n in BEAMS} | {64: scene / "velodyne"}
        for n, cloud in sources.items():
            sparse = stage / f"sparse{n}" / seq
            if not sparse.is_dir() or len(list(sparse.glob("*.png"))) < args.frames:
                sparsetools(
                    "project",
                    cloud,
                    "--calib",
                    scene / "calib",
                    "--image",
                    scene / "image_2",
                    "-o",
                    sparse,
                )
            # the calibrations written beside the maps are not sparse depth
            shutil.rmtree(sparse / "calib", ignore_errors=True)
    datasets = {}
    for n in (*BEAMS, 64):
        ds = out / f"dataset_{n}beams"
        if not (ds / "manifest.parquet").is_file():
            sparsetools(
                "dataset",
                "build",
                "-o",
                ds,
                "--rgb",
                stage / "rgb",
                "--sparse",
                stage / f"sparse{n}",
                "--gt",
                stage / "gt",
                "--source",
                f"lidar-{n}beam",
                "--splits",
                args.split,
                "--seed",
                0,
                "--sparse-format",
                "png",
            )
        datasets[n] = ds
    return datasets


def split_ids(ds: Path, split: str) -> list[str]:
    import pyarrow.parquet as pq

    t = pq.read_table(ds / "manifest.parquet", columns=["id", "split"]).to_pylist()
    return sorted(r["id"] for r in t if r["split"] == split)


def train_and_eval(name: str, ds: Path, runs: Path, args, *, input_mode: str) -> dict:
    run = runs / name
    common = [
        "--width",
        args.width,
        "--batch-size",
        args.batch_size,
        "--epochs",
        args.epochs,
        "--lr",
        args.lr,
        "--loss",
        args.loss,
        "--seed",
        0,
        "--pictures",
        3,
        "--lr-schedule",
        "cosine",
        "--final-layer",
    ]
    if args.crop_size:
        common += ["--crop-size", args.crop_size]
    if not (run / "last.pt").is_file():
        sparsetools("train", ds, "-o", run, "--input", input_mode, *common)
    elif _epochs_done(run) < args.epochs:
        sparsetools("train", ds, "-o", run, "--resume", "--epochs", args.epochs)
    with open(run / "metrics.csv") as f:  # training time as logged, also for reused runs
        seconds = sum(float(r["seconds"]) for r in csv.DictReader(f))
    res = json.loads(
        sparsetools(
            "eval", "--checkpoint", run / "best.pt", ds, "--split", "test", "--json", capture=True
        )
    )
    return {
        "name": name,
        "input": input_mode,
        "dataset": ds.name,
        "seconds": round(seconds, 1),
        "run": str(run),
        **res["metrics"],
    }


def _epochs_done(run: Path) -> int:
    with open(run / "metrics.csv") as f:
        return sum(1 for r in csv.DictReader(f) if r["complete"] == "1")


def nearest_fill_reference(ds: Path) -> dict:
    """Test metrics of the LiDAR alone, holes filled with the nearest measured pixel."""
    from scipy import ndimage

    from sparsetools.io.dataset_reader import DatasetReader
    from sparsetools.ops.metrics import aggregate_metrics, depth_metrics

    test = DatasetReader(ds).split("test")
    per_image = []
    for i in range(len(test)):
        s = test.sample(i)
        sparse = s["sparse"]
        if not (sparse > 0).any():
            continue
        nearest = ndimage.distance_transform_edt(
            sparse == 0, return_distances=False, return_indices=True
        )
        per_image.append(depth_metrics(sparse[tuple(nearest)], s["gt"]))
    return aggregate_metrics(per_image)


def _metric_rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv") as f:
        return [
            {k: v for k, v in r.items() if k not in ("seconds", "samples_per_s", "run_id")}
            for r in csv.DictReader(f)
        ]


def table(rows: list[dict]) -> str:
    cols = [
        ("name", "model", "{}"),
        ("rmse", "RMSE m", "{:.3f}"),
        ("mae", "MAE m", "{:.3f}"),
        ("abs_rel", "AbsRel", "{:.4f}"),
        ("sq_rel", "SqRel m", "{:.3f}"),
        ("rmse_log", "RMSE log", "{:.4f}"),
        ("irmse", "iRMSE 1/km", "{:.2f}"),
        ("delta1", "δ<1.25", "{:.4f}"),
        ("delta2", "δ<1.25²", "{:.4f}"),
        ("delta3", "δ<1.25³", "{:.4f}"),
        ("seconds", "train s", "{:.0f}"),
    ]
    lines = [
        "| " + " | ".join(c[1] for c in cols) + " |",
        "|" + "|".join("---" if i == 0 else "---:" for i in range(len(cols))) + "|",
    ]
    for r in rows:
        lines.append("| " + " | ".join(fmt.format(r[k]) for k, _, fmt in cols) + " |")
    return "\n".join(lines)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    # maximum PNG compression: the docs pictures must stay small
    ok, buf = cv2.imencode(".png", rgb[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    path.write_bytes(buf.tobytes())


def docs_pictures(run: Path, dataset: Path, img: Path) -> None:
    """Curves of ``run`` and its predictions on two test frames (docs/img/train_*.png)."""
    import torch

    from sparsetools.io.dataset_reader import DatasetReader
    from sparsetools.train.checkpoint import load_checkpoint, model_from_checkpoint
    from sparsetools.train.model import model_inputs
    from sparsetools.train.plots import draw_curves, prediction_picture

    with open(run / "metrics.csv") as f:  # numbers only: the run id (0.3) is text
        history = [{k: float(v) for k, v in r.items() if k != "run_id"} for r in csv.DictReader(f)]
    _write_png(img / "train_curves.png", draw_curves(history, loss_name="l1"))
    model = model_from_checkpoint(load_checkpoint(run / "best.pt")).eval()
    test = DatasetReader(dataset).split("test")
    rows = []
    for i in (0, len(test) // 2):
        s = test.sample(i)
        rgb = torch.from_numpy(s["rgb"].transpose(2, 0, 1).copy()).float()[None] / 255
        sparse = torch.from_numpy(s["sparse"])[None, None]
        with torch.no_grad():
            pred = model(model_inputs(rgb, sparse, model.input_mode))[0, 0].numpy()
        rows.append((s["rgb"], s["sparse"], pred, s["gt"]))
    _write_png(img / "train_predictions.png", prediction_picture(rows))


def compare_picture(results: list[dict], datasets: dict[int, Path], out: Path) -> None:
    """rgb | rgb-only | 1 | 4 | 16 | 64 beams predictions | gt for two test frames."""
    import cv2
    import torch

    from sparsetools.io.dataset_reader import DatasetReader
    from sparsetools.ops.colormap import colorize_depth, side_by_side
    from sparsetools.train.checkpoint import load_checkpoint, model_from_checkpoint
    from sparsetools.train.model import model_inputs

    test = DatasetReader(datasets[16]).split("test")
    picks = [0, len(test) // 2]
    rows = []
    for i in picks:
        sid = test.row(i)["id"]
        panels = [test.sample(sid)["rgb"]]
        for r in results:
            ds_n = int(r["dataset"].split("_")[1].replace("beams", ""))
            s = DatasetReader(datasets[ds_n]).sample(sid)
            model = model_from_checkpoint(load_checkpoint(Path(r["run"]) / "best.pt")).eval()
            rgb = torch.from_numpy(s["rgb"].transpose(2, 0, 1).copy()).float()[None] / 255
            sparse = torch.from_numpy(s["sparse"])[None, None]
            with torch.no_grad():
                pred = model(model_inputs(rgb, sparse, model.input_mode))[0, 0].numpy()
            panels.append(colorize_depth(pred))
        panels.append(colorize_depth(test.sample(sid)["gt"]))
        rows.append(side_by_side(panels, vertical=False, gap=3))
    body = side_by_side(rows, vertical=True, gap=3)
    header = np.full((18, body.shape[1], 3), 255, np.uint8)
    w = test.sample(0)["rgb"].shape[1] + 3
    names = ["rgb", *[r["name"] for r in results], "ground truth"]
    for k, name in enumerate(names):
        cv2.putText(
            header, name, (k * w + 3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA
        )
    _write_png(out, np.concatenate([header, body], axis=0))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO / "out" / "acceptance_train")
    p.add_argument("--sequences", type=int, default=12)
    p.add_argument("--frames", type=int, default=25)
    p.add_argument(
        "--size",
        type=lambda s: tuple(int(v) for v in s.split("x")),
        default=(192, 64),
        help="image size WxH",
    )
    p.add_argument("--split", default="train=0.67,val=0.16,test=0.17")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--width", type=int, default=8)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--loss", default="l1")
    p.add_argument(
        "--crop-size", default="", help="training crop WxH, e.g. 320x96 (default: full images)"
    )
    p.add_argument("--no-repeat", action="store_true", help="skip the determinism re-run")
    p.add_argument("--docs", action="store_true", help="write the docs/img/train_*.png pictures")
    args = p.parse_args(argv)

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    datasets = prepare(out, args)
    prep_s = time.perf_counter() - t0
    test_ids = split_ids(datasets[16], "test")
    for n, ds in datasets.items():
        assert split_ids(ds, "test") == test_ids, f"test split differs for {n} beams"
    counts = {s: len(split_ids(datasets[16], s)) for s in ("train", "val", "test")}
    print(f"data ready in {prep_s:.0f} s: {counts}", flush=True)

    runs = out / "runs"
    results = [train_and_eval("rgb", datasets[16], runs, args, input_mode="rgb")]
    results[0]["name"] = "camera only"
    for n in (*BEAMS, 64):
        r = train_and_eval(f"rgbd_{n}beams", datasets[n], runs, args, input_mode="rgbd")
        r["name"] = f"camera + {n}-beam LiDAR"
        results.append(r)
    for r in results:
        print(
            f"{r['name']:<28} RMSE {r['rmse']:.3f} m  AbsRel {r['abs_rel']:.4f}  "
            f"delta1 {r['delta1']:.4f}  ({r['seconds']:.0f} s)",
            flush=True,
        )

    determinism = None
    if not args.no_repeat:
        # two identical 2-epoch runs (the full-length runs above are not repeated, for time)
        short = argparse.Namespace(**{**vars(args), "epochs": 2})
        pair = [
            train_and_eval(f"determinism_{k}", datasets[4], runs, short, input_mode="rgbd")
            for k in "ab"
        ]
        csvs = [_metric_rows(Path(r["run"])) for r in pair]
        determinism = csvs[0] == csvs[1] and all(
            pair[0][k] == pair[1][k] for k in ("rmse", "abs_rel", "delta1", "mae")
        )
        print(f"two runs with the same seed: identical metrics.csv and test metrics: {determinism}")

    fills = []
    for n in (*BEAMS, 64):
        ref = nearest_fill_reference(datasets[n])
        fills.append({"name": f"{n}-beam LiDAR alone, nearest fill", "seconds": 0.0, **ref})

    rgb, by_n = results[0], {int(r["dataset"].split("_")[1][:-5]): r for r in results[1:]}
    checks = {
        "rgbd (16 beams) RMSE < 0.5 x rgb RMSE": by_n[16]["rmse"] < 0.5 * rgb["rmse"],
        "rgbd (16 beams) AbsRel < 0.5 x rgb AbsRel": by_n[16]["abs_rel"] < 0.5 * rgb["abs_rel"],
        "RMSE: 16 beams < 4 beams < 1 beam": by_n[16]["rmse"] < by_n[4]["rmse"] < by_n[1]["rmse"],
        "AbsRel: 16 beams < 4 beams < 1 beam": by_n[16]["abs_rel"]
        < by_n[4]["abs_rel"]
        < by_n[1]["abs_rel"],
        "every LiDAR input beats camera only": all(r["rmse"] < rgb["rmse"] for r in by_n.values()),
    }
    if determinism is not None:
        checks["same seed, same metrics"] = determinism

    md = [
        f"Synthetic dataset: {args.sequences} sequences x {args.frames} frames, "
        f"{args.size[0]}x{args.size[1]} px; splits by sequence {counts}.",
        f"Training: --width {args.width} --batch-size {args.batch_size} --epochs {args.epochs} "
        f"--lr {args.lr} --loss {args.loss} --crop-size {args.crop_size or 'none'} --seed 0, "
        "2 CPU threads; "
        "test split, best.pt (lowest validation RMSE).",
        "",
        table(results),
        "",
        "Reference without learning (the LiDAR alone, every pixel given the depth of the "
        "nearest measured pixel):",
        "",
        table(fills),
        "",
    ]
    md += [f"- {'PASS' if ok else 'FAIL'}: {name}" for name, ok in checks.items()]
    report = "\n".join(md)
    (out / "results.md").write_text(report + "\n")
    (out / "results.json").write_text(
        json.dumps({"results": results, "nearest_fill": fills, "checks": checks}, indent=1) + "\n"
    )
    print(report)

    if args.docs:
        img = REPO / "docs" / "img"
        docs_pictures(runs / "rgbd_16beams", datasets[16], img)
        compare_picture(results, datasets, img / "train_compare.png")
        print(f"pictures written to {img}")
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
