"""Acceptance run of self-supervised training from video (issue 14; not part of `make test`).

Synthetic street videos (`synth-scene --video`) split by sequence; everything goes through the
command line, as a user would run it:

    sparsetools synth-scene -o VIDEOS --video --sequences S --frames F --image-size WxH --seed 100
    sparsetools beams VIDEOS/<seq>/velodyne --n 4,16 -o BEAMS/<seq>
    sparsetools project BEAMS/<seq>/n<N> --calib VIDEOS/<seq>/calib --image VIDEOS/<seq>/image_2 \
        -o SPARSE<N>/<seq>
    sparsetools lowlight-synth VIDEOS/<seq>/image_2 --depth ... --calib ... -o NIGHT/<seq> ...
    sparsetools dataset build -o DS --rgb STAGE/rgb --sparse SPARSE<N> --gt STAGE/gt \
        --calib STAGE/calib --splits train=...,val=...,test=...
    sparsetools train DS -o RUNS/<name> --self-supervised [--sparse-loss silog] [--mcie --sbm]
    sparsetools eval --checkpoint RUNS/<name>/best.pt DS --split test --json

Models (same settings otherwise):

- day, camera only (evaluated with per-image median scaling, monodepth2's protocol);
- day, camera + 4-beam sparse loss; camera + 16-beam sparse loss (both evaluated unscaled);
- day, camera + 16-beam LiDAR as input too (``--input rgbd``, early fusion) + its sparse loss;
- night (``lowlight-synth`` frames), camera only, without and with MCIE + SBM (RNW).

Sizes: ``--tiny`` (a minute or two, for development) or the default full run (see
docs/selfsup.md for its measured wall time). Existing videos, datasets and finished runs under
``--out`` are reused. Prints the tables (Markdown), the checks and the wall time.

    .venv/bin/python benchmarks/acceptance_selfsup.py --out out/acceptance_selfsup [--docs]
    .venv/bin/python benchmarks/acceptance_selfsup.py --out out/acc_tiny --tiny
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from _selfsup_data import VideoSettings, prepare_datasets, sparsetools

REPO = Path(__file__).resolve().parent.parent
BEAMS = (4, 16)
#: Dataset key -> (images, beam count of the sparse depth).
DATASETS = {"day4": ("rgb", 4), "day16": ("rgb", 16), "night16": ("night", 16)}


def prepare(out: Path, args) -> dict[str, Path]:
    """The three datasets (data preparation: benchmarks/_selfsup_data.py)."""
    settings = VideoSettings(
        size=args.size,
        sequences=args.sequences,
        frames=args.frames,
        split=args.split,
        workers=args.workers,
        beams=BEAMS,
        night_brightness=args.night_brightness,
    )
    return prepare_datasets(out, settings, DATASETS)


# -- runs -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Model:
    name: str
    label: str
    dataset: str
    options: tuple


MODELS = (
    Model("day_camera", "camera only (median-scaled)", "day4", ("--input", "rgb")),
    Model(
        "day_sparse4",
        "camera + 4-beam sparse loss",
        "day4",
        ("--input", "rgb", "--sparse-loss", "silog"),
    ),
    Model(
        "day_sparse16",
        "camera + 16-beam sparse loss",
        "day16",
        ("--input", "rgb", "--sparse-loss", "silog"),
    ),
    Model(
        "day_rgbd16",
        "camera + 16-beam input and sparse loss",
        "day16",
        ("--input", "rgbd", "--sparse-loss", "silog"),
    ),
    Model("night_camera", "night, camera only (median-scaled)", "night16", ("--input", "rgb")),
    Model(
        "night_mcie_sbm",
        "night, + MCIE + SBM (median-scaled)",
        "night16",
        ("--input", "rgb", "--mcie", "--sbm"),
    ),
)


def train_and_eval(model: Model, ds: Path, runs: Path, args) -> dict:
    run = runs / model.name
    common = [
        "--self-supervised", "--width", args.width, "--pose-width", args.pose_width,
        "--batch-size", args.batch_size, "--epochs", args.epochs, "--lr", args.lr,
        "--lr-schedule", "cosine", "--seed", 0, "--pictures", 2,
    ]  # fmt: skip
    if not (run / "last.pt").is_file():
        sparsetools("train", ds, "-o", run, *model.options, *common)
    elif _epochs_done(run) < args.epochs:
        sparsetools("train", ds, "-o", run, "--resume", "--epochs", args.epochs)
    with open(run / "metrics.csv") as f:
        seconds = sum(float(r["seconds"]) for r in csv.DictReader(f))
    res = json.loads(
        sparsetools(
            "eval", "--checkpoint", run / "best.pt", ds, "--split", "test", "--json", capture=True
        )
    )
    pose = res.get("pose") or {}
    return {
        "name": model.name,
        "label": model.label,
        "seconds": seconds,
        "median_scaling": res["median_scaling"],
        "ate": pose.get("ate_mean", float("nan")),
        "ate_std": pose.get("ate_std", float("nan")),
        **res["metrics"],
    }


def _epochs_done(run: Path) -> int:
    with open(run / "metrics.csv") as f:
        return sum(1 for r in csv.DictReader(f) if r["complete"] == "1")


# -- report -----------------------------------------------------------------------------------------
COLUMNS = (
    ("abs_rel", "AbsRel", "{:.3f}"),
    ("sq_rel", "SqRel m", "{:.3f}"),
    ("rmse", "RMSE m", "{:.3f}"),
    ("rmse_log", "RMSE log", "{:.3f}"),
    ("delta1", "δ<1.25", "{:.3f}"),
    ("delta2", "δ<1.25²", "{:.3f}"),
    ("delta3", "δ<1.25³", "{:.3f}"),
    ("ate", "ATE m", "{:.3f}"),
    ("seconds", "train s", "{:.0f}"),
)


def table(rows: list[dict]) -> str:
    head = "| model | " + " | ".join(c[1] for c in COLUMNS) + " |"
    sep = "|---|" + "---:|" * len(COLUMNS)
    body = [
        "| " + r["label"] + " | " + " | ".join(fmt.format(r[k]) for k, _, fmt in COLUMNS) + " |"
        for r in rows
    ]
    return "\n".join([head, sep, *body])


def checks(results: dict[str, dict]) -> list[tuple[bool, str]]:
    r = results
    return [
        (
            r["day_sparse4"]["abs_rel"] < r["day_camera"]["abs_rel"],
            "AbsRel: + 4-beam sparse loss (unscaled) < camera only (median-scaled)",
        ),
        (
            r["day_sparse16"]["abs_rel"] < r["day_sparse4"]["abs_rel"],
            "AbsRel: 16 beams < 4 beams (sparse loss)",
        ),
        (
            r["day_rgbd16"]["abs_rel"] < r["day_sparse16"]["abs_rel"],
            "AbsRel: 16-beam input + loss < loss alone",
        ),
        (
            r["night_mcie_sbm"]["abs_rel"] < r["night_camera"]["abs_rel"],
            "AbsRel, night: MCIE + SBM < plain",
        ),
        (
            not r["day_sparse4"]["median_scaling"] and r["day_camera"]["median_scaling"],
            "protocol: median scaling only for camera-only models",
        ),
    ]


def docs_pictures(runs: Path, datasets: dict[str, Path], img: Path) -> None:
    """docs/img/selfsup_compare.png and selfsup_night.png: test frames and predictions."""
    import cv2
    import torch

    from sparsetools.io.dataset_reader import DatasetReader
    from sparsetools.io.image import write_image
    from sparsetools.ops.colormap import colorize_depth, side_by_side
    from sparsetools.train.checkpoint import load_checkpoint, model_from_checkpoint

    def predict(name, sample):
        ckpt = load_checkpoint(runs / name / "best.pt")
        model = model_from_checkpoint(ckpt).eval()
        rgb = torch.from_numpy(sample["rgb"].transpose(2, 0, 1).copy()).float()[None] / 255
        sparse = torch.from_numpy(sample["sparse"])[None, None]
        with torch.no_grad():
            d = model.depth_of(rgb, sparse)[0, 0].numpy()
        valid = (sample["gt"] > 1e-3) & (sample["gt"] < 80)
        if not ckpt.config.selfsup.metric_scale:  # as evaluated: per-image median scaling
            d = d * np.median(sample["gt"][valid]) / np.median(d[valid])
        return colorize_depth(d, max_depth=80.0)

    def big(x):
        return cv2.resize(x, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)

    for out_name, key, names in (
        (
            "selfsup_compare.png",
            "day16",
            ("day_camera", "day_sparse4", "day_sparse16", "day_rgbd16"),
        ),
        ("selfsup_night.png", "night16", ("night_camera", "night_mcie_sbm")),
    ):
        test = DatasetReader(datasets[key]).split("test")
        rows = []
        for i in (len(test) // 3, 2 * len(test) // 3):
            s = test.sample(i)
            panels = [
                s["rgb"],
                *(predict(n, s) for n in names),
                colorize_depth(s["gt"], max_depth=80.0),
            ]
            rows.append(side_by_side([big(p) for p in panels], vertical=False, gap=4))
        write_image(img / out_name, side_by_side(rows, vertical=True, gap=4))
        print(f"wrote {img / out_name}")


def method_picture(path: Path) -> None:
    """docs/img/selfsup_masks.png: the loss's parts on two synthetic triplets with true depth
    and poses -- a street with moving cars (seed 2) and a stopped ego car (seed 5)."""
    import torch

    from sparsetools.io.image import write_image
    from sparsetools.ops.colormap import colorize_depth, side_by_side
    from sparsetools.synth.video import simulate_video
    from sparsetools.train.selfsup.geometry import warp_frame
    from sparsetools.train.selfsup.masks import StatisticsMask, auto_mask, temporal_change
    from sparsetools.train.selfsup.photometric import photometric_error

    def tensor(img):
        return torch.from_numpy(img.transpose(2, 0, 1).astype(np.float64) / 255)[None]

    def label(img, text):
        from sparsetools.ops.text import put_outlined_text

        return put_outlined_text(img.copy(), text, (4, 14), scale=0.42, thickness=1, outline=1)

    def error(e, valid):  # photometric error 0 (blue) .. 0.3 (red); grey: no depth (sky)
        out = colorize_depth(np.maximum(e, 1e-4), max_depth=0.3)
        out[~valid] = 160
        return out

    def mask(m):
        return np.repeat((m * 255).astype(np.uint8)[:, :, None], 3, axis=2)

    def final_picture(used, moving):
        out = mask(used)
        out[moving] = (out[moving] // 2 + np.array([128, 0, 0])).astype(np.uint8)
        return out

    rows = []
    for seed, what in ((2, "moving cars"), (5, "ego car stopped")):
        frames = simulate_video(seed, n_frames=3, image_size=(416, 128), lidar=False).frames
        t = frames[1]
        imgs = [tensor(f.image) for f in frames]
        depth = torch.from_numpy(t.depth.astype(np.float64))[None, None]
        reproj, ident = [], []
        for k in (0, 2):
            T = np.linalg.inv(frames[k].T_world_from_cam) @ t.T_world_from_cam
            warp = warp_frame(
                imgs[k], depth, torch.from_numpy(T)[None], torch.from_numpy(t.K)[None]
            )
            reproj.append(photometric_error(warp.image, imgs[1]))
            ident.append(photometric_error(imgs[k], imgs[1]))
        reproj, ident = torch.cat(reproj, 1), torch.cat(ident, 1)
        auto = auto_mask(reproj, ident, generator=torch.Generator().manual_seed(0))[0, 0].numpy()
        change = temporal_change(imgs[1], torch.stack([imgs[0], imgs[2]], 1))
        sbm = StatisticsMask(q=10)
        sbm.update(change)
        chosen = reproj.min(1, keepdim=True).indices
        sbm_mask = torch.gather(sbm.mask(change), 1, chosen)[0, 0].numpy()
        panels = [
            label(t.image, f"target I_t ({what})"),
            label(
                error(reproj.min(1).values[0].numpy(), t.depth > 0),
                "min_s pe(I_t, I_s->t), true depth + pose",
            ),
            label(
                error(ident.min(1).values[0].numpy(), t.depth > 0), "min_s pe(I_t, I_s), no warp"
            ),
            label(mask(auto & (t.depth > 0)), "auto-mask (white = used)"),
            label(mask(sbm_mask), "SBM (10th percentile)"),
            label(
                final_picture(auto & sbm_mask & (t.depth > 0), t.moving_mask),
                "auto-mask x SBM; red: moving objects",
            ),
        ]
        rows.append(side_by_side(panels[:3], vertical=False, gap=4))
        rows.append(side_by_side(panels[3:], vertical=False, gap=4))
    write_image(path, side_by_side(rows, vertical=True, gap=4))
    print(f"wrote {path}")


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--out", type=Path, default=REPO / "out" / "acceptance_selfsup")
    p.add_argument("--tiny", action="store_true", help="development size: a minute or two")
    p.add_argument("--docs", action="store_true", help="also draw docs/img/selfsup_*.png")
    p.add_argument("--only", nargs="*", default=None, help="train only these models")
    p.add_argument(
        "--method-picture", action="store_true", help="only draw docs/img/selfsup_masks.png"
    )
    args = p.parse_args()
    if args.method_picture:
        method_picture(REPO / "docs" / "img" / "selfsup_masks.png")
        return
    if args.tiny:
        args.size, args.sequences, args.frames, args.epochs = (96, 32), 4, 6, 1
        args.split = "train=0.5,val=0.25,test=0.25"
    else:
        args.size, args.sequences, args.frames, args.epochs = (208, 64), 24, 30, 5
        args.split = "train=0.67,val=0.16,test=0.17"
    args.width, args.pose_width, args.batch_size, args.lr = 8, 16, 4, 1e-3
    args.workers, args.night_brightness = 2, 0.3
    started = time.perf_counter()
    print(f"machine load (1, 5, 15 min): {os.getloadavg()}", flush=True)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    datasets = prepare(out, args)
    t_data = time.perf_counter() - started
    results = {}
    for model in MODELS:
        if args.only and model.name not in args.only:
            continue
        results[model.name] = train_and_eval(model, datasets[model.dataset], out / "runs", args)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    print()
    print(table(list(results.values())))
    print()
    if len(results) == len(MODELS):
        for ok, text in checks(results):
            print(f"- {'PASS' if ok else 'FAIL'}: {text}")
    if args.docs:
        docs_pictures(out / "runs", datasets, REPO / "docs" / "img")
        method_picture(REPO / "docs" / "img" / "selfsup_masks.png")
    wall = time.perf_counter() - started
    print(f"\ndata {t_data:.0f} s; wall time {wall:.0f} s ({wall / 60:.1f} min)")
    print(f"machine load (1, 5, 15 min): {os.getloadavg()}")


if __name__ == "__main__":
    main()
