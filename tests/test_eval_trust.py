"""`sparsetools eval` says what it saw (issue 23): prediction holes counted and never clipped in
silence, frames of sequence and KITTI depth-completion trees matched by (sequence, frame), the
frames of either side without a match named, and the results of each evaluated dataset kept in
files of their own.

Each guarantee has a test here that goes red when its guard is disabled (docs/reliability.md
lists the pairs).
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import FormatError
from sparsetools.io.image import write_depth_png
from sparsetools.ops.metrics import depth_metrics
from sparsetools.train.results import evaluate_folders, score_prediction


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_line_error(result, code=1) -> str:
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 or (code == 2 and lines[-1].startswith("Error:")), result.stderr
    return lines[-1]


# -- prediction holes ------------------------------------------------------------------------------
GT = 20.0
PRED = 22.0
H, W = 6, 8


def holed_prediction() -> np.ndarray:
    """22 m everywhere but 3 pixels of 0 (KITTI's "no value") and one NaN."""
    pred = np.full((H, W), PRED, dtype=np.float32)
    pred[0, 0] = pred[2, 3] = pred[5, 7] = 0.0
    pred[4, 1] = np.nan
    return pred


def holed_folders(root: Path) -> tuple[Path, Path]:
    (root / "pred").mkdir(parents=True)
    (root / "gt").mkdir()
    write_depth_png(root / "gt" / "000001.png", np.full((H, W), GT))
    np.save(root / "pred" / "000001.npy", holed_prediction())
    return root / "pred", root / "gt"


def test_holes_are_counted_and_left_out_by_default(tmp_path):
    """--fill none (the default): the 4 holes are left out of the metrics, so a prediction
    that is 2 m off wherever it has a value scores RMSE 2 m. Before, a 0 was clipped to 1 mm
    in silence (each one adds about 1,000 1/km to the iRMSE) and a NaN was refused."""
    pred_dir, gt_dir = holed_folders(tmp_path)
    res = evaluate_folders(pred_dir, gt_dir)
    m = res.metrics
    assert res.fill == "none" and m["n_holes"] == 4 and m["n_pixels"] == H * W - 4
    assert m["rmse"] == pytest.approx(2.0) and m["abs_rel"] == pytest.approx(0.1)
    assert m["irmse"] == pytest.approx(1000 * (1 / GT - 1 / PRED), rel=1e-6)
    assert res.per_image[0]["n_holes"] == 4

    # what the command prints and writes: text, JSON and CSV all carry the count and the choice
    r = run("eval", "--pred", pred_dir, "--gt", gt_dir, "-o", tmp_path / "res.json")
    assert r.exit_code == 0, r.output
    line = next(x for x in r.stdout.splitlines() if x.startswith("n_holes"))
    assert " 4 of 48 ground-truth pixels" in line and "--fill none" in line
    saved = json.loads((tmp_path / "res.json").read_text())
    assert saved["fill"] == "none" and saved["metrics"]["n_holes"] == 4
    assert saved["per_image"][0]["n_holes"] == 4
    with open(tmp_path / "res.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["n_holes"] for r in rows] == ["4", "4"]  # the image, then the total
    r = run("eval", "--pred", pred_dir, "--gt", gt_dir, "--json")
    assert json.loads(r.stdout)["metrics"]["n_holes"] == 4


@pytest.mark.parametrize(
    ("fill", "n_pixels", "rmse"),
    [
        ("none", H * W - 4, 2.0),
        ("nearest", H * W, 2.0),  # every neighbour says 22 m
        ("min-depth", H * W, math.sqrt((44 * 2.0**2 + 4 * (GT - 1e-3) ** 2) / 48)),
    ],
)
def test_each_fill_does_what_it_says_and_is_named(tmp_path, fill, n_pixels, rmse):
    pred_dir, gt_dir = holed_folders(tmp_path)
    r = run("eval", "--pred", pred_dir, "--gt", gt_dir, "--fill", fill, "--json")
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["fill"] == fill and data["metrics"]["n_holes"] == 4
    assert data["metrics"]["n_pixels"] == n_pixels
    assert data["metrics"]["rmse"] == pytest.approx(rmse, rel=1e-6)
    r = run("eval", "--pred", pred_dir, "--gt", gt_dir, "--fill", fill)
    assert f"(--fill {fill})" in r.stdout


def test_min_depth_fill_is_the_old_clipping():
    """--fill min-depth gives exactly what depth_metrics gives a 0 prediction (monodepth2)."""
    pred = holed_prediction()
    gt = np.full((H, W), GT)
    got = score_prediction(pred, gt, fill="min-depth")
    want = depth_metrics(np.nan_to_num(pred, nan=0.0), gt)
    assert got == {**want, "n_holes": 4}


def test_holes_outside_the_ground_truth_are_not_holes():
    pred = holed_prediction()
    gt = np.full((H, W), GT)
    gt[0, 0] = gt[2, 3] = 0.0  # no ground truth there: nothing is missing
    gt[5, 7] = 100.0  # beyond --max-depth: not evaluated either
    assert score_prediction(pred, gt)["n_holes"] == 1


def test_a_prediction_of_holes_only_is_refused(tmp_path):
    (tmp_path / "p").mkdir()
    (tmp_path / "g").mkdir()
    write_depth_png(tmp_path / "g" / "a.png", np.full((4, 5), 10.0))
    write_depth_png(tmp_path / "p" / "a.png", np.zeros((4, 5)))
    with pytest.raises(FormatError, match="every evaluated ground-truth pixel .* hole"):
        evaluate_folders(tmp_path / "p", tmp_path / "g")
    res = evaluate_folders(tmp_path / "p", tmp_path / "g", fill="min-depth")
    assert res.metrics["n_holes"] == 20 and res.metrics["n_pixels"] == 20


def test_fill_is_an_option_of_pred_only(tmp_path):
    r = run("eval", "--checkpoint", tmp_path, tmp_path, "--fill", "nearest")
    assert r.exit_code == 2 and "--fill is for --pred" in r.output


# -- trees and matching ----------------------------------------------------------------------------
def write_tree(root: Path, frames: dict[str, float], shape=(4, 6)) -> Path:
    """``root/<sequence>/<frame>.png`` maps of constant depth."""
    for key, depth in frames.items():
        p = root / f"{key}.png"
        p.parent.mkdir(parents=True, exist_ok=True)
        write_depth_png(p, np.full(shape, depth))
    return root


def test_sequence_trees_are_matched_by_sequence_and_frame(tmp_path):
    """Two sequences with the same frame names: each prediction meets its own ground truth
    (matched by stem alone, a flat reading would mix them or refuse them)."""
    gt = write_tree(tmp_path / "gt", {"seqA/000001": 10.0, "seqB/000001": 40.0, "seqB/000002": 40})
    pred = write_tree(
        tmp_path / "pred", {"seqA/000001": 11.0, "seqB/000001": 44.0, "seqB/000002": 44}
    )
    res = evaluate_folders(pred, gt)
    assert [r["id"] for r in res.per_image] == ["seqA/000001", "seqB/000001", "seqB/000002"]
    assert all(r["abs_rel"] == pytest.approx(0.1) for r in res.per_image)
    assert res.unmatched_predictions == 0 and res.metrics["n_images"] == 3


def test_a_flat_prediction_folder_against_a_tree(tmp_path):
    """Frame names unique across the tree: a flat folder of predictions keeps working."""
    gt = write_tree(tmp_path / "gt", {"seqA/000001": 10.0, "seqB/000002": 40.0})
    pred = write_tree(tmp_path / "pred", {"000001": 11.0, "000002": 44.0})
    res = evaluate_folders(pred, gt)
    assert res.metrics["n_images"] == 2 and res.metrics["abs_rel"] == pytest.approx(0.1)


def test_kitti_depth_completion_tree_as_ground_truth(tmp_path):
    """A KITTI depth-completion tree (``<split>/<drive>/proj_depth/groundtruth/image_02``) is
    read through io/sources: its ground truth, keyed (drive, frame), against a tree of
    predictions ``PRED/<drive>/<frame>.png``."""
    kitti = tmp_path / "kitti_dc"
    for split, drive, value in (
        ("train", "2011_09_26_drive_0001_sync", 10.0),
        ("val", "2011_09_26_drive_0002_sync", 30.0),
    ):
        base = kitti / split / drive / "proj_depth"
        write_tree(base / "groundtruth" / "image_02", {"0000000005": value})
        write_tree(base / "velodyne_raw" / "image_02", {"0000000005": 1.0})  # not the GT
    pred = write_tree(
        tmp_path / "pred",
        {
            "2011_09_26_drive_0001_sync/0000000005": 11.0,
            "2011_09_26_drive_0002_sync/0000000005": 33,
        },
    )
    res = evaluate_folders(pred, kitti)
    assert [r["id"] for r in res.per_image] == [
        "2011_09_26_drive_0001_sync/0000000005",
        "2011_09_26_drive_0002_sync/0000000005",
    ]
    assert res.metrics["abs_rel"] == pytest.approx(0.1)


def test_unmatched_frames_are_named_on_both_sides(tmp_path):
    gt = write_tree(tmp_path / "gt", {"s/01": 10.0, "s/02": 10.0, "s/03": 10.0})
    pred = write_tree(tmp_path / "pred", {"s/01": 11.0, "s/02": 11.0, "s/03": 11, "t/09": 5.0})
    # predictions without ground truth: evaluated without them, counted and named
    r = run("eval", "--pred", pred, "--gt", gt, "--json")
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["unmatched_predictions"] == 1 and data["unmatched_predictions_first"] == ["t/09"]
    r = run("eval", "--pred", pred, "--gt", gt)
    assert any(x.startswith("unmatched") and "t/09" in x for x in r.stdout.splitlines())
    # ground truth without a prediction: refused, the first names of both sides given
    (pred / "s" / "02.png").unlink()
    (pred / "s" / "03.png").unlink()
    r = run("eval", "--pred", pred, "--gt", gt, "-o", tmp_path / "res.json")
    msg = one_line_error(r)
    assert "2 of 3 ground-truth frame(s) have no prediction" in msg
    assert "s/02, s/03" in msg and "t/09" in msg
    assert not (tmp_path / "res.json").exists()


# -- results of each dataset in files of their own -------------------------------------------------
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A one-step run and two datasets: ``a/dataset`` and its copy ``b/other``."""
    from sparsetools.train.config import TrainConfig
    from sparsetools.train.loop import train
    from test_train import make_dataset

    root = tmp_path_factory.mktemp("eval_names")
    ds = make_dataset(root / "a", n_seq=5, frames=2)
    other = root / "b" / "other"
    shutil.copytree(ds, other)
    run_dir = root / "run"
    train(
        TrainConfig(
            dataset=str(ds), out_dir=str(run_dir), width=4, epochs=1, batch_size=4,
            threads=1, pictures=0, max_steps=1,
        )
    )  # fmt: skip
    return run_dir, ds, other


def test_each_dataset_and_split_gets_its_own_results(trained, tmp_path):
    run_src, ds, other = trained
    run_dir = tmp_path / "run"
    shutil.copytree(run_src, run_dir)
    assert run("eval", "--checkpoint", run_dir, ds).exit_code == 0
    assert run("eval", "--checkpoint", run_dir, other).exit_code == 0
    assert run("eval", "--checkpoint", run_dir, other, "--split", "val").exit_code == 0
    r = run("eval", "--checkpoint", run_dir / "last.pt", ds, "--json")
    assert r.exit_code == 0, r.output
    names = sorted(p.name for p in run_dir.glob("eval_*.json"))
    assert names == [
        "eval_dataset_test.json",
        "eval_dataset_test_last.json",
        "eval_other_test.json",
        "eval_other_val.json",
    ]
    first = json.loads((run_dir / "eval_dataset_test.json").read_text())
    assert first["dataset"] == str(ds) and first["split"] == "test"
    assert json.loads((run_dir / "eval_other_test.json").read_text())["dataset"] == str(other)
    assert json.loads(r.stdout)["run_id"] == first["run_id"]  # the run's id, in the results


def test_another_dataset_of_the_same_name_is_refused_not_replaced(trained, tmp_path):
    run_src, ds, _ = trained
    run_dir = tmp_path / "run"
    shutil.copytree(run_src, run_dir)
    twin = tmp_path / "elsewhere" / ds.name  # same folder name, another dataset
    shutil.copytree(ds, twin)
    assert run("eval", "--checkpoint", run_dir, ds).exit_code == 0
    results = run_dir / "eval_dataset_test.json"
    before = results.read_bytes()
    msg = one_line_error(run("eval", "--checkpoint", run_dir, twin))
    assert "eval_dataset_test" in msg and str(twin.resolve()) in msg and "--overwrite" in msg
    assert results.read_bytes() == before
    # -o names the file: the same rule
    assert run("eval", "--checkpoint", run_dir, ds, "-o", tmp_path / "m.json").exit_code == 0
    msg = one_line_error(run("eval", "--checkpoint", run_dir, twin, "-o", tmp_path / "m.json"))
    assert "m.json" in msg and "DATASET" in msg
    # the same dataset again replaces eval's own results; --overwrite replaces another's
    assert run("eval", "--checkpoint", run_dir, ds, "--garg-crop").exit_code == 0
    assert json.loads(results.read_text())["garg_crop"] is True
    assert run("eval", "--checkpoint", run_dir, twin, "--overwrite").exit_code == 0
    assert json.loads(results.read_text())["dataset"] == str(twin)


def test_results_of_other_predictions_are_not_replaced(tmp_path):
    gt = write_tree(tmp_path / "gt", {"s/01": 10.0})
    mine = write_tree(tmp_path / "mine", {"s/01": 11.0})
    theirs = write_tree(tmp_path / "theirs", {"s/01": 12.0})
    assert run("eval", "--pred", mine, "--gt", gt, "-o", tmp_path / "r.json").exit_code == 0
    msg = one_line_error(run("eval", "--pred", theirs, "--gt", gt, "-o", tmp_path / "r.json"))
    assert "--pred" in msg and str(theirs.resolve()) in msg
