"""Issue 24: the metric pose scale, the pose-failure flag, LiDAR dropout / holdout against the
SFE shortcut, and self-supervised model selection without ground truth."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import ParameterError
from sparsetools.train.config import SelfSupSettings, TrainConfig
from sparsetools.train.loop import train
from sparsetools.train.model import DepthCompletionUNet, disparity_to_depth
from sparsetools.train.selfsup.pose_eval import snippet_ate
from sparsetools.train.selfsup.pose_net import (
    POSE_SCALE,
    PoseNet,
    camera_only_initial_depth,
    metric_translation_scale,
)
from sparsetools.train.selfsup.task import (
    METRIC_INITIAL_DEPTH,
    pose_translation_scale,
    split_lidar,
)
from test_selfsup_scene import video, write_video_dataset
from test_train import read_rows


# -- the metric pose scale --------------------------------------------------------------------------
def initial_flow(*, metric: bool, translation_scale: float, seed: int = 0) -> float:
    """Median initial t / z (|translation| over the depth of the target frame) of freshly built
    depth and pose networks on one synthetic triplet."""
    frames = video(3, 64, 96, speed=1.0)
    rgb = [
        torch.from_numpy(f.rgb.transpose(2, 0, 1).astype(np.float32) / 255)[None] for f in frames
    ]
    torch.manual_seed(seed)
    depth_net = DepthCompletionUNet(
        "rgb",
        width=4,
        output="disparity",
        initial_depth=METRIC_INITIAL_DEPTH if metric else None,
    ).eval()
    pose_net = PoseNet(width=4, translation_scale=translation_scale).eval()
    with torch.no_grad():
        depth = disparity_to_depth(depth_net.run(rgb[1], None)[0], 0.1, 100.0)
        _, t = pose_net(rgb[1], rgb[2])
    return float(t.norm() / depth.median())


def test_metric_runs_start_with_the_camera_only_initial_flow():
    camera = initial_flow(metric=False, translation_scale=POSE_SCALE)
    settings = SelfSupSettings(sparse_loss="silog")
    metric = initial_flow(metric=True, translation_scale=pose_translation_scale(settings))
    assert 0.5 < metric / camera < 2, (metric, camera)
    # with monodepth2's 0.01 on a metric run the initial flow is ~50x too small (the bug)
    legacy = initial_flow(metric=True, translation_scale=POSE_SCALE)
    assert camera / legacy > 20


def test_the_translation_scale_follows_from_the_initial_depth():
    assert camera_only_initial_depth((0.1, 100.0)) == pytest.approx(1 / (0.01 + 0.5 * 9.99))
    assert metric_translation_scale(10.0, (0.1, 100.0)) == pytest.approx(
        0.01 * 10.0 * (0.01 + 0.5 * 9.99)
    )
    assert pose_translation_scale(SelfSupSettings()) == POSE_SCALE  # camera only
    assert pose_translation_scale(SelfSupSettings(sparse_loss="l1")) == pytest.approx(0.5005)
    assert (
        pose_translation_scale(SelfSupSettings(sparse_loss="l1", pose_translation_scale=0.2)) == 0.2
    )
    # the rotation keeps 0.01; only the translation scales
    torch.manual_seed(1)
    a = PoseNet(width=4)
    torch.manual_seed(1)
    b = PoseNet(width=4, translation_scale=0.5)
    x, y = torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        (ra, ta), (rb, tb) = a(x, y), b(x, y)
    assert torch.equal(ra, rb) and torch.allclose(tb, 50 * ta, rtol=1e-6)
    assert b.config()["translation_scale"] == 0.5 and "translation_scale" not in a.config()
    with pytest.raises(ParameterError, match="translation scale"):
        PoseNet(width=4, translation_scale=0.0)


def test_settings_before_04_keep_their_meaning():
    old = SelfSupSettings.from_dict({"sparse_loss": "silog"})
    assert old.pose_translation_scale == 0.01 and old.select_by == "gt"
    new = SelfSupSettings.from_dict(SelfSupSettings(sparse_loss="silog").to_dict())
    assert new.pose_translation_scale is None and new.select_by == "photometric"
    cfg = {"dataset": "d", "out_dir": "o", "input_mode": "rgb", "lidar_encoder": "sfe"}
    assert TrainConfig.from_dict(cfg).lidar_scales == (1, 2, 4, 8, 16)
    assert TrainConfig.from_dict({**cfg, "lidar_scales": [2, 4]}).lidar_scales == (2, 4)
    assert TrainConfig(dataset="d", out_dir="o").lidar_scales == (2, 4, 8, 16)


# -- ATE figures ------------------------------------------------------------------------------------
def test_unscaled_and_standing_still_ate():
    g = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2], [0, 0, 3], [0, 0, 4.0]])
    assert snippet_ate(g / 2, g) == pytest.approx(0.0, abs=1e-12)  # up to scale: perfect
    # as predicted: half the motion is off by g / 2
    assert snippet_ate(g / 2, g, scaled=False) == pytest.approx(np.sqrt((g**2).sum() / 4) / 5)
    still = snippet_ate(np.zeros_like(g), g, scaled=False)
    assert still == pytest.approx(np.sqrt((g**2).sum()) / 5)
    # no prediction, however wrong its direction, does worse than standing still once scaled
    rng = np.random.default_rng(0)
    for _ in range(20):
        p = np.cumsum(rng.normal(size=(5, 3)), axis=0)
        assert snippet_ate(p, g) <= still + 1e-12


# -- LiDAR dropout and holdout ----------------------------------------------------------------------
def sparse_batch(seed=0, b=4, h=16, w=24):
    g = torch.Generator().manual_seed(seed)
    depth = 5 + 20 * torch.rand(b, 1, h, w, generator=g)
    return torch.where(torch.rand(b, 1, h, w, generator=g) < 0.3, depth, torch.zeros_like(depth))


def test_split_lidar_holdout_gives_disjoint_sets_that_cover_every_point():
    sparse = sparse_batch()
    same = split_lidar(sparse, dropout=0.0, holdout=0.0, seed=0, step=0)
    assert same[0] is sparse and same[1] is sparse
    fractions = []
    for step in range(20):
        lidar_input, target = split_lidar(sparse, dropout=0.0, holdout=0.3, seed=5, step=step)
        assert not ((lidar_input > 0) & (target > 0)).any()  # disjoint
        assert torch.equal(lidar_input + target, sparse)  # together: every point, unchanged
        fractions.append(float((target > 0).sum() / (sparse > 0).sum()))
        again = split_lidar(sparse, dropout=0.0, holdout=0.3, seed=5, step=step)
        assert torch.equal(again[0], lidar_input)  # a function of (seed, step)
    assert abs(np.mean(fractions) - 0.3) < 0.03
    other = split_lidar(sparse, dropout=0.0, holdout=0.3, seed=6, step=0)
    assert not torch.equal(
        other[0], split_lidar(sparse, dropout=0.0, holdout=0.3, seed=5, step=0)[0]
    )


def test_lidar_dropout_empties_the_input_of_a_fraction_of_batches():
    sparse = sparse_batch(1)
    dropped = []
    for step in range(200):
        lidar_input, target = split_lidar(sparse, dropout=0.25, holdout=0.0, seed=2, step=step)
        assert torch.equal(target, sparse)  # the loss keeps every point
        empty = not lidar_input.any()
        assert empty or torch.equal(lidar_input, sparse)
        dropped.append(empty)
    assert 0.15 < np.mean(dropped) < 0.35


def test_a_dropped_batch_runs_the_camera_only_network_exactly():
    sparse = sparse_batch(2, b=2, h=32, w=48)
    rgb = torch.rand(2, 3, 32, 48, generator=torch.Generator().manual_seed(3))
    torch.manual_seed(4)
    camera = DepthCompletionUNet("rgb", width=4, output="disparity").eval()
    torch.manual_seed(4)
    fused = DepthCompletionUNet("rgb", width=4, output="disparity", lidar_encoder="sfe").eval()
    step = next(
        k
        for k in range(100)
        if not split_lidar(sparse, dropout=0.5, holdout=0, seed=0, step=k)[0].any()
    )
    lidar_input, _ = split_lidar(sparse, dropout=0.5, holdout=0.0, seed=0, step=step)
    with torch.no_grad():
        want = camera.run(rgb, None)
        got = fused.run(rgb, lidar_input)
        kept = fused.run(rgb, sparse)
    assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))
    assert (kept[0] - want[0]).abs().max() > 0  # the branch does act when it has points


def test_dropout_and_holdout_are_refused_where_they_mean_nothing():
    def cfg(**selfsup):
        return TrainConfig(
            dataset="d", out_dir="o", input_mode="rgb", selfsup=SelfSupSettings(**selfsup)
        )

    with pytest.raises(ParameterError, match="LiDAR input") as err:
        cfg(lidar_dropout=0.2, sparse_loss="l1").validate()
    assert err.value.param == "lidar_dropout"
    with pytest.raises(ParameterError, match="add --sparse-loss"):
        TrainConfig(
            dataset="d",
            out_dir="o",
            input_mode="rgbd",
            selfsup=SelfSupSettings(lidar_holdout=0.5),
        ).validate()
    for bad in (dict(lidar_dropout=1.0), dict(lidar_holdout=-0.1), dict(select_by="rmse")):
        with pytest.raises(ParameterError):
            SelfSupSettings(**bad).validate()


# -- model selection without ground truth, the pose-failure flag ------------------------------------
@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("pose_scale")
    seqs = {
        f"s{i}": video(6, 32, 48, speed=0.5 + 0.15 * i, yaw_rate=0.01 * (i - 2), start=2.0 * i)
        for i in range(4)
    }
    splits = {"s0": "train", "s1": "train", "s2": "train", "s3": "val"}
    return {
        "gt": write_video_dataset(root / "gt", seqs, splits),
        "no_gt": write_video_dataset(root / "no_gt", seqs, splits, gt=False),
    }


def config(dataset, out, **selfsup) -> TrainConfig:
    return TrainConfig(
        dataset=str(dataset),
        out_dir=str(out),
        input_mode="rgbd",
        width=4,
        epochs=3,
        batch_size=4,
        lr=1e-3,
        threads=1,
        pictures=0,
        selfsup=SelfSupSettings(pose_width=4, sparse_loss="silog", **selfsup),
    )


def test_a_dataset_without_ground_truth_trains_and_selects(datasets, tmp_path):
    summary = train(config(datasets["no_gt"], tmp_path / "run"))
    rows = read_rows(tmp_path / "run")
    assert summary.best_metric == "photometric" and summary.extras["selected_by"] == "photometric"
    pe = [float(r["photometric"]) for r in rows]
    assert summary.best_epoch == 1 + int(np.argmin(pe)) and summary.best_value == min(pe)
    assert all(math.isnan(float(r["rmse"])) for r in rows)  # nothing GT-based was computed
    # --select-by gt needs the ground truth it asks for
    with pytest.raises(ParameterError, match="select-by gt"):
        train(config(datasets["no_gt"], tmp_path / "gt_run", select_by="gt"))


def test_selection_by_photometric_loss_ignores_the_ground_truth(datasets, tmp_path):
    by_pe = train(config(datasets["gt"], tmp_path / "pe"))
    by_gt = train(config(datasets["gt"], tmp_path / "gt", select_by="gt"))
    rows = read_rows(tmp_path / "pe")
    assert rows == read_rows(tmp_path / "gt")  # the same training either way
    assert by_pe.best_epoch == 1 + int(np.argmin([float(r["photometric"]) for r in rows]))
    assert by_gt.best_epoch == 1 + int(np.argmin([float(r["rmse"]) for r in rows]))
    assert by_gt.best_metric == "rmse" and by_gt.extras["selected_by"] == "gt"
    saved = json.loads((tmp_path / "pe" / "config.json").read_text())
    assert saved["selfsup"]["select_by"] == "photometric"


def test_pose_failure_is_flagged_in_the_log_and_the_summary(datasets, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="sparsetools.train.selfsup.task"):
        strict = train(config(datasets["gt"], tmp_path / "strict", pose_failure_ratio=1e-6))
    rows = read_rows(tmp_path / "strict")
    last = rows[-1]
    ratio = float(last["ate"]) / float(last["ate_still"])
    assert 0 < ratio <= 1 and float(last["ate_unscaled"]) >= 0
    assert strict.extras["pose_failure"] is True
    assert strict.extras["pose_ate_ratio"] == pytest.approx(ratio, abs=1e-4)
    assert any("pose failure" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sparsetools.train.selfsup.task"):
        lenient = train(config(datasets["gt"], tmp_path / "lenient", pose_failure_ratio=1.0))
    assert lenient.extras["pose_failure"] is False
    assert not any("pose failure" in r.getMessage() for r in caplog.records)


def test_cli_options_and_their_errors(datasets, tmp_path):
    runner = CliRunner()
    common = ["--width", "4", "--pose-width", "4", "--batch-size", "4", "--epochs", "1",
              "--threads", "1", "--self-supervised", "--sparse-loss", "silog"]  # fmt: skip
    run = tmp_path / "run"
    r = runner.invoke(
        cli,
        ["train", str(datasets["gt"]), "-o", str(run), "--lidar-encoder", "sfe",
         "--lidar-scales", "4,16", "--lidar-holdout", "0.5", "--lidar-dropout", "0.2",
         "--select-by", "gt", *common, "--json"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    saved = json.loads((run / "config.json").read_text())
    assert saved["lidar_scales"] == [4, 16]
    assert saved["selfsup"]["lidar_holdout"] == 0.5 and saved["selfsup"]["select_by"] == "gt"
    assert json.loads(r.stdout)["selected_by"] == "gt"
    for bad in ("3", "2,2", "16,4", "0"):
        r = runner.invoke(
            cli,
            ["train", str(datasets["gt"]), "-o", str(tmp_path / f"bad{bad}"),
             "--lidar-encoder", "sfe", "--lidar-scales", bad, *common],
        )  # fmt: skip
        assert r.exit_code != 0 and "lidar" in r.output.lower() and "Traceback" not in r.output
        assert not (tmp_path / f"bad{bad}").exists()
