"""One acceptance protocol for the papers' claims on the bundled training (issue 24; not part of
`make test`).

Every claim is a set of models trained on the same synthetic street videos, each with at least
two seeds; every number is reported as the mean over the seeds with its range (min-max), with
the paper's number beside it, and every ordering the paper reports is checked IN THE MEAN and
marked reproduced or not. Everything goes through the command line, as a user runs it (data:
benchmarks/_selfsup_data.py):

    sparsetools synth-scene -o VIDEOS --video --sequences 12 --frames 20 --image-size 208x64
    sparsetools beams VIDEOS/<seq>/velodyne --n 1,2,3,4,16 -o BEAMS/<seq>
    (every 10th azimuth step of the scans kept: the density of EffisDepth's maps, see below)
    sparsetools project THIN/<seq>/n<N> --calib ... --image ... -o SPARSE<N>/<seq>
    sparsetools dataset build -o DS<N> ...
    sparsetools train DS<N> -o RUNS/<model>/seed<k> --self-supervised ... --seed k --threads 1
    sparsetools eval --checkpoint RUNS/<model>/seed<k>/best.pt DS<N> --split test --json
        (twice: --scaling auto, and --scaling median)

Sparsity. At 208x64 one laser covers about one image row and the synthetic LiDAR has 2,000
azimuth steps per turn (0.18 deg, ~2 steps per image column), so 4 beams fill ~6 % of the
pixels; EffisDepth's 4-beam maps at 640x192 fill ~1.3 %. Keeping every 10th azimuth step of
the scans (a sensor with 1.8 deg horizontal resolution) gives EffisDepth's densities at a
CPU-feasible size: the run prints the measured density per beam count.

Claims (``--claims``, default all that are implemented):

- ``effisdepth_t2``: EffisDepth Table 2, AbsRel M (0.110) > M+L (0.105) > M+L+SFE in depth
  (0.076), metric and median-scaled; with the probes of issue 24: M+L with monodepth2's pose
  translation scale 0.01 (the constant before the fix), and the SFE fused at full resolution
  too (the layout before the fix), with LiDAR dropout, with disjoint point sets (holdout), and
  M+L with the 4 beams unthinned (5x the density).
- ``effisdepth_t3``: EffisDepth Table 3, AbsRel falls with beams 1 -> 2 -> 3 -> 4 -> 16
  (0.091, 0.087, 0.084, 0.073, 0.064), with the M+L+SFE model.
- ``rnw_night``: RNW night, camera only vs + MCIE + SBM (median-scaled).
- ``ultradepth_t2``: UltraDepth Table 2, supervised early fusion rgb (RMSE 3.59) vs rgbd (1.21,
  -66 %) vs rgbdm (1.44) with 64 beams, and with 16, on the same videos' FULL scans (not
  thinned: UltraDepth uses KITTI's own LiDAR); evaluated on the dense GT and on KITTI-like GT
  (the dense GT at the pixels a 64-beam scan hits, inside the Garg crop); probes: camera only
  and rgbd with 4x the epochs.
- ``radar_t2``: the radar paper's Tables 2 and 6 in miniature: the same supervised model with
  raw radar (5 sweeps), height-extended radar, JBF radar (sigma_s 25, sigma_r 10, threshold
  0.05) and JBF radar + confidence (``--input rgbdc``), on single-frame synthetic streets
  (``synth-scene --frames``, which writes nuScenes-format radar) at 416x128, evaluated on the
  projected 64-beam LiDAR (METHODS.md section 12 has the paper's figures); probes: camera only
  on the same frames, and camera only and JBF with 4x the epochs.

Runs are resumable (finished runs and evaluations are kept under ``--out``); two run at a time
with one torch thread each (CPU results do not depend on it beyond the thread count, which is
fixed). The results (every model x seed) go to ``benchmarks/results/acceptance_claims.json``
with the command that made them; ``--tables`` prints the Markdown tables of the docs from that
file alone.

    .venv/bin/python benchmarks/acceptance_claims.py --out out/claims
    .venv/bin/python benchmarks/acceptance_claims.py --out out/claims --claims effisdepth_t2
    .venv/bin/python benchmarks/acceptance_claims.py --tables
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from _selfsup_data import VideoSettings, prepare_datasets, sparsetools

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results" / "acceptance_claims.json"
BEAMS = (1, 2, 3, 4, 16)
#: keep every K-th of the synthetic LiDAR's 2,000 azimuth steps (module docstring)
AZIMUTH_KEEP = 10


@dataclass(frozen=True)
class Model:
    name: str
    label: str
    dataset: str
    options: tuple
    paper: float | None = None  # the paper's AbsRel (KITTI Eigen, 640x192; radar: nuScenes)
    supervised: bool = False
    paper_rmse: float | None = None
    #: other datasets (same frames and splits, other ground truth) to evaluate on: key -> flags
    also: tuple = ()
    #: epochs when not the claim's default (a probe of under-training)
    epochs: int | None = None


SFE = ("--input", "rgb", "--lidar-encoder", "sfe", "--sparse-loss", "silog")
CLAIMS: dict[str, tuple[Model, ...]] = {
    "effisdepth_t2": (
        Model("M", "M (camera only)", "day4", ("--input", "rgb"), 0.110),
        Model(
            "ML", "M+L (sparse loss)", "day4", ("--input", "rgb", "--sparse-loss", "silog"), 0.105
        ),
        Model("MLS", "M+L+SFE (depth)", "day4", SFE, 0.076),
        Model(
            "ML_pose001",
            "probe: M+L, pose translation x0.01 (before the fix)",
            "day4",
            ("--input", "rgb", "--sparse-loss", "silog", "--pose-translation-scale", "0.01"),
        ),
        Model(
            "MLS_full",
            "probe: M+L+SFE fused at 1..1/16 (before the fix)",
            "day4",
            (*SFE, "--lidar-scales", "1,2,4,8,16"),
        ),
        Model(
            "MLS_drop",
            "probe: M+L+SFE, LiDAR dropout 0.5",
            "day4",
            (*SFE, "--lidar-dropout", "0.5"),
        ),
        Model("MLS_hold", "probe: M+L+SFE, holdout 0.5", "day4", (*SFE, "--lidar-holdout", "0.5")),
        Model(
            "ML_full4",
            "probe: M+L, 4 beams at full azimuth resolution (5x the density)",
            "full4",
            ("--input", "rgb", "--sparse-loss", "silog"),
        ),
    ),
    "effisdepth_t3": tuple(
        # 4 beams is Table 2's M+L+SFE run (the same model on the same data)
        Model(
            "MLS" if n == 4 else f"MLS_b{n}",
            f"M+L+SFE, {n} beam{'s' if n > 1 else ''}",
            f"day{n}",
            SFE,
            paper,
        )
        for n, paper in zip(BEAMS, (0.091, 0.087, 0.084, 0.073, 0.064), strict=True)
    ),
    "rnw_night": (
        Model("night_M", "night, camera only", "night4", ("--input", "rgb")),
        Model(
            "night_MCIE_SBM", "night, + MCIE + SBM", "night4", ("--input", "rgb", "--mcie", "--sbm")
        ),
    ),
}
KITTI_GT = (("kitti_gt", ("--garg-crop",)),)
CLAIMS["ultradepth_t2"] = (
    *(
        Model(
            name,
            label,
            ds,
            ("--input", mode),
            paper,
            supervised=True,
            paper_rmse=rmse,
            also=KITTI_GT,
        )
        for name, label, ds, mode, paper, rmse in (
            ("U_rgb", "camera only (rgb)", "full64", "rgb", 0.113, 3.59),
            ("U_rgbd64", "rgbd, 64 beams", "full64", "rgbd", 0.0445, 1.21),
            ("U_rgbdm64", "rgbdm, 64 beams", "full64", "rgbdm", 0.0422, 1.44),
            ("U_rgbd16", "rgbd, 16 beams", "full16", "rgbd", None, None),
            ("U_rgbdm16", "rgbdm, 16 beams", "full16", "rgbdm", None, None),
        )
    ),
    *(
        Model(
            name,
            f"probe: {label}, 32 epochs (4x)",
            "full64",
            ("--input", mode),
            supervised=True,
            also=KITTI_GT,
            epochs=32,
        )
        for name, mode, label in (
            ("U_rgb_e32", "rgb", "camera only"),
            ("U_rgbd64_e32", "rgbd", "rgbd, 64 beams"),
        )
    ),
)
CLAIMS["radar_t2"] = tuple(
    Model(name, label, ds, ("--input", mode), paper, supervised=True, paper_rmse=rmse)
    for name, label, ds, mode, paper, rmse in (
        ("R_raw", "raw radar (S2D: 0.115)", "radar_raw", "rgbd", 0.115, 5.628),
        ("R_he", "height-extended (DORNradar: 0.109)", "radar_he", "rgbd", 0.109, 5.191),
        ("R_jbf", "JBF (DORNradar: 0.104)", "radar_jbf", "rgbd", 0.104, 5.228),
        ("R_jbfc", "JBF + confidence (RCDPT: 0.087)", "radar_jbf", "rgbdc", 0.087, 4.735),
        ("R_rgb", "probe: camera only, same frames", "radar_raw", "rgb", None, None),
    )
) + tuple(
    Model(name, label, ds, ("--input", mode), supervised=True, epochs=32)
    for name, label, ds, mode in (
        ("R_rgb_e32", "probe: camera only, 32 epochs (4x)", "radar_raw", "rgb"),
        ("R_jbf_e32", "probe: JBF, 32 epochs (4x)", "radar_jbf", "rgbd"),
    )
)
#: orderings the papers report: (claim, better model, worse model, metric, scaled?)
ORDERINGS = (
    ("effisdepth_t2", "ML", "M", "abs_rel", True),
    ("effisdepth_t2", "MLS", "ML", "abs_rel", False),
    ("effisdepth_t2", "MLS", "ML", "abs_rel", True),
    ("effisdepth_t2", "ML", "M", "abs_rel_metric_vs_scaled", None),
    ("effisdepth_t3", "MLS_b2", "MLS_b1", "abs_rel", False),
    ("effisdepth_t3", "MLS_b3", "MLS_b2", "abs_rel", False),
    ("effisdepth_t3", "MLS", "MLS_b3", "abs_rel", False),
    ("effisdepth_t3", "MLS_b16", "MLS", "abs_rel", False),
    ("rnw_night", "night_MCIE_SBM", "night_M", "abs_rel", True),
    ("ultradepth_t2", "U_rgbd64", "U_rgb", "rmse", False),
    ("ultradepth_t2", "U_rgbd64", "U_rgb", "rmse@kitti_gt", False),
    ("ultradepth_t2", "U_rgbdm64", "U_rgb", "rmse", False),
    ("ultradepth_t2", "U_rgbd64", "U_rgbdm64", "rmse", False),
    ("ultradepth_t2", "U_rgbd16", "U_rgb", "rmse", False),
    ("radar_t2", "R_he", "R_raw", "abs_rel", False),
    ("radar_t2", "R_jbf", "R_he", "abs_rel", False),
    ("radar_t2", "R_jbfc", "R_jbf", "abs_rel", False),
    ("radar_t2", "R_he", "R_raw", "-delta1", False),
    ("radar_t2", "R_jbf", "R_he", "-delta1", False),
)


# -- data -------------------------------------------------------------------------------------------
def thin_azimuth(src: Path, dst: Path, keep: int, steps: int = 2000) -> None:
    """Copy KITTI .bin scans keeping the points of every ``keep``-th azimuth step."""
    dst.mkdir(parents=True, exist_ok=True)
    for f in sorted(src.glob("*.bin")):
        out = dst / f.name
        if out.is_file():
            continue
        pts = np.fromfile(f, np.float32).reshape(-1, 4)
        az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) % 360.0
        step = np.floor(az / (360.0 / steps)).astype(np.int64)
        tmp = out.with_suffix(".tmp")
        pts[step % keep == 0].tofile(tmp)
        os.replace(tmp, out)


def prepare(out: Path, args) -> dict[str, Path]:
    settings = VideoSettings(
        size=args.size,
        sequences=args.sequences,
        frames=args.frames,
        split=args.split,
        workers=2,
        beams=BEAMS,
        night_brightness=0.3,
        azimuth_keep=AZIMUTH_KEEP,
    )
    datasets = {f"day{n}": ("rgb", n) for n in BEAMS}
    datasets["night4"] = ("night", 4)
    return prepare_datasets(out, settings, datasets, thin=thin_azimuth)


def prepare_full_scans(out: Path, args) -> dict[str, Path]:
    """UltraDepth's data: the videos' full 64-beam scans and unthinned 16 beams, the dense GT,
    and KITTI-like GT (dense GT where the 64-beam scan hits)."""
    from _selfsup_data import link, sequence_files, sequence_names
    from sparsetools.io.depth_files import read_depth_file
    from sparsetools.io.image import write_depth_png

    stage = out / "stage"
    for name in sequence_names(out):
        f = sequence_files(out, name, BEAMS)
        for n, scans in ((64, f.velodyne), (16, f.beams[16]), (4, f.beams[4])):
            dst = out / f"sparse{n}full" / name
            sparsetools("project", scans, "--calib", f.calib, "--image", f.images, "-o", dst)
            link(dst, stage / f"sparse{n}full" / name)
        kgt = out / "gt_kitti" / name
        kgt.mkdir(parents=True, exist_ok=True)
        for gt in sorted(f.depth.glob("*.png")):
            if not (kgt / gt.name).is_file():
                hit = read_depth_file(out / "sparse64full" / name / gt.name) > 0
                write_depth_png(kgt / gt.name, np.where(hit, read_depth_file(gt), 0.0))
        link(kgt, stage / "gt_kitti" / name)
    made = {}
    for key, sparse, gt in (
        ("full64", "sparse64full", "gt"),
        ("full16", "sparse16full", "gt"),
        ("full4", "sparse4full", "gt"),
        ("full64_kitti_gt", "sparse64full", "gt_kitti"),
        ("full16_kitti_gt", "sparse16full", "gt_kitti"),
    ):
        made[key] = build(out / f"dataset_{key}", stage, "rgb", sparse, gt, args.split)
    return made


def build(ds: Path, stage: Path, rgb: str, sparse: str, gt: str, split: str, conf=None) -> Path:
    if not (ds / "manifest.parquet").is_file():
        extra = () if conf is None else ("--confidence", stage / conf)
        sparsetools(
            "dataset", "build", "-o", ds, "--rgb", stage / rgb, "--sparse", stage / sparse,
            "--gt", stage / gt, "--calib", stage / "calib", "--splits", split, "--seed", 0,
            "--sparse-format", "png", *extra,
        )  # fmt: skip
    return ds


def prepare_radar(out: Path, args) -> dict[str, Path]:
    """Single-frame synthetic streets with 5-sweep radar: raw, height-extended and JBF radar
    depth, JBF confidence, and the projected 64-beam LiDAR as ground truth."""
    from _selfsup_data import link

    root = out / "radar"
    stage = root / "stage"
    w, h = args.radar_size
    for k in range(args.radar_streets):
        name = f"street{k}"
        sc = root / "scenes" / name
        if not (sc / "scene.json").is_file():
            sparsetools(
                "synth-scene", "-o", sc, "--frames", args.radar_frames, "--image-size",
                f"{w}x{h}", "--underwater-frames", 0, "--seed", 200 + k, "--overwrite",
            )  # fmt: skip
        raw = root / "raw" / name
        pcds = sorted(p for p in (sc / "radar").glob("*.pcd") if "_sweep" not in p.name)
        sparsetools("project", *pcds, "--calib", sc / "calib_radar", "--image", sc / "image_2",
                    "-o", raw)  # fmt: skip
        for method, folder in (("jbf", "jbf"), ("height-extend", "he")):
            sparsetools(
                "jbf-expand", raw, "--calib", raw / "calib", "--image", sc / "image_2",
                "--method", method, "-o", root / folder / name,
            )  # fmt: skip
        lidar = root / "lidar_gt" / name
        sparsetools("project", sc / "velodyne", "--calib", sc / "calib", "--image",
                    sc / "image_2", "-o", lidar)  # fmt: skip
        link(sc / "image_2", stage / "rgb" / name)
        link(sc / "calib", stage / "calib" / name)
        link(lidar, stage / "gt" / name)
        link(raw, stage / "raw" / name)
        for folder in ("jbf", "he"):  # depth maps and confidence maps in folders of their own
            for png in sorted((root / folder / name).glob("*.png")):
                kind = "conf" if png.stem.endswith("_conf") else folder
                link(png, stage / f"{folder}_{kind}" / name / png.name)
    split = "train=0.67,val=0.16,test=0.17"
    return {
        "radar_raw": build(root / "dataset_raw", stage, "rgb", "raw", "gt", split),
        "radar_he": build(root / "dataset_he", stage, "rgb", "he_he", "gt", split),
        "radar_jbf": build(
            root / "dataset_jbf", stage, "rgb", "jbf_jbf", "gt", split, conf="jbf_conf"
        ),
    }


def density(ds: Path) -> float:
    """Mean fraction of pixels with sparse depth over the test split (%)."""
    from sparsetools.io.dataset_reader import DatasetReader

    test = DatasetReader(ds).split("test")
    n = min(len(test), 20)
    return 100 * float(np.mean([(test.sample(i)["sparse"] > 0).mean() for i in range(n)]))


# -- runs -------------------------------------------------------------------------------------------
def run_one(model: Model, seed: int, datasets: dict, out: Path, args) -> dict:
    ds = datasets[model.dataset]
    run = out / "runs" / model.name / f"seed{seed}"
    done = out / "results" / f"{model.name}_seed{seed}.json"
    if done.is_file():
        return {**json.loads(done.read_text()), "fresh": False}
    epochs = args.sup_epochs if model.supervised else args.epochs
    if model.epochs and not args.tiny:
        epochs = model.epochs
    if model.supervised:
        common = [
            "--width", 8, "--batch-size", 4, "--epochs", epochs, "--lr", 1e-3,
            "--loss", "berhu", "--lr-schedule", "cosine", "--seed", seed, "--pictures", 0,
            "--threads", 1,
        ]  # fmt: skip
    else:
        common = [
            "--self-supervised", "--width", 8, "--pose-width", 16, "--batch-size", 4,
            "--epochs", epochs, "--lr", 1e-3, "--lr-schedule", "cosine", "--seed", seed,
            "--pictures", 0, "--threads", 1,
        ]  # fmt: skip
    if not (run / "last.pt").is_file():
        sparsetools("train", ds, "-o", run, *model.options, *common)
    elif _epochs_done(run) < epochs:
        sparsetools("train", ds, "-o", run, "--resume", "--epochs", epochs)
    with open(run / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    res = {}
    for key, flags in model.also:
        other = json.loads(
            sparsetools(
                "eval",
                "--checkpoint",
                run / "best.pt",
                datasets[f"{model.dataset}_{key}"],
                "--split",
                "test",
                *flags,
                "--json",
                capture=True,
            )
        )
        res[key] = other
    for scaling in ("auto", "median"):
        res[scaling] = json.loads(
            sparsetools(
                "eval",
                "--checkpoint",
                run / "best.pt",
                ds,
                "--split",
                "test",
                "--scaling",
                scaling,
                "--json",
                capture=True,
            )
        )
    pose = res["auto"].get("pose") or {}
    last = rows[-1]
    ratio = float(last["ate"]) / float(last["ate_still"]) if last.get("ate") else math.nan
    if model.supervised:
        record = {
            "model": model.name,
            "seed": seed,
            "train_seconds": sum(float(r["seconds"]) for r in rows),
            "median_scaling": False,
            "metrics": res["auto"]["metrics"],
            "metrics_median_scaled": res["median"]["metrics"],
            **{f"metrics_{key}": res[key]["metrics"] for key, _ in model.also},
            "best_epoch": _best_epoch(run),
        }
        done.parent.mkdir(parents=True, exist_ok=True)
        done.write_text(json.dumps(record, indent=1))
        return {**record, "fresh": True}
    record = {
        "model": model.name,
        "seed": seed,
        "train_seconds": sum(float(r["seconds"]) for r in rows),
        "median_scaling": res["auto"]["median_scaling"],
        "metrics": res["auto"]["metrics"],
        "metrics_median_scaled": res["median"]["metrics"],
        "ate": pose.get("ate_mean", math.nan),
        "ate_unscaled": pose.get("ate_unscaled_mean", math.nan),
        "ate_still": pose.get("ate_still_mean", math.nan),
        "val_ate_ratio_last_epoch": ratio,
        "best_epoch": _best_epoch(run),
        "train_sparse_last": float(last["train_sparse"]),
        "train_photometric_last": float(last["train_photometric"]),
    }
    done.parent.mkdir(parents=True, exist_ok=True)
    done.write_text(json.dumps(record, indent=1))
    return {**record, "fresh": True}


def _best_epoch(run: Path) -> int:
    import torch

    raw = torch.load(run / "best.pt", map_location="cpu", weights_only=True)
    return int(raw["epoch"]) if "epoch" in raw else -1


def _epochs_done(run: Path) -> int:
    with open(run / "metrics.csv") as f:
        return sum(1 for r in csv.DictReader(f) if r["complete"] == "1")


# -- report -----------------------------------------------------------------------------------------
def _stat(values: list[float]) -> tuple[float, float, float]:
    v = [x for x in values if math.isfinite(x)]
    return (float(np.mean(v)), min(v), max(v)) if v else (math.nan, math.nan, math.nan)


def _cell(values: list[float], fmt: str = "{:.3f}") -> str:
    m, lo, hi = _stat(values)
    if not math.isfinite(m):
        return "n/a"
    return f"{fmt.format(m)} ({fmt.format(lo)}-{fmt.format(hi)})"


def _runs(results: dict, name: str) -> list[dict]:
    return [r for r in results["runs"].values() if r["model"] == name]


def _value(run: dict, metric: str, scaled: bool) -> float:
    """``metric`` of a run; ``name@key``: on the other GT ``key``; ``-name``: negated (so that
    lower is better for every ordering)."""
    sign = -1.0 if metric.startswith("-") else 1.0
    metric = metric.lstrip("-")
    name, _, key = metric.partition("@")
    table = (
        run[f"metrics_{key}"]
        if key
        else (run["metrics_median_scaled"] if scaled else run["metrics"])
    )
    return sign * table[name]


def tables(results: dict) -> str:
    out = []
    for claim, models in CLAIMS.items():
        if not any(_runs(results, m.name) for m in models):
            continue
        if models[0].supervised:
            out += supervised_table(results, claim, models)
            continue
        out += [
            f"#### {claim}",
            "",
            "| model | seeds | AbsRel | AbsRel median-scaled | RMSE m | δ<1.25 | ATE m "
            "(scaled) | ATE m (unscaled) | paper AbsRel |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for m in models:
            runs = _runs(results, m.name)
            if not runs:
                continue
            metric = [_value(r, "abs_rel", False) for r in runs]
            scaled = [_value(r, "abs_rel", True) for r in runs]
            out.append(
                f"| {m.label} | {len(runs)} | {_cell(metric)} | {_cell(scaled)} | "
                f"{_cell([_value(r, 'rmse', False) for r in runs], '{:.2f}')} | "
                f"{_cell([_value(r, 'delta1', False) for r in runs])} | "
                f"{_cell([r['ate'] for r in runs])} | {_cell([r['ate_unscaled'] for r in runs])} | "
                f"{'' if m.paper is None else f'{m.paper:.3f}'} |"
            )
        out.append("")
    out.append("#### orderings (in the mean over seeds)")
    out.append("")
    for ok, text in checks(results):
        out.append(f"- {'reproduced' if ok else 'NOT reproduced'}: {text}")
    return "\n".join(out)


def supervised_table(results: dict, claim: str, models) -> list[str]:
    kitti = any(m.also for m in models)
    head = "| model | seeds | AbsRel | RMSE m | δ<1.25 |"
    sep = "|---|---:|---:|---:|---:|"
    if kitti:
        head += " RMSE m, KITTI-like GT | AbsRel, KITTI-like GT |"
        sep += "---:|---:|"
    out = [f"#### {claim}", "", head + " paper AbsRel | paper RMSE m |", sep + "---:|---:|"]
    for m in models:
        runs = _runs(results, m.name)
        if not runs:
            continue
        row = (
            f"| {m.label} | {len(runs)} | {_cell([_value(r, 'abs_rel', False) for r in runs])} | "
            f"{_cell([_value(r, 'rmse', False) for r in runs], '{:.2f}')} | "
            f"{_cell([_value(r, 'delta1', False) for r in runs])} |"
        )
        if kitti:
            row += (
                f" {_cell([_value(r, 'rmse@kitti_gt', False) for r in runs], '{:.2f}')} |"
                f" {_cell([_value(r, 'abs_rel@kitti_gt', False) for r in runs])} |"
            )
        paper = "" if m.paper is None else f"{m.paper:.4g}"
        rmse = "" if m.paper_rmse is None else f"{m.paper_rmse:.3g}"
        out.append(row + f" {paper} | {rmse} |")
    out.append("")
    return out


def checks(results: dict) -> list[tuple[bool, str]]:
    found = []
    labels = {m.name: m.label for ms in CLAIMS.values() for m in ms}
    for _claim, better, worse, metric, scaled in ORDERINGS:
        a, b = _runs(results, better), _runs(results, worse)
        if not a or not b:
            continue
        if metric == "abs_rel_metric_vs_scaled":  # unscaled M+L against median-scaled M
            va = _stat([_value(r, "abs_rel", False) for r in a])[0]
            vb = _stat([_value(r, "abs_rel", True) for r in b])[0]
            how = f"{labels[better]} unscaled {va:.3f} < {labels[worse]} median-scaled {vb:.3f}"
        else:
            va = _stat([_value(r, metric, scaled) for r in a])[0]
            vb = _stat([_value(r, metric, scaled) for r in b])[0]
            kind = "median-scaled" if scaled else "as predicted"
            if metric.startswith("-"):  # higher is better: say it so
                how = (
                    f"{metric[1:]} ({kind}): {labels[better]} {-va:.3f} > {labels[worse]} {-vb:.3f}"
                )
            else:
                how = f"{metric} ({kind}): {labels[better]} {va:.3f} < {labels[worse]} {vb:.3f}"
        found.append((va < vb, how))
    return found


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--out", type=Path, default=REPO / "out" / "acceptance_claims")
    p.add_argument("--claims", default=",".join(CLAIMS))
    p.add_argument("--seeds", default="0,1")
    p.add_argument("--only", default=None, help="comma-separated model names")
    p.add_argument("--tiny", action="store_true", help="development size: a few minutes")
    p.add_argument("--tables", action="store_true", help="only print the tables of the results")
    p.add_argument("--parallel", type=int, default=2, help="runs at a time (1 thread each)")
    args = p.parse_args()
    if args.tables:
        print(tables(json.loads(RESULTS.read_text())))
        return
    if args.tiny:
        args.size, args.sequences, args.frames, args.epochs = (96, 32), 4, 8, 1
        args.split = "train=0.5,val=0.25,test=0.25"
        args.sup_epochs, args.radar_size, args.radar_streets, args.radar_frames = 1, (96, 32), 3, 4
    else:
        args.size, args.sequences, args.frames, args.epochs = (208, 64), 12, 20, 6
        args.split = "train=0.67,val=0.16,test=0.17"
        args.sup_epochs, args.radar_size, args.radar_streets, args.radar_frames = (
            8,
            (416, 128),
            6,
            25,
        )
    started = time.perf_counter()
    load0 = os.getloadavg()
    print(f"machine load (1, 5, 15 min): {load0}", flush=True)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    claims = args.claims.split(",")
    datasets = prepare(out, args)
    if "ultradepth_t2" in claims or "effisdepth_t2" in claims:
        datasets.update(prepare_full_scans(out, args))
    if "radar_t2" in claims:
        datasets.update(prepare_radar(out, args))
    densities = {
        k: round(density(v), 3) for k, v in datasets.items() if not k.endswith("_kitti_gt")
    }
    print(f"sparse density, % of pixels (test split): {densities}", flush=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    only = set(args.only.split(",")) if args.only else None
    jobs = [
        (m, s) for c in claims for m in CLAIMS[c] if only is None or m.name in only for s in seeds
    ]
    jobs = list(dict.fromkeys((m.name, s) for m, s in jobs))  # shared by two claims: once
    models = {m.name: m for ms in CLAIMS.values() for m in ms}
    jobs = [(models[name], s) for name, s in jobs]
    with ThreadPoolExecutor(args.parallel) as pool:
        records = list(pool.map(lambda j: run_one(j[0], j[1], datasets, out, args), jobs))
    if not args.tiny:
        previous = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"runs": {}}
        made = {
            f"{r['model']}/seed{r['seed']}": {k: v for k, v in r.items() if k != "fresh"}
            for r in records
        }
        runs = {**previous["runs"], **made}
        wall = time.perf_counter() - started
        command = "python benchmarks/acceptance_claims.py " + shlex.join(sys.argv[1:])
        invocation = {
            "command": command,
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "runs_made": sorted(f"{r['model']}/seed{r['seed']}" for r in records if r["fresh"]),
            "wall_seconds": round(wall),
            "machine_load_start": load0,
            "machine_load_end": os.getloadavg(),
        }
        results = {
            "command": command,
            "invocations": [*previous.get("invocations", []), invocation],
            "settings": {
                "image_size": list(args.size),
                "sequences": args.sequences,
                "frames": args.frames,
                "epochs": args.epochs,
                "supervised_epochs": args.sup_epochs,
                "radar": {
                    "image_size": list(args.radar_size),
                    "streets": args.radar_streets,
                    "frames": args.radar_frames,
                },
                "split": args.split,
                "azimuth_keep": AZIMUTH_KEEP,
                "width": 8,
                "pose_width": 16,
                "batch_size": 4,
                "threads_per_run": 1,
            },
            "sparse_density_percent": densities,
            "machine_load_start": load0,
            "machine_load_end": os.getloadavg(),
            "wall_seconds_last_invocation": round(wall),
            "runs": dict(sorted(runs.items())),
        }
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(results, indent=1) + "\n")
        print(f"wrote {RESULTS}")
        print(tables(results))
    wall = time.perf_counter() - started
    print(f"\nwall time {wall:.0f} s ({wall / 60:.1f} min); load {os.getloadavg()}")


if __name__ == "__main__":
    main()
