"""Training loop: determinism, exact resume, augmentation, checkpoints, evaluation, bad input."""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from sparsetools.errors import FormatError, OutputError, ParameterError
from sparsetools.io.image import read_image, write_depth_png, write_image
from sparsetools.ops.metrics import METRIC_NAMES, depth_metrics
from sparsetools.train.checkpoint import load_checkpoint
from sparsetools.train.config import TrainConfig, epoch_lr
from sparsetools.train.data import (
    DepthDataset,
    augment_sample,
    bottom_centre_crop,
    collate,
)
from sparsetools.train.evaluate import (
    evaluate_checkpoint,
    evaluate_folders,
    write_eval_results,
)
from sparsetools.train.loop import train
from sparsetools.train.plots import draw_curves, prediction_picture

#: Columns of metrics.csv that differ between two identical runs: their timing and run id.
TIMING = {"seconds", "samples_per_s", "run_id"}


def make_dataset(
    root: Path, *, n_seq=5, frames=4, h=24, w=40, seed=0, gt=True, sizes=None, split=None
) -> Path:
    """A tiny learnable dataset: a ground plane whose depth the image brightness encodes.

    ``sizes`` maps a sequence number to its own (h, w) to make mixed-size datasets.
    """
    from sparsetools.pipeline.batch import Batch
    from sparsetools.pipeline.dataset import build_dataset

    rng = np.random.default_rng(seed)
    inputs = root / "inputs"
    for s in range(n_seq):
        hh, ww = (sizes or {}).get(s, (h, w))
        for f in range(frames):
            rows = np.arange(hh, dtype=np.float32)[:, None]
            depth = 5 + 40 * (1 - rows / hh) + rng.uniform(-2, 2)
            depth = np.repeat(depth, ww, axis=1) + rng.uniform(0, 3, (1, ww))
            depth = depth.astype(np.float32)
            depth[: hh // 4] = 0  # no ground truth in the "sky"
            grey = np.clip(255 * (1 - depth / 60), 0, 255)[:, :, None].repeat(3, axis=2)
            rgb = np.clip(grey + rng.integers(-10, 10, grey.shape), 0, 255).astype(np.uint8)
            sparse = np.where(rng.random((hh, ww)) < 0.05, depth, 0).astype(np.float32)
            name = Path(f"seq{s}") / f"{f:06d}.png"
            for folder, arr in (("rgb", rgb), ("sparse", sparse), ("gt", depth)):
                p = inputs / folder / name
                p.parent.mkdir(parents=True, exist_ok=True)
                (write_image if folder == "rgb" else write_depth_png)(p, arr)
    out = root / "dataset"
    build_dataset(
        out,
        rgb=inputs / "rgb",
        sparse=inputs / "sparse",
        gt=(inputs / "gt") if gt else None,
        split=split or {"train": 0.6, "val": 0.2, "test": 0.2},
        batch=Batch(progress=False),
    )
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("train_ds"))


def config(dataset, out, **kw) -> TrainConfig:
    base = dict(
        dataset=str(dataset),
        out_dir=str(out),
        width=4,
        epochs=2,
        batch_size=4,
        lr=3e-3,
        threads=1,
        pictures=2,
    )
    base.update(kw)
    return TrainConfig(**base)


def read_rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv") as f:
        return [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(f)]


def state_equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# -- determinism and resume -------------------------------------------------------------------------
def test_same_seed_same_metrics_and_weights(dataset, tmp_path):
    s1 = train(config(dataset, tmp_path / "a"))
    s2 = train(config(dataset, tmp_path / "b"))
    rows = read_rows(tmp_path / "a")
    assert len(rows) == 2 and rows == read_rows(tmp_path / "b")
    assert s1.best_metric == "rmse" and s1.best_value == s2.best_value
    assert state_equal(
        load_checkpoint(tmp_path / "a" / "last.pt").model,
        load_checkpoint(tmp_path / "b" / "last.pt").model,
    )
    # another seed gives another model
    train(config(dataset, tmp_path / "c", seed=1))
    assert read_rows(tmp_path / "c") != rows


def test_resume_is_exact(dataset, tmp_path):
    train(config(dataset, tmp_path / "full", epochs=2))
    train(config(dataset, tmp_path / "half", epochs=1))
    assert len(read_rows(tmp_path / "half")) == 1
    train(config(dataset, tmp_path / "half", epochs=2), resume=True)
    assert read_rows(tmp_path / "half") == read_rows(tmp_path / "full")
    full = load_checkpoint(tmp_path / "full" / "last.pt")
    half = load_checkpoint(tmp_path / "half" / "last.pt")
    assert state_equal(full.model, half.model)
    assert full.state.step == half.state.step == 6
    # optimizer moments too
    ma, mb = full.optimizer["state"], half.optimizer["state"]
    assert all(torch.equal(ma[k]["exp_avg_sq"], mb[k]["exp_avg_sq"]) for k in ma)


def test_resume_mid_epoch_after_max_steps(dataset, tmp_path):
    # 12 training samples / batch 4 = 3 steps per epoch; stop after 2 steps, then resume
    train(config(dataset, tmp_path / "full", epochs=2))
    partial = train(config(dataset, tmp_path / "cut", epochs=2, max_steps=2))
    assert partial.steps == 2 and partial.epochs_done == 0
    rows = read_rows(tmp_path / "cut")
    assert len(rows) == 1 and rows[0]["complete"] == "0" and rows[0]["batches"] == "2"
    train(config(dataset, tmp_path / "cut", epochs=2), resume=True)
    assert read_rows(tmp_path / "cut") == read_rows(tmp_path / "full")
    assert state_equal(
        load_checkpoint(tmp_path / "cut" / "last.pt").model,
        load_checkpoint(tmp_path / "full" / "last.pt").model,
    )


def test_lr_schedules():
    c = TrainConfig(dataset="x", out_dir="y", lr=1e-2, epochs=5)
    assert [epoch_lr(c, e) for e in range(3)] == [1e-2] * 3
    c.lr_schedule, c.lr_step, c.lr_gamma = "step", 2, 0.2
    assert [epoch_lr(c, e) for e in range(5)] == pytest.approx([1e-2, 1e-2, 2e-3, 2e-3, 4e-4])
    c.lr_schedule = "cosine"
    lrs = [epoch_lr(c, e) for e in range(5)]
    assert lrs[0] == pytest.approx(1e-2) and lrs[-1] == pytest.approx(1e-4)
    assert lrs[2] == pytest.approx(1e-2 * (0.01 + 0.99 * 0.5))
    assert all(lrs[i] > lrs[i + 1] for i in range(len(lrs) - 1))
    c.lr_schedule = "exp"
    with pytest.raises(ParameterError, match="schedule"):
        c.validate()


def test_resume_is_exact_with_step_schedule(dataset, tmp_path):
    kw = dict(lr_schedule="step", lr_step=1, lr_gamma=0.5, epochs=2)
    train(config(dataset, tmp_path / "full", **kw))
    train(config(dataset, tmp_path / "half", **{**kw, "epochs": 1}))
    train(config(dataset, tmp_path / "half", **kw), resume=True)
    rows = read_rows(tmp_path / "full")
    assert read_rows(tmp_path / "half") == rows
    assert [float(r["lr"]) for r in rows] == [3e-3, 1.5e-3]


def test_max_steps_caps_total_steps(dataset, tmp_path):
    s = train(config(dataset, tmp_path / "r", epochs=5, max_steps=4))
    assert s.steps == 4
    assert load_checkpoint(tmp_path / "r" / "last.pt").state.step == 4
    # resuming a finished run does nothing more
    again = train(config(dataset, tmp_path / "r", epochs=5, max_steps=4), resume=True)
    assert again.steps == 4


@pytest.mark.slow
def test_workers_do_not_change_results(dataset, tmp_path):
    train(config(dataset, tmp_path / "w0", epochs=1, workers=0))
    train(config(dataset, tmp_path / "w2", epochs=1, workers=2))
    assert read_rows(tmp_path / "w0") == read_rows(tmp_path / "w2")


@pytest.mark.slow
def test_training_learns(dataset, tmp_path):
    train(config(dataset, tmp_path / "r", epochs=15, batch_size=4, loss="l1"))
    rows = read_rows(tmp_path / "r")
    first, best = float(rows[0]["rmse"]), min(float(r["rmse"]) for r in rows)
    assert best < 0.5 * first
    assert float(rows[-1]["train_loss"]) < float(rows[0]["train_loss"])


# -- run folder contents ---------------------------------------------------------------------------
def test_run_folder_contents(dataset, tmp_path):
    run = tmp_path / "run"
    summary = train(config(dataset, run, input_mode="rgbdm", final_layer=True, loss="silog"))
    for name in (
        "config.json",
        "metrics.csv",
        "last.pt",
        "best.pt",
        "curves.png",
        "predictions/epoch_001.png",
        "predictions/epoch_002.png",
    ):
        assert (run / name).is_file(), name
    assert not list(run.rglob(".tmp-*"))
    rows = read_rows(run)
    for k in ("epoch", "train_loss", "val_loss", *METRIC_NAMES):
        assert k in rows[0]
    ckpt = load_checkpoint(run / "best.pt")
    assert ckpt.model_config == {"input_mode": "rgbdm", "width": 4, "final_layer": True}
    assert ckpt.kind == "supervised"
    assert ckpt.state.best.name == "rmse"
    assert ckpt.state.best.value == pytest.approx(min(float(r["rmse"]) for r in rows))
    assert summary.best_epoch == ckpt.state.best.epoch
    assert ckpt.config.loss == "silog"
    curves = read_image(run / "curves.png")
    assert curves.shape[0] > 200 and curves.shape[1] > 600
    pic = read_image(run / "predictions" / "epoch_002.png")
    assert pic.shape[1] >= 4 * 240  # four panels, enlarged


def test_best_checkpoint_reproduces_validation_metrics(dataset, tmp_path):
    run = tmp_path / "run"
    train(config(dataset, run, epochs=3))
    rows = read_rows(run)
    best = min(rows, key=lambda r: float(r["rmse"]))
    res = evaluate_checkpoint(run / "best.pt", dataset, split="val", batch_size=3)
    for k in METRIC_NAMES:
        assert res.metrics[k] == pytest.approx(float(best[k]), rel=1e-5), k
    # a run folder means its best.pt
    again = evaluate_checkpoint(run, dataset, split="val", batch_size=3)
    assert again.metrics == res.metrics
    assert not res.median_scaling and res.kind == "supervised"
    test_res = evaluate_checkpoint(run / "last.pt", dataset, split="test")
    assert test_res.metrics["n_images"] == 4
    written = write_eval_results(test_res, tmp_path / "out" / "m.json")
    assert [p.name for p in written] == ["m.json", "m.csv"]
    lines = written[1].read_text().splitlines()
    assert lines[0].startswith("id,abs_rel") and lines[-1].startswith("mean,")
    assert len(lines) == 1 + 4 + 1


# -- evaluation of folders ------------------------------------------------------------------------
def test_evaluate_folders_matches_depth_metrics(tmp_path):
    rng = np.random.default_rng(0)
    (tmp_path / "p").mkdir()
    (tmp_path / "g").mkdir()
    per = []
    for i in range(3):
        gt = np.where(rng.random((10, 12)) < 0.5, rng.uniform(1, 70, (10, 12)), 0)
        pred = rng.uniform(1, 70, (10, 12))
        write_depth_png(tmp_path / "g" / f"{i:06d}.png", gt)
        write_depth_png(tmp_path / "p" / f"{i:06d}.png", pred)
        # compare with what the PNGs hold (quantised to 1/256 m)
        per.append(depth_metrics(np.round(pred * 256) / 256, np.round(gt * 256) / 256))
    write_depth_png(tmp_path / "p" / "extra.png", np.ones((10, 12)))
    res = evaluate_folders(tmp_path / "p", tmp_path / "g")
    assert res.unmatched_predictions == 1
    assert res.metrics["n_images"] == 3
    for k in METRIC_NAMES:
        assert res.metrics[k] == pytest.approx(np.mean([m[k] for m in per]), rel=1e-5), k


def test_evaluate_folders_bad_input(tmp_path):
    (tmp_path / "p").mkdir()
    (tmp_path / "g").mkdir()
    write_depth_png(tmp_path / "g" / "a.png", np.full((4, 5), 10.0))
    write_depth_png(tmp_path / "g" / "b.png", np.full((4, 5), 10.0))
    write_depth_png(tmp_path / "p" / "a.png", np.full((4, 6), 10.0))
    with pytest.raises(FormatError, match="no prediction"):
        evaluate_folders(tmp_path / "p", tmp_path / "g")
    write_depth_png(tmp_path / "p" / "b.png", np.full((4, 5), 10.0))
    with pytest.raises(FormatError, match="'a'.*4.*ground truth"):
        evaluate_folders(tmp_path / "p", tmp_path / "g")
    with pytest.raises(FormatError, match="--gt: .*does_not_exist: no such file or folder"):
        evaluate_folders(tmp_path / "p", tmp_path / "does_not_exist")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError, match=r"--gt: no \*.png/\*.npy files"):
        evaluate_folders(tmp_path / "p", tmp_path / "empty")


# -- bad input -----------------------------------------------------------------------------------------
def test_split_without_gt(tmp_path):
    ds = make_dataset(tmp_path / "nogt", n_seq=3, frames=2, gt=False)
    with pytest.raises(FormatError, match="no ground truth"):
        train(config(ds, tmp_path / "run"))
    assert not (tmp_path / "run").exists()


def test_missing_or_empty_split(dataset, tmp_path):
    with pytest.raises(ParameterError, match="no samples in split 'validation'"):
        train(config(dataset, tmp_path / "run", val_split="validation"))
    with pytest.raises(ParameterError, match="split 'nope'"):
        DepthDataset(dataset, "nope")
    assert not (tmp_path / "run").exists()


def test_mixed_sizes_need_a_crop(tmp_path):
    ds = make_dataset(
        tmp_path / "mixed", n_seq=3, frames=2, sizes={1: (20, 36)}, split={"train": 1.0}
    )
    with pytest.raises(ParameterError, match=r"sizes \(36x20, 40x24, WxH\).* --crop-size WxH$"):
        train(config(ds, tmp_path / "run", val_split="train"))
    with pytest.raises(ParameterError, match="larger than"):
        train(config(ds, tmp_path / "run", val_split="train", crop=(24, 40)))
    s = train(config(ds, tmp_path / "run", val_split="train", crop=(16, 32), epochs=1))
    assert s.steps == 2
    # the collate function refuses mixed sizes itself too
    items = [
        {
            "rgb": torch.zeros(3, 4, 5),
            "sparse": torch.zeros(1, 4, 5),
            "gt": torch.zeros(1, 4, 5),
            "index": 0,
        },
        {
            "rgb": torch.zeros(3, 4, 6),
            "sparse": torch.zeros(1, 4, 6),
            "gt": torch.zeros(1, 4, 6),
            "index": 1,
        },
    ]
    with pytest.raises(
        ParameterError, match=r"different sizes .*\(5x4, 6x4, WxH\): use --crop-size"
    ):
        collate(items)


def test_existing_run_and_resume_errors(dataset, tmp_path):
    run = tmp_path / "run"
    with pytest.raises(ParameterError, match="nothing to resume"):
        train(config(dataset, run), resume=True)
    first = train(config(dataset, run, epochs=1))
    before = (run / "last.pt").read_bytes()
    rows = read_rows(run)
    # the resume rule: the same settings on a finished run are a no-op
    again = train(config(dataset, run, epochs=1))
    assert again.steps == first.steps and again.best_value == first.best_value
    assert (run / "last.pt").read_bytes() == before and read_rows(run) == rows
    # another setting, more epochs without --resume, or a dataset changed since: refused
    for changed in (dict(epochs=1, seed=7), dict(epochs=2), dict(epochs=1, width=8)):
        with pytest.raises(OutputError, match="already holds a run"):
            train(config(dataset, run, **changed))
    manifest = dataset / "manifest.parquet"
    stat = manifest.stat()
    try:
        os.utime(manifest, (stat.st_atime, (run / "last.pt").stat().st_mtime + 10))
        with pytest.raises(OutputError, match="already holds a run"):
            train(config(dataset, run, epochs=1))
    finally:
        os.utime(manifest, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    with pytest.raises(ParameterError, match="input mode 'rgbd', not 'rgb'"):
        train(
            config(dataset, run, epochs=2, input_mode="rgb"), resume=True, explicit={"input_mode"}
        )
    with pytest.raises(ParameterError, match="lr"):
        train(config(dataset, run, epochs=2, lr=0.5), resume=True, explicit={"lr"})
    assert (run / "last.pt").read_bytes() == before
    with pytest.raises(OutputError, match="inside the dataset"):
        train(config(dataset, dataset / "run"))


def test_checkpoint_input_mode_and_corruption(dataset, tmp_path):
    run = tmp_path / "run"
    train(config(dataset, run, epochs=1, input_mode="rgb"))
    with pytest.raises(ParameterError, match="input mode 'rgb'"):
        evaluate_checkpoint(run / "best.pt", dataset, input_mode="rgbd")
    # weights of one mode under the configuration of another
    ckpt = torch.load(run / "best.pt", weights_only=True)
    ckpt["model_config"]["input_mode"] = "rgbdm"
    torch.save(ckpt, tmp_path / "mixed.pt")
    with pytest.raises(FormatError, match="3 input channels"):
        load_checkpoint(tmp_path / "mixed.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(FormatError, match="not a readable"):
        load_checkpoint(tmp_path / "junk.pt")
    torch.save({"a": 1}, tmp_path / "foreign.pt")
    with pytest.raises(FormatError, match="not a sparsetools"):
        load_checkpoint(tmp_path / "foreign.pt")
    with pytest.raises(FormatError, match="no such"):
        load_checkpoint(tmp_path / "absent.pt")


def test_bad_config():
    for kw in (
        {"input_mode": "depth"},
        {"loss": "huber"},
        {"optimizer": "lbfgs"},
        {"epochs": 0},
        {"lr": -1.0},
        {"max_steps": 0},
        {"device": "tpu"},
        {"crop": (0, 4)},
    ):
        with pytest.raises(ParameterError):
            TrainConfig(dataset="x", out_dir="y", **kw).validate()


def test_diverged_loss_is_reported(dataset, tmp_path):
    with pytest.raises(
        ParameterError, match="^--lr: training diverged: the l1 loss is .* lower --lr$"
    ):
        train(config(dataset, tmp_path / "run", lr=1e30, optimizer="sgd", epochs=3))


def test_a_task_of_ones_own_runs_through_fit(dataset, tmp_path):
    """The example of docs/train.md ("Your own training task"): fit drives any TrainingTask."""
    from sparsetools.train.epochs import StepResult, TrainingTask, fit
    from sparsetools.train.evaluate import batch_inputs, cap_depth
    from sparsetools.train.loop import prepare_run
    from sparsetools.train.supervised import SupervisedTask

    class NearFirst(SupervisedTask):
        """The L1 loss, with every pixel weighted by 10 m / max(gt, 10 m)."""

        def step(self, batch, state):
            rgb, sparse, extra = batch_inputs(batch, self.device)
            gt = cap_depth(batch["gt"].to(self.device), self.config.max_depth)
            pred = self.model.run(rgb, sparse, **extra)
            valid = gt > 0
            weight = 10.0 / gt.clamp(min=10.0)
            loss = ((pred - gt).abs() * weight)[valid].mean()
            return StepResult(loss, {"loss": float(loss.detach())}, len(rgb))

    def run(out, **kw):
        cfg, ckpt = prepare_run(config(dataset, out, **kw), resume=False, explicit=None)
        task = NearFirst(cfg)
        assert isinstance(task, TrainingTask)
        return fit(task, cfg, ckpt=ckpt)

    s = run(tmp_path / "near", epochs=1)
    assert s.epochs_done == 1 and s.steps == 3 and s.best_metric == "rmse"
    # another loss, another model; the rest of the run is the same
    train(config(dataset, tmp_path / "l1", epochs=1))
    near, l1 = read_rows(tmp_path / "near"), read_rows(tmp_path / "l1")
    assert near[0].keys() == l1[0].keys() and near[0]["train_loss"] != l1[0]["train_loss"]
    assert (tmp_path / "near" / "best.pt").is_file()


# -- data and augmentation -----------------------------------------------------------------------------
def test_dataset_items(dataset):
    ds = DepthDataset(dataset, "train")
    item = ds[0]
    assert item["rgb"].shape == (3, 24, 40) and item["rgb"].dtype == torch.float32
    assert 0 <= float(item["rgb"].min()) and float(item["rgb"].max()) <= 1
    assert item["sparse"].shape == item["gt"].shape == (1, 24, 40)
    sample = ds.reader.sample(0)
    np.testing.assert_array_equal(item["gt"][0].numpy(), sample["gt"])
    np.testing.assert_array_equal(item["sparse"][0].numpy(), sample["sparse"])
    cropped = DepthDataset(dataset, "train", crop=(16, 30))[0]
    np.testing.assert_array_equal(cropped["gt"][0].numpy(), sample["gt"][8:, 5:35])


def test_bottom_centre_crop():
    a = np.arange(6 * 7).reshape(6, 7)
    np.testing.assert_array_equal(bottom_centre_crop(a, 2, 3), a[4:, 2:5])
    np.testing.assert_array_equal(bottom_centre_crop(a, 6, 7), a)
    with pytest.raises(ParameterError):
        bottom_centre_crop(a, 7, 3)


def test_augmentation_is_joint_and_seeded():
    rng = np.random.default_rng(0)
    h, w = 12, 16
    gt = rng.uniform(1, 50, (h, w)).astype(np.float32)
    sparse = np.where(rng.random((h, w)) < 0.3, gt, 0).astype(np.float32)
    # rgb encodes the column index: a flip must move rgb and depth together
    rgb = np.repeat(np.repeat((np.arange(w) * 15)[None, :, None], h, 0), 3, 2).astype(np.uint8)
    flips = 0
    for seed in range(8):
        out = augment_sample(
            rgb,
            sparse,
            gt,
            np.random.default_rng(seed),
            crop=(8, 10),
            scale_range=(1.0, 1.5),
            jitter=0.0,
        )
        r, s, g = out
        assert r.shape == (8, 10, 3) and s.shape == g.shape == (8, 10)
        # nearest resampling: every depth is an original depth divided by the scale factor
        # (the first draw of the generator, see augment_sample)
        scale = np.random.default_rng(seed).uniform(1.0, 1.5)
        err = np.abs(g.ravel()[:, None] * scale - gt.ravel()[None, :]).min(axis=1)
        assert err.max() < 1e-4 * gt.max()
        # sparse stays a subset of gt pixels
        assert np.all((s == 0) | np.isclose(s, g))
        flipped = r[0, 0, 0] > r[0, -1, 0]
        flips += bool(flipped)
        # same generator state, same result
        again = augment_sample(
            rgb,
            sparse,
            gt,
            np.random.default_rng(seed),
            crop=(8, 10),
            scale_range=(1.0, 1.5),
            jitter=0.0,
        )
        for x, y in zip(out, again, strict=True):
            np.testing.assert_array_equal(x, y)
    assert 0 < flips < 8


def test_colour_jitter_touches_rgb_only():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    gt = rng.uniform(1, 50, (6, 8)).astype(np.float32)
    sparse = gt * (rng.random((6, 8)) < 0.5)
    r, s, g = augment_sample(rgb, sparse, gt, np.random.default_rng(3), flip=False, jitter=0.3)
    np.testing.assert_array_equal(g, gt)
    np.testing.assert_array_equal(s, sparse)
    assert r.min() >= 0 and r.max() <= 1
    assert not np.allclose(r, rgb / 255.0)


def test_augmentation_differs_per_epoch(dataset):
    ds = DepthDataset(dataset, "train", augment=True, seed=0)
    a = [ds[i]["rgb"] for i in range(4)]
    ds.set_epoch(1)
    b = [ds[i]["rgb"] for i in range(4)]
    assert any(not torch.equal(x, y) for x, y in zip(a, b, strict=True))
    ds.set_epoch(0)
    assert all(torch.equal(x, ds[i]["rgb"]) for i, x in enumerate(a))


def test_pictures():
    rows = [
        (
            np.zeros((10, 20, 3), np.uint8),
            np.zeros((10, 20)),
            np.full((10, 20), 30.0),
            np.full((10, 20), 40.0),
        )
    ] * 2
    pic = prediction_picture(rows)
    assert pic.dtype == np.uint8 and pic.shape[1] >= 4 * 240
    history = [
        {
            "epoch": e,
            "train_loss": 5.0 / e,
            "val_loss": math.nan if e == 2 else 6.0 / e,
            "rmse": 10.0 / e,
        }
        for e in (1, 2, 3)
    ]
    img = draw_curves(history)
    assert img.ndim == 3 and img.dtype == np.uint8
    # one epoch only (flat ranges) still draws
    assert draw_curves(history[:1]).shape == img.shape
    # values over several decades: logarithmic axis, same picture size
    steep = [
        dict(r, train_loss=100.0 / r["epoch"] ** 4, rmse=50.0 / r["epoch"] ** 3) for r in history
    ]
    assert draw_curves(steep).shape == img.shape
    assert not np.array_equal(draw_curves(steep), img)


def test_worker_error_is_one_line(tmp_path):
    import shutil

    ds = make_dataset(tmp_path / "src", n_seq=2, frames=2, split={"train": 1.0})
    broken = tmp_path / "broken"
    shutil.copytree(ds, broken)
    for png in (broken / "gt").rglob("*.png"):
        png.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    for workers in (0, 1):
        with pytest.raises(FormatError) as info:
            train(config(broken, tmp_path / f"run{workers}", val_split="train", workers=workers))
        message = str(info.value)
        assert "\n" not in message and "Traceback" not in message
        assert "cannot decode" in message or "PNG" in message
