"""`sparsetools predict`: a trained checkpoint's depth maps as KITTI PNGs, in the sequence tree
and in KITTI depth completion's submission layout; read back by `eval --pred` and the DC reader."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from _cli import one_line_error, run, summary
from sparsetools.cli.main import cli
from sparsetools.io.dataset_reader import DatasetReader
from sparsetools.io.image import read_depth_png, write_depth_png, write_image
from test_train import make_dataset
from test_train_inputs import make_confidence_dataset

TINY = ["--width", "4", "--batch-size", "4", "--epochs", "1", "--threads", "1", "--pictures", "1"]
DRIVES = ("2011_09_26_drive_0002_sync", "2011_09_28_drive_0037_sync")
DC_W, DC_H = 1216, 352


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("predict")
    ds = make_dataset(root, n_seq=5, frames=2)
    r = run("train", ds, "-o", root / "run", *TINY)
    assert r.exit_code == 0, r.output
    return ds, root / "run" / "best.pt"


def _reference_depth(ckpt: Path, ds: Path, split: str) -> dict[str, np.ndarray]:
    """The network's depth of every sample, one by one (no batching), independent of predict."""
    from sparsetools.train.checkpoint import load_checkpoint, model_from_checkpoint

    model = model_from_checkpoint(load_checkpoint(ckpt)).eval()
    reader = DatasetReader(ds).split(split)
    out = {}
    with torch.no_grad():
        for i in range(len(reader)):
            s = reader.sample(i)
            rgb = torch.from_numpy(s["rgb"].astype(np.float32) / 255).permute(2, 0, 1)[None]
            sparse = torch.from_numpy(s["sparse"])[None, None]
            out[s["id"]] = model.depth_of(rgb, sparse)[0, 0].numpy()
    return out


def test_predict_writes_one_uint16_map_per_frame_and_reruns_as_a_no_op(trained, tmp_path):
    ds, ckpt = trained
    out = tmp_path / "pred"
    s = summary("predict", ckpt, ds, "-o", out, "--split", "test", "--batch-size", "3")
    reader = DatasetReader(ds).split("test")
    rows = reader.manifest.to_pylist()
    assert s["frames"] == s["processed"] == len(rows) > 0
    assert s["holes"] == 0 and s["clipped"] == 0 and s["kind"] == "supervised"
    written = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.png"))
    assert written == sorted(f"{r['sequence']}/{r['frame']}.png" for r in rows)
    ref = _reference_depth(ckpt, ds, "test")
    for r in rows:
        raw = cv2.imread(str(out / r["sequence"] / f"{r['frame']}.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (r["height"], r["width"])
        # depth x 256 rounded: within half a step of the unbatched network (plus float noise)
        assert np.abs(raw / 256.0 - ref[r["id"]]).max() <= 0.5 / 256 + 1e-4
        assert raw.min() > 0  # every pixel holds a prediction
    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*.png")}
    again = summary("predict", ckpt, ds, "-o", out, "--split", "test")
    assert again["processed"] == 0 and again["skipped_existing"] == len(rows)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.png")} == mtimes
    r = run("predict", ckpt, ds, "-o", out, "--split", "val")  # another split: refused
    assert "--split" in one_line_error(r)


def test_eval_of_the_predictions_equals_eval_of_the_checkpoint(trained, tmp_path):
    """`predict` then `eval --pred` gives `eval --checkpoint`'s metrics. The PNG stores depth
    to the nearest 1/256 m, so each predicted value moves by at most e = 1/512 m: RMSE and MAE
    (metres) by at most e, AbsRel by at most e / min(gt); the delta thresholds may flip for
    a pixel within e of 1.25^k gt, so they get one pixel's share."""
    ds, ckpt = trained
    out = tmp_path / "pred"
    assert run("predict", ckpt, ds, "-o", out).exit_code == 0
    reader = DatasetReader(ds).split("test")
    gt_tree = tmp_path / "gt"
    gt_min, n_px = np.inf, np.inf
    for i in range(len(reader)):
        s = reader.sample(i)
        write_depth_png(gt_tree / s["sequence"] / f"{s['frame']}.png", s["gt"])
        valid = s["gt"][(s["gt"] > 1e-3) & (s["gt"] < 80)]
        gt_min, n_px = min(gt_min, float(valid.min())), min(n_px, valid.size)
    by_pred = summary("eval", "--pred", out, "--gt", gt_tree)
    by_ckpt = summary("eval", "--checkpoint", ckpt, ds, "--split", "test", "-o", tmp_path / "e")
    a, b = by_pred["metrics"], by_ckpt["metrics"]
    e = 0.5 / 256 + 1e-5
    assert a["n_holes"] == 0 and by_pred["unmatched_predictions"] == 0
    assert a["n_pixels"] == b["n_pixels"]
    assert a["rmse"] == pytest.approx(b["rmse"], abs=e)
    assert a["mae"] == pytest.approx(b["mae"], abs=e)
    assert a["abs_rel"] == pytest.approx(b["abs_rel"], abs=e / gt_min)
    assert a["delta1"] == pytest.approx(b["delta1"], abs=1.0 / n_px + 1e-9)


def _split_gt_tree(ds: Path, split: str, out: Path) -> Path:
    reader = DatasetReader(ds).split(split)
    for i in range(len(reader)):
        s = reader.sample(i)
        write_depth_png(out / s["sequence"] / f"{s['frame']}.png", s["gt"])
    return out


def test_self_supervised_checkpoint_predicts_relative_depth(tmp_path):
    """A camera-only self-supervised model: predict writes its unscaled depth and says so;
    eval --pred --scaling median then gives eval --checkpoint's (median-scaled) metrics. An
    untrained one predicts ~0.2 m everywhere, where 1/256 m PNG steps are 2 % errors: the
    float32 .npy maps (--format npy) agree to float precision, the PNGs only to 2 %."""
    from test_selfsup_scene import video, write_video_dataset

    seqs = {f"s{i}": video(6, 32, 48, speed=0.6 + 0.2 * i, start=2.0 * i) for i in range(3)}
    ds = write_video_dataset(tmp_path / "ds", seqs, {"s0": "train", "s1": "val", "s2": "test"})
    r = run("train", ds, "-o", tmp_path / "run", "--input", "rgb", "--self-supervised",
            "--pose-width", "4", *TINY)  # fmt: skip
    assert r.exit_code == 0, r.output
    ckpt = tmp_path / "run" / "best.pt"
    s = summary("predict", ckpt, ds, "-o", tmp_path / "npy", "--format", "npy")
    assert s["kind"] == "self-supervised" and s["processed"] == 6 and "relative" in s["scale"]
    assert len(list((tmp_path / "npy").rglob("*.npy"))) == 6
    assert summary("predict", ckpt, ds, "-o", tmp_path / "png")["processed"] == 6
    gt = _split_gt_tree(ds, "test", tmp_path / "gt")
    by_ckpt = summary("eval", "--checkpoint", ckpt, ds, "-o", tmp_path / "e")
    assert by_ckpt["median_scaling"] is True
    b = by_ckpt["metrics"]
    for folder, rel in (("npy", 1e-5), ("png", 0.02)):
        a = summary("eval", "--pred", tmp_path / folder, "--gt", gt, "--scaling", "median")
        for k in ("abs_rel", "rmse", "mae", "delta1"):
            assert a["metrics"][k] == pytest.approx(b[k], rel=rel), (folder, k)


def test_input_mode_mismatch_is_one_line_and_writes_nothing(trained, tmp_path):
    ds, _ = trained
    conf = make_confidence_dataset(tmp_path / "conf")
    r = run("train", conf, "-o", tmp_path / "run", "--input", "rgbdc", *TINY)
    assert r.exit_code == 0, r.output
    r = run("predict", tmp_path / "run" / "best.pt", ds, "-o", tmp_path / "out")
    line = one_line_error(r)
    assert "takes input 'rgbdc' (with a confidence map)" in line and "have none" in line
    assert not (tmp_path / "out").exists()


def test_kitti_dc_layout_refuses_other_sizes(trained, tmp_path):
    ds, ckpt = trained
    r = run("predict", ckpt, ds, "-o", tmp_path / "out", "--layout", "kitti-dc")
    assert "are 1216x352" in one_line_error(r)
    r = run("predict", ckpt, ds, "-o", tmp_path / "out", "--layout", "kitti-dc", "--format", "npy")
    assert r.exit_code == 2 and "--format png" in r.output
    assert not (tmp_path / "out").exists()


# -- the KITTI depth-completion layouts --------------------------------------------------------------


def _selection_tree(root: Path) -> Path:
    """depth_selection/val_selection_cropped with 3 frames of 2 drives, 1216x352."""
    rng = np.random.default_rng(1)
    sel = root / "depth_selection" / "val_selection_cropped"
    for sub in ("image", "velodyne_raw", "groundtruth_depth", "intrinsics"):
        (sel / sub).mkdir(parents=True)
    rows = np.arange(DC_H, dtype=np.float32)[:, None]
    for drive, frame in ((DRIVES[0], "0000000005"), (DRIVES[0], "0000000006"),
                         (DRIVES[1], "0000000123")):  # fmt: skip
        stem = f"{drive}_{{}}_{frame}_image_02"
        depth = np.repeat(5 + 40 * (1 - rows / DC_H), DC_W, axis=1)
        write_image(sel / "image" / f"{stem.format('image')}.png",
                    rng.integers(0, 255, (DC_H, DC_W, 3)).astype(np.uint8))  # fmt: skip
        sparse = np.where(rng.random((DC_H, DC_W)) < 0.05, depth, 0)
        write_depth_png(sel / "velodyne_raw" / f"{stem.format('velodyne_raw')}.png", sparse)
        gt = np.where(rng.random((DC_H, DC_W)) < 0.3, depth, 0)
        write_depth_png(sel / "groundtruth_depth" / f"{stem.format('groundtruth_depth')}.png", gt)
        (sel / "intrinsics" / f"{stem.format('image')}.txt").write_text(
            "7.215377e+02 0 5.965593e+02 0 7.215377e+02 1.498540e+02 0 0 1\n"
        )
    return sel


def test_kitti_dc_layout_names_sizes_and_read_back(trained, tmp_path):
    from sparsetools.io.sources import depth_frames

    _, ckpt = trained
    sel = _selection_tree(tmp_path / "dc")
    s = summary("dataset", "kitti-dc", tmp_path / "dc", "--selection", "-o", tmp_path / "ds")
    assert s["splits"] == {"val_selection": 3}
    out = tmp_path / "submission"
    s = summary("predict", ckpt, tmp_path / "ds", "-o", out, "--split", "val_selection",
                "--layout", "kitti-dc")  # fmt: skip
    assert s["processed"] == 3 and s["holes"] == 0
    # the official names: those of the ground truth the devkit pairs them with, flat in OUT
    names = sorted(p.name for p in out.glob("*.png"))
    assert names == sorted(p.name for p in (sel / "groundtruth_depth").glob("*.png"))
    assert not [p for p in out.rglob("*.png") if p.parent != out]
    for p in out.glob("*.png"):
        raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (DC_H, DC_W) and raw.min() > 0
    # the existing readers key them by (drive, frame), so eval pairs them with the selection
    frames = depth_frames([out], role="depth", option="--pred")
    assert sorted(str(f.key) for f in frames) == [
        f"{DRIVES[0]}/0000000005",
        f"{DRIVES[0]}/0000000006",
        f"{DRIVES[1]}/0000000123",
    ]
    ev = summary("eval", "--pred", out, "--gt", sel)
    assert ev["metrics"]["n_holes"] == 0 and ev["unmatched_predictions"] == 0
    assert ev["metrics"]["n_pixels"] > 0
    # a submission folder without sparsetools' record (copied, or written by other code) is
    # keyed by its names alike
    plain = tmp_path / "plain"
    plain.mkdir()
    for p in out.glob("*.png"):
        shutil.copy(p, plain / p.name)
    assert summary("eval", "--pred", plain, "--gt", sel)["metrics"] == ev["metrics"]


def test_kitti_dc_test_set_keeps_the_input_names(trained, tmp_path):
    _, ckpt = trained
    test = tmp_path / "test_depth_completion_anonymous"
    rng = np.random.default_rng(2)
    for i in range(2):
        name = f"{i:010d}"
        write_image(test / "image" / f"{name}.png",
                    rng.integers(0, 255, (DC_H, DC_W, 3)).astype(np.uint8))  # fmt: skip
        sparse = np.where(rng.random((DC_H, DC_W)) < 0.05, 20.0, 0.0)
        write_depth_png(test / "velodyne_raw" / f"{name}.png", sparse)
        (test / "intrinsics").mkdir(exist_ok=True)
        (test / "intrinsics" / f"{name}.txt").write_text("721.5 0 596.5 0 721.5 149.9 0 0 1\n")
    s = summary("dataset", "build", "-o", tmp_path / "ds", "--rgb", test / "image",
                "--sparse", test / "velodyne_raw", "--calib", test / "intrinsics",
                "--splits", "test=1")  # fmt: skip
    assert s["splits"] == {"test": 2}
    out = tmp_path / "submission"
    s = summary("predict", ckpt, tmp_path / "ds", "-o", out, "--layout", "kitti-dc")
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "0000000000.png",
        "0000000001.png",
    ]
    assert read_depth_png(out / "0000000000.png").shape == (DC_H, DC_W)


# -- holes and values out of the PNG's range -----------------------------------------------------------


class _Fixed:
    """A predictor giving fixed maps (no torch)."""

    def __init__(self, maps):
        self.maps = maps

    def depth(self, index):
        return self.maps[index]


def test_holes_and_clipped_values_are_counted_never_filled(tmp_path):
    from sparsetools.pipeline.batch import Batch
    from sparsetools.pipeline.core import run_job
    from sparsetools.pipeline.predict import PredictJob, PredictSample, PredictSettings

    a = np.full((4, 6), 10.0, np.float32)
    a[0, 0], a[1, 1], a[2, 2], a[3, 3] = 0.0, np.nan, np.inf, 300.0
    b = np.full((4, 6), 12.0, np.float32)
    b[0, 5] = -1.0
    samples = [PredictSample(0, "s", "a", 6, 4), PredictSample(1, "s", "b", 6, 4)]
    job = PredictJob(PredictSettings(checkpoint="c", dataset="d"), _Fixed([a, b]))
    res = run_job(job, samples, tmp_path / "out", batch=Batch(progress=False)).as_dict()
    assert res["holes"] == 4 and res["frames_with_holes"] == 2
    assert res["holes_first"] == ["s/a", "s/b"]
    assert res["clipped"] == 1 and res["clipped_first"] == ["s/a"]
    raw = cv2.imread(str(tmp_path / "out" / "s" / "a.png"), cv2.IMREAD_UNCHANGED)
    assert raw[0, 0] == raw[1, 1] == raw[2, 2] == 0 and raw[3, 3] == 65535
    assert raw[0, 1] == 2560
    # eval --pred counts the holes where the ground truth has a value
    gt = tmp_path / "gt" / "s"
    write_depth_png(gt / "a.png", np.full((4, 6), 10.0))
    write_depth_png(gt / "b.png", np.full((4, 6), 12.0))
    ev = summary("eval", "--pred", tmp_path / "out", "--gt", tmp_path / "gt")
    assert ev["metrics"]["n_holes"] == 4


def test_holes_of_a_network_are_reported_by_the_command(trained, tmp_path, monkeypatch):
    """Through the command line: a network giving NaN and 0 at two pixels of every map."""
    from sparsetools.train.predict import Predictor

    original = Predictor.depth

    def with_holes(self, index):
        d = original(self, index).copy()
        d[0, 0], d[-1, -1] = np.nan, 0.0
        return d

    monkeypatch.setattr(Predictor, "depth", with_holes)
    ds, ckpt = trained
    r = CliRunner().invoke(cli, ["predict", str(ckpt), str(ds), "-o", str(tmp_path / "p"),
                                 "--json"])  # fmt: skip
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["holes"] == 2 * s["frames"] and s["frames_with_holes"] == s["frames"]
    assert f"{s['holes']} pixel(s) of {s['frames']} map(s) have no prediction" in r.stderr
    for p in (tmp_path / "p").rglob("*.png"):
        raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert raw[0, 0] == raw[-1, -1] == 0 and np.count_nonzero(raw == 0) == 2


def test_eval_reports_unmatched_frames_on_both_sides(tmp_path):
    for side, names in (("pred", ("a", "b", "x")), ("gt", ("a", "b"))):
        for n in names:
            write_depth_png(tmp_path / side / "s" / f"{n}.png", np.full((4, 6), 10.0))
    ev = summary("eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt")
    assert ev["unmatched_predictions"] == 1 and ev["unmatched_predictions_first"] == ["s/x"]
    shutil.copy(tmp_path / "gt" / "s" / "a.png", tmp_path / "gt" / "s" / "y.png")
    (tmp_path / "pred" / "s" / "x.png").unlink()
    line = one_line_error(run("eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt"))
    assert "1 of 3 ground-truth frame(s) have no prediction" in line and "s/y" in line
