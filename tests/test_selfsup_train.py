"""Self-supervised training: determinism, exact resume, run folder, CLI, eval protocol, real data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import ParameterError
from sparsetools.ops.metrics import METRIC_NAMES
from sparsetools.train.checkpoint import load_checkpoint
from sparsetools.train.config import SelfSupSettings, TrainConfig
from sparsetools.train.evaluate import evaluate_checkpoint
from sparsetools.train.loop import train
from test_selfsup_scene import video, write_video_dataset
from test_train import read_rows, state_equal


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("selfsup_ds")
    seqs = {
        f"s{i}": video(6, 32, 48, speed=0.5 + 0.15 * i, yaw_rate=0.01 * (i - 2), start=2.0 * i)
        for i in range(5)
    }
    splits = {"s0": "train", "s1": "train", "s2": "train", "s3": "val", "s4": "test"}
    return write_video_dataset(root / "ds", seqs, splits)


def config(dataset, out, **kw) -> TrainConfig:
    selfsup = kw.pop("selfsup", {})
    base = dict(
        dataset=str(dataset),
        out_dir=str(out),
        input_mode="rgb",
        width=4,
        epochs=2,
        batch_size=4,
        lr=1e-3,
        threads=1,
        pictures=1,
        selfsup=SelfSupSettings(pose_width=4, **selfsup),
    )
    base.update(kw)
    return TrainConfig(**base)


# -- determinism and resume -------------------------------------------------------------------------
def test_same_seed_same_metrics_and_weights(dataset, tmp_path):
    night = {"mcie": True, "sbm": True}
    s1 = train(config(dataset, tmp_path / "a", selfsup=night))
    s2 = train(config(dataset, tmp_path / "b", selfsup=night))
    rows = read_rows(tmp_path / "a")
    assert len(rows) == 2 and rows == read_rows(tmp_path / "b")
    # best.pt by the validation photometric loss (the default: no ground truth read for it)
    assert s1.self_supervised and s1.best_metric == "photometric"
    assert s1.best_value == s2.best_value == min(float(r["photometric"]) for r in rows)
    a, b = load_checkpoint(tmp_path / "a" / "last.pt"), load_checkpoint(tmp_path / "b" / "last.pt")
    assert a.kind == "self-supervised"
    assert state_equal(a.model, b.model) and state_equal(a.pose_model, b.pose_model)
    assert a.sbm_threshold is not None and a.sbm_threshold == b.sbm_threshold
    # camera only: median-scaled validation metrics, logged in the rows
    assert rows[0]["median_scaling"] == "1" and float(rows[0]["abs_rel"]) > 0
    train(config(dataset, tmp_path / "c", seed=1, selfsup=night))
    assert read_rows(tmp_path / "c") != rows


def test_resume_is_exact_at_epoch_end_and_mid_epoch(dataset, tmp_path):
    kw = dict(selfsup={"sbm": True, "sparse_loss": "silog"}, input_mode="rgbd")
    train(config(dataset, tmp_path / "full", **kw))
    full_rows = read_rows(tmp_path / "full")
    full = load_checkpoint(tmp_path / "full" / "last.pt")
    # 12 training triplets / batch 4 = 3 steps per epoch
    train(config(dataset, tmp_path / "half", epochs=1, **kw))
    train(config(dataset, tmp_path / "half", **kw), resume=True)
    cut = train(config(dataset, tmp_path / "cut", max_steps=4, **kw))
    assert cut.steps == 4 and cut.epochs_done == 1
    train(config(dataset, tmp_path / "cut", **kw), resume=True)
    for name in ("half", "cut"):
        assert read_rows(tmp_path / name) == full_rows, name
        ckpt = load_checkpoint(tmp_path / name / "last.pt")
        assert state_equal(ckpt.model, full.model) and state_equal(ckpt.pose_model, full.pose_model)
        assert ckpt.sbm_threshold == full.sbm_threshold and ckpt.state.step == 6
        ma, mb = ckpt.optimizer["state"], full.optimizer["state"]
        assert all(torch.equal(ma[k]["exp_avg_sq"], mb[k]["exp_avg_sq"]) for k in ma)


@pytest.mark.slow
def test_workers_do_not_change_results(dataset, tmp_path):
    train(config(dataset, tmp_path / "w0", epochs=1, workers=0, selfsup={"mcie": True}))
    train(config(dataset, tmp_path / "w2", epochs=1, workers=2, selfsup={"mcie": True}))
    assert read_rows(tmp_path / "w0") == read_rows(tmp_path / "w2")


def test_resume_keeps_the_kind_and_settings(dataset, tmp_path):
    run = tmp_path / "run"
    train(config(dataset, run, epochs=1))
    with pytest.raises(ParameterError, match="sparse_loss"):
        train(
            config(dataset, run, selfsup={"sparse_loss": "l1"}),
            resume=True,
            explicit={"selfsup.sparse_loss"},
        )
    supervised = TrainConfig(
        dataset=str(dataset), out_dir=str(run), input_mode="rgb", width=4, epochs=2
    )
    with pytest.raises(ParameterError, match="self-supervised run"):
        train(supervised, resume=True, explicit={"self_supervised"})
    # without naming them, the run's own settings continue
    s = train(supervised, resume=True, explicit=set())
    assert s.self_supervised and s.epochs_done == 2 and s.steps == 6


def test_bad_settings():
    for kw in (
        {"sparse_loss": "l2"},
        {"scales": 5},
        {"depth_range": (10.0, 1.0)},
        {"sbm_beta": 1.0},
        {"sbm_percentile": 120.0},
        {"silog_lambda": 2.0},
    ):
        with pytest.raises(ParameterError):
            SelfSupSettings(**kw).validate()
    with pytest.raises(ParameterError, match="final"):
        TrainConfig(
            dataset="x", out_dir="y", final_layer=True, selfsup=SelfSupSettings()
        ).validate()


def test_too_small_images_are_refused(tmp_path):
    ds = write_video_dataset(tmp_path / "ds", {"a": video(4, 8, 8)}, {"a": "train"})
    with pytest.raises(ParameterError, match="too small"):
        train(config(ds, tmp_path / "run", val_split="train"))


# -- evaluation protocol ---------------------------------------------------------------------------
def test_eval_median_scaling_and_pose(dataset, tmp_path):
    cam = tmp_path / "cam"
    train(config(dataset, cam, epochs=1))
    res = evaluate_checkpoint(cam / "best.pt", dataset, split="test")
    assert res.kind == "self-supervised" and res.median_scaling
    assert all(r["scale"] > 0 for r in res.per_image)
    assert res.pose is not None and res.pose.n_snippets == 2 and res.pose.ate_mean >= 0
    unscaled = evaluate_checkpoint(cam / "best.pt", dataset, split="test", median_scaling=False)
    assert not unscaled.median_scaling and unscaled.metrics["abs_rel"] != res.metrics["abs_rel"]
    lidar = tmp_path / "lidar"
    train(config(dataset, lidar, epochs=1, input_mode="rgbd", selfsup={"sparse_loss": "silog"}))
    res = evaluate_checkpoint(lidar / "best.pt", dataset, split="test")
    assert not res.median_scaling and "scale" not in res.per_image[0]


def test_cli_train_and_eval(dataset, tmp_path):
    run = tmp_path / "run"
    runner = CliRunner()
    common = [
        "--width",
        "4",
        "--pose-width",
        "4",
        "--batch-size",
        "4",
        "--epochs",
        "1",
        "--threads",
        "1",
    ]
    r = runner.invoke(
        cli,
        [
            "train",
            str(dataset),
            "-o",
            str(run),
            "--input",
            "rgb",
            "--self-supervised",
            *common,
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert (
        summary["mode"] == "self-supervised"
        and summary["epochs_done"] == 1
        and "best_photometric" in summary
        and summary["selected_by"] == "photometric"
    )
    # true poses in the validation split: the run says whether its pose network learnt
    assert isinstance(summary["pose_failure"], bool) and 0 <= summary["pose_ate_ratio"] <= 1
    saved = json.loads((run / "config.json").read_text())
    assert saved["selfsup"]["sparse_loss"] == "none" and saved["selfsup"]["pose_width"] == 4
    for name in ("metrics.csv", "last.pt", "best.pt", "curves.png", "predictions/epoch_001.png"):
        assert (run / name).is_file(), name
    r = runner.invoke(
        cli, ["eval", "--checkpoint", str(run / "best.pt"), str(dataset), "--split", "test"]
    )
    assert r.exit_code == 0, r.output
    assert "median" in r.output and "pose ATE" in r.output
    for name in METRIC_NAMES:  # every metric of ops.metrics, log10 (BTS) included when present
        assert name in r.output
    data = json.loads((run / f"eval_{Path(dataset).name}_test.json").read_text())
    assert data["median_scaling"] is True and data["kind"] == "self-supervised"
    assert data["pose"]["snippet_length"] == 5
    r = runner.invoke(
        cli,
        [
            "eval",
            "--checkpoint",
            str(run),
            str(dataset),
            "--split",
            "test",
            "--scaling",
            "none",
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["median_scaling"] is False
    # a self-supervised option without --self-supervised is a usage error
    r = runner.invoke(cli, ["train", str(dataset), "-o", str(tmp_path / "x"), "--sbm"])
    assert r.exit_code == 2 and "--self-supervised" in r.output
    # resuming with the mode's settings works without repeating --self-supervised
    r = runner.invoke(
        cli, ["train", str(dataset), "-o", str(run), "--resume", "--epochs", "2", "--json"]
    )
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["epochs_done"] == 2


# -- real data ---------------------------------------------------------------------------------------
@pytest.mark.real
def test_real_kitti_sequence_photometric_loss_falls(real_dir, tmp_path):
    """The 11 real KITTI frames (one drive, images only: camera-only training) for a few steps:
    the photometric loss on the training triplets falls."""
    import cv2

    from sparsetools.io.calib import load_calibration

    seq = real_dir / "kitti-raw-sequence-2011_09_26"
    names = sorted(p.stem for p in (seq / "image_02" / "data").glob("*.png"))
    assert len(names) == 11
    calib = load_calibration(seq)
    h, w = 48, 160  # every frame resized by about 1/7.8 (KITTI's aspect), intrinsics alike
    sx, sy = w / 1242, h / 375
    K = np.array(calib.K, np.float64)
    K = np.array(
        [
            [K[0, 0] * sx, 0, sx * (K[0, 2] + 0.5) - 0.5],
            [0, K[1, 1] * sy, sy * (K[1, 2] + 0.5) - 0.5],
            [0, 0, 1],
        ]
    )
    frames = []
    from test_selfsup_scene import Frame

    for name in names:
        rgb = cv2.imread(str(seq / "image_02" / "data" / f"{name}.png"))[:, :, ::-1]
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        frames.append(Frame(rgb, np.zeros((h, w), np.float32), K, np.eye(4), int(name)))
    ds = write_video_dataset(
        tmp_path / "ds", {"drive": frames}, {"drive": "train"}, poses=False, gt=False
    )
    run = tmp_path / "run"
    cfg = TrainConfig(
        dataset=str(ds),
        out_dir=str(run),
        input_mode="rgb",
        width=8,
        epochs=6,
        batch_size=3,
        lr=1e-3,
        threads=2,
        pictures=0,
        val_split="train",
        jitter=0.0,
        selfsup=SelfSupSettings(pose_width=8),
    )
    summary = train(cfg)
    rows = read_rows(run)
    assert summary.best_metric == "photometric"  # no ground truth: best by photometric loss
    # monodepth2's photometric loss of the training batches, first epoch vs last
    first, last = float(rows[0]["train_photometric"]), float(rows[-1]["train_photometric"])
    assert last < 0.9 * first, [r["train_photometric"] for r in rows]
