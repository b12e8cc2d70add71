"""Pose evaluation (ATE over 5-frame snippets, monodepth2's protocol) and eval records."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sparsetools.errors import ParameterError
from sparsetools.train.evaluate import EvalResult
from sparsetools.train.selfsup.pose_eval import (
    evaluate_pose,
    snippet_ate,
    snippet_positions,
)
from test_selfsup_scene import video, write_video_dataset


def translation(x, y, z):
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def test_snippet_positions_follow_the_camera():
    # the camera moves 1 m forward per frame: points move 1 m backwards in the next camera
    positions = snippet_positions([translation(0, 0, -1.0)] * 4)
    np.testing.assert_allclose(positions, [[0, 0, k] for k in range(5)], atol=1e-12)
    # a 90 degree turn to the right (about +y) after the first step, then 1 m forward
    turn = np.eye(4)
    turn[:3, :3] = [[0, 0, -1], [0, 1, 0], [1, 0, 0]]  # points of camera k in camera k+1
    positions = snippet_positions([translation(0, 0, -1.0), turn, translation(0, 0, -1.0)])
    np.testing.assert_allclose(positions[-1], [1, 0, 1], atol=1e-12)


def test_snippet_ate_hand_values():
    true = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2.0]])
    assert snippet_ate(3.0 * true, true) == pytest.approx(0.0, abs=1e-12)  # scale is free
    # s = (0 + 1 + 2) / (0 + 1 + 1) = 1.5; errors 0, 0.5, -0.5 -> sqrt(0.5) / 3 (monodepth2)
    pred = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 1.0]])
    assert snippet_ate(pred, true) == pytest.approx(math.sqrt(0.5) / 3, rel=1e-12)
    # the first frames are aligned: an offset of the whole prediction changes nothing
    assert snippet_ate(pred + np.array([5, -2, 1]), true) == pytest.approx(
        math.sqrt(0.5) / 3, rel=1e-12
    )
    with pytest.raises(ParameterError):
        snippet_ate(pred[:, :2], true[:, :2])


class FixedMotion(torch.nn.Module):
    """A stand-in pose network that predicts the same motion for every pair of frames."""

    def __init__(self, T):
        super().__init__()
        self.T = torch.as_tensor(T, dtype=torch.float64)

    def transform(self, a, b):
        return self.T.expand(len(a), 4, 4)


def test_evaluate_pose_on_a_straight_drive(tmp_path):
    # 0.8 m per frame straight ahead, no turn (the helper's sideways sway off)
    frames = video(7, 16, 24, speed=0.8)
    for k, f in enumerate(frames):
        f.T_world_cam = translation(0, 0, 0.8 * k)
    ds = write_video_dataset(
        tmp_path / "ds", {"a": frames, "b": frames[:4]}, {"a": "test", "b": "test"}
    )
    exact = evaluate_pose(
        FixedMotion(translation(0, 0, -0.8)), ds, split="test", device=torch.device("cpu")
    )
    # 7 frames: 3 snippets of 5; the 4-frame sequence has none
    assert exact.n_snippets == 3 and exact.n_sequences == 1 and exact.snippet_length == 5
    assert exact.ate_mean == pytest.approx(0.0, abs=1e-12)
    scaled = evaluate_pose(
        FixedMotion(translation(0, 0, -0.1)), ds, split="test", device=torch.device("cpu")
    )
    assert scaled.ate_mean == pytest.approx(0.0, abs=1e-12)  # camera-only: up to scale
    sideways = evaluate_pose(
        FixedMotion(translation(-0.8, 0, 0)), ds, split="test", device=torch.device("cpu")
    )
    # predicted positions (k, 0, 0) against (0, 0, 0.8 k): the best scale is 0, ATE = |g| / 5
    g = np.array([[0, 0, 0.8 * k] for k in range(5)])
    assert sideways.ate_mean == pytest.approx(np.sqrt((g**2).sum()) / 5, rel=1e-9)
    # no poses in the manifest: no pose evaluation
    ds2 = write_video_dataset(tmp_path / "np", {"a": frames}, {"a": "test"}, poses=False)
    assert (
        evaluate_pose(FixedMotion(np.eye(4)), ds2, split="test", device=torch.device("cpu")) is None
    )


def test_eval_result_to_dict():
    res = EvalResult(
        metrics={"abs_rel": 0.1},
        per_image=[],
        garg_crop=False,
        min_depth=1e-3,
        max_depth=80.0,
        median_scaling=True,
        checkpoint="run/best.pt",
        kind="self-supervised",
        input_mode="rgb",
        epoch=3,
        dataset="ds",
        split="test",
    )
    d = res.to_dict()
    assert (
        d["median_scaling"] is True and d["epoch"] == 3 and "pred_dir" not in d and "pose" not in d
    )
    folders = EvalResult(
        metrics={},
        per_image=[],
        garg_crop=False,
        min_depth=1e-3,
        max_depth=80.0,
        pred_dir="p",
        gt_dir="g",
        unmatched_predictions=0,
    )
    d = folders.to_dict()
    assert "epoch" not in d and "checkpoint" not in d and d["unmatched_predictions"] == 0


def test_evaluate_folders_median_scaling(tmp_path):
    from sparsetools.io.image import write_depth_png
    from sparsetools.ops.metrics import depth_metrics
    from sparsetools.train.evaluate import evaluate_folders

    rng = np.random.default_rng(0)
    (tmp_path / "p").mkdir()
    (tmp_path / "g").mkdir()
    gt = rng.uniform(2, 60, (8, 10))
    write_depth_png(tmp_path / "g" / "a.png", gt)
    write_depth_png(tmp_path / "p" / "a.png", gt / 7.0)  # right up to a scale of 1/7
    res = evaluate_folders(tmp_path / "p", tmp_path / "g", median_scaling=True)
    assert res.median_scaling and res.per_image[0]["scale"] == pytest.approx(7.0, rel=1e-2)
    assert res.metrics["abs_rel"] < 0.01
    ref = depth_metrics(np.round(gt / 7 * 256) / 256, np.round(gt * 256) / 256, median_scaling=True)
    assert res.metrics["abs_rel"] == pytest.approx(ref["abs_rel"], rel=1e-6)
    plain = evaluate_folders(tmp_path / "p", tmp_path / "g")
    assert not plain.median_scaling and plain.metrics["abs_rel"] > 0.8
