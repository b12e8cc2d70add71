"""`train --input d | rgbdc`: the radar-only baseline and the JBF confidence channel, and one
training step on each real dataset route (KITTI depth completion, KITTI raw, nuScenes + JBF).

The trees come from the real samples in ../shared/data/real, built by the helpers of
tests/test_real_trees.py (KITTI) and tests/_nuscenes_tree.py (nuScenes)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import ParameterError
from sparsetools.io.image import write_depth_png, write_image
from sparsetools.train.checkpoint import load_checkpoint, model_from_checkpoint
from sparsetools.train.config import SelfSupSettings, TrainConfig
from sparsetools.train.data import DepthDataset, augment_sample, collate
from test_real_trees import raw_root  # noqa: F401  (the KITTI raw date folder fixture)

TINY = ["--width", "4", "--epochs", "1", "--threads", "1", "--pictures", "1"]


def cli_run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_error_line(result) -> str:
    assert result.exit_code == 1, result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
    return lines[0]


def stem_channels(run: Path) -> int:
    """Input channels of the first convolution of the run's best model, rebuilt from disk."""
    model = model_from_checkpoint(load_checkpoint(run / "best.pt"))
    return int(model.stem[0].weight.shape[1])


# -- a synthetic dataset with confidence maps ----------------------------------------------------


def _position_code(h: int, w: int) -> np.ndarray:
    """A value per pixel that names the pixel: (row * w + col + 1) / (h * w), in (0, 1]."""
    rows, cols = np.mgrid[0:h, 0:w]
    return ((rows * w + cols + 1) / (h * w)).astype(np.float32)


def make_confidence_dataset(root: Path, *, frames=3, h=24, w=40, with_conf=True) -> Path:
    """Two sequences of ``frames`` frames, one in ``train`` and one in ``val``; with
    ``with_conf`` every frame has a ``<frame>_conf.png`` confidence map: the position code, as
    uint16 / 65535."""
    import cv2

    from sparsetools.pipeline.batch import Batch
    from sparsetools.pipeline.dataset import build_dataset

    rng = np.random.default_rng(0)
    inputs = root / "inputs"
    for i in range(2 * frames):
        depth = np.repeat(5 + 40 * (1 - np.arange(h, dtype=np.float32) / h)[:, None], w, axis=1)
        rgb = rng.integers(0, 255, (h, w, 3)).astype(np.uint8)
        sparse = np.where(rng.random((h, w)) < 0.2, depth, 0).astype(np.float32)
        name = f"seq{i // frames}/{i % frames:06d}"
        for folder, arr in (("rgb", rgb), ("sparse", sparse), ("gt", depth)):
            p = inputs / folder / f"{name}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            (write_image if folder == "rgb" else write_depth_png)(p, arr)
        if with_conf:
            conf = np.round(_position_code(h, w) * 65535).astype(np.uint16)
            p = inputs / "conf" / f"{name}_conf.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(p), conf)  # 16-bit single-channel PNG, as jbf-expand writes
    out = root / "dataset"
    build_dataset(
        out,
        rgb=inputs / "rgb",
        sparse=inputs / "sparse",
        gt=inputs / "gt",
        confidence=inputs / "conf" if with_conf else None,
        split={"train": 0.5, "val": 0.5},
        batch=Batch(progress=False),
    )
    from sparsetools.io.dataset_reader import DatasetReader

    splits = DatasetReader(out).manifest.column("split").to_pylist()
    assert sorted(splits) == ["train"] * frames + ["val"] * frames
    return out


def drop_confidence(dataset: Path, ids: set[str]) -> None:
    """Remove the confidence map of samples ``ids`` from the manifest (as a dataset merged
    from builds with and without ``--confidence`` would have it)."""
    import pyarrow as pa

    from sparsetools.io.dataset import read_manifest
    from sparsetools.io.manifest_writer import write_manifest

    table, info = read_manifest(dataset / "manifest.parquet")
    keep = [None if i in ids else p for i, p in zip(table.column("id").to_pylist(),
            table.column("confidence_path").to_pylist(), strict=True)]  # fmt: skip
    col = table.schema.get_field_index("confidence_path")
    table = table.set_column(col, "confidence_path", pa.array(keep, pa.string()))
    write_manifest(dataset / "manifest.parquet", table, info=info)


@pytest.fixture(scope="module")
def conf_ds(tmp_path_factory) -> Path:
    return make_confidence_dataset(tmp_path_factory.mktemp("conf_ds"))


# -- augmentation keeps the confidence on its pixel ----------------------------------------------


def _reference_augment(conf, rng, *, crop, scale_range):
    """What the augmentation must do to a map, written out: the same draws, nearest resize by
    s, bottom-centre crop, flip."""
    import cv2

    s = float(rng.uniform(*scale_range))
    flip = bool(rng.random() < 0.5)
    h, w = conf.shape
    if s != 1.0:
        conf = cv2.resize(conf, (round(w * s), round(h * s)), interpolation=cv2.INTER_NEAREST)
    ch, cw = crop
    left = (conf.shape[1] - cw) // 2
    conf = conf[conf.shape[0] - ch :, left : left + cw]
    return (conf[:, ::-1] if flip else conf), s, flip


def test_confidence_follows_the_image_through_crop_and_flip():
    """No scaling: the image encodes each pixel's position exactly, so the augmented confidence
    must be the confidence of the position the augmented image shows, pixel by pixel."""
    h, w = 30, 50
    rows, cols = np.mgrid[0:h, 0:w]
    rgb = np.stack([rows * 5, cols * 5, np.zeros_like(rows)], axis=2).astype(np.uint8)
    conf = _position_code(h, w)
    sparse = np.where((rows + cols) % 3 == 0, 10.0 + conf, 0).astype(np.float32)
    gt = np.full((h, w), 20.0, np.float32)
    flips = set()
    for seed in range(8):
        out_rgb, out_sparse, _, out_conf = augment_sample(
            rgb, sparse, gt, np.random.default_rng(seed), crop=(20, 36), jitter=0.0,
            confidence=conf,
        )  # fmt: skip
        r = np.rint(out_rgb[..., 0] * 255 / 5).astype(int)
        c = np.rint(out_rgb[..., 1] * 255 / 5).astype(int)
        np.testing.assert_array_equal(out_conf, conf[r, c])
        np.testing.assert_array_equal(out_sparse, sparse[r, c])
        flips.add(bool(c[0, 0] > c[0, -1]))
    assert flips == {True, False}  # both flipped and unflipped samples were checked


def test_confidence_scales_with_the_depth_maps_but_keeps_its_values():
    """With scale augmentation: the confidence equals the reference pipeline's (nearest resize,
    crop, flip from the same draws) and is not divided by the scale, the depth is."""
    h, w = 30, 50
    conf = _position_code(h, w)
    sparse = (1.0 + conf).astype(np.float32)  # every pixel has depth: a position code too
    rgb = np.zeros((h, w, 3), np.uint8)
    gt = np.full((h, w), 20.0, np.float32)
    for seed in range(6):
        _, out_sparse, out_gt, out_conf = augment_sample(
            rgb, sparse, gt, np.random.default_rng(seed), crop=(24, 40),
            scale_range=(1.1, 1.6), jitter=0.0, confidence=conf,
        )  # fmt: skip
        ref, s, _ = _reference_augment(
            conf, np.random.default_rng(seed), crop=(24, 40), scale_range=(1.1, 1.6)
        )
        assert s > 1.05
        np.testing.assert_array_equal(out_conf, ref)
        # the depth went through the same resampling, divided by s
        np.testing.assert_allclose(out_sparse * s, 1.0 + out_conf, rtol=1e-6)
        np.testing.assert_allclose(out_gt, 20.0 / s, rtol=1e-6)


def test_rgbd_augmentation_is_unchanged_by_the_confidence_option():
    rng_a, rng_b = np.random.default_rng(5), np.random.default_rng(5)
    rgb = np.random.default_rng(1).integers(0, 255, (20, 30, 3)).astype(np.uint8)
    sparse = np.random.default_rng(2).uniform(0, 50, (20, 30)).astype(np.float32)
    gt = np.random.default_rng(3).uniform(1, 50, (20, 30)).astype(np.float32)
    kw = dict(crop=(16, 24), scale_range=(1.0, 1.3))
    three = augment_sample(rgb, sparse, gt, rng_a, **kw)
    four = augment_sample(rgb, sparse, gt, rng_b, confidence=np.ones((20, 30), np.float32), **kw)
    assert len(three) == 3 and len(four) == 4
    for a, b in zip(three, four[:3], strict=True):
        np.testing.assert_array_equal(a, b)


def test_dataset_items_carry_the_confidence_only_for_rgbdc(conf_ds):
    plain = DepthDataset(conf_ds, "train")
    assert "confidence" not in plain[0]
    ds = DepthDataset(conf_ds, "train", input_mode="rgbdc", crop=(16, 30))
    item = ds[0]
    assert item["confidence"].shape == (1, 16, 30) and item["confidence"].dtype == torch.float32
    expected = np.round(_position_code(24, 40) * 65535) / 65535  # as stored (uint16 PNG)
    np.testing.assert_allclose(item["confidence"][0].numpy(), expected[8:, 5:35], atol=1e-7)
    batch = collate([ds[0], ds[1]])
    assert batch["confidence"].shape == (2, 1, 16, 30)


# -- refusals ----------------------------------------------------------------------------------


def test_rgbdc_without_confidence_is_refused_up_front(tmp_path):
    none = make_confidence_dataset(tmp_path / "none", with_conf=False)
    with pytest.raises(ParameterError, match=r"--input rgbdc needs a confidence map.*no sample"):
        DepthDataset(none, "train", input_mode="rgbdc")
    some = make_confidence_dataset(tmp_path / "some", frames=4)
    drop_confidence(some, {"seq1/000001"})
    r = cli_run("train", some, "-o", tmp_path / "run", "--input", "rgbdc", *TINY)
    line = one_error_line(r)
    assert "--input rgbdc needs a confidence map" in line and "1 of the 4 samples" in line
    assert "(e.g. 'seq1/000001')" in line
    assert "--confidence" in line
    assert not (tmp_path / "run").exists()  # refused before anything was written


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"input_mode": "d", "selfsup": SelfSupSettings()}, "no camera image"),
        ({"input_mode": "rgbdc", "selfsup": SelfSupSettings()}, "carry no confidence map"),
        ({"input_mode": "d", "lidar_encoder": "sfe"}, "use --input rgb, not d"),
        ({"input_mode": "rgbdc", "lidar_encoder": "dense"}, "use --input rgb, not rgbdc"),
    ],
)
def test_new_inputs_are_refused_where_they_make_no_sense(kw, match):
    with pytest.raises(ParameterError, match=match):
        TrainConfig(dataset="x", out_dir="y", **kw).validate()


def test_cli_refuses_d_for_self_supervised_training(conf_ds, tmp_path):
    r = cli_run("train", conf_ds, "-o", tmp_path / "r", "--input", "d", "--self-supervised")
    assert "photometric loss" in one_error_line(r)


# -- train, eval, resume on the synthetic dataset --------------------------------------------------


@pytest.mark.parametrize(("mode", "channels"), [("d", 1), ("rgbdc", 5)])
def test_train_eval_resume_with_the_new_inputs(conf_ds, tmp_path, mode, channels):
    run = tmp_path / "run"
    r = cli_run("train", conf_ds, "-o", run, "--input", mode, *TINY, "--batch-size", "3",
                "--max-steps", "1", "--final-layer", "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["input_mode"] == mode
    ckpt = load_checkpoint(run / "last.pt")
    assert ckpt.input_mode == mode and ckpt.config.input_mode == mode
    assert ckpt.model["stem.0.weight"].shape[1] == channels == stem_channels(run)
    r = cli_run("eval", "--checkpoint", run, conf_ds, "--split", "val", "--json")
    assert r.exit_code == 0, r.output
    res = json.loads(r.stdout)
    assert res["input_mode"] == mode and res["metrics"]["n_images"] == 3
    assert all(np.isfinite(res["metrics"][k]) for k in ("rmse", "abs_rel", "mae"))
    # eval rebuilds the same channels: its metrics are the training's validation metrics
    rows = (run / "metrics.csv").read_text().splitlines()
    header, last = rows[0].split(","), rows[-1].split(",")
    assert float(last[header.index("rmse")]) == pytest.approx(res["metrics"]["rmse"], rel=1e-6)
    r = cli_run("train", conf_ds, "-o", run, "--resume", "--max-steps", "3", "--threads", "1",
                "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert (
        json.loads(r.stdout)["steps"] == 3 and load_checkpoint(run / "last.pt").input_mode == mode
    )
    other = "rgbd" if mode == "d" else "d"
    r = cli_run("train", conf_ds, "-o", run, "--resume", "--input", other)
    assert f"input mode '{mode}', not '{other}'" in one_error_line(r)


def test_d_ignores_the_image_and_rgbdc_uses_the_confidence(conf_ds, tmp_path):
    """The radar-only model's prediction does not change with the image; the rgbdc model's
    changes with the confidence map."""
    from sparsetools.train.evaluate import batch_inputs

    for mode in ("d", "rgbdc"):
        run = tmp_path / mode
        cfg = TrainConfig(dataset=str(conf_ds), out_dir=str(run), input_mode=mode, width=4,
                          epochs=1, batch_size=3, threads=1, pictures=0, max_steps=2)  # fmt: skip
        from sparsetools.train.loop import train

        train(cfg)
        model = model_from_checkpoint(load_checkpoint(run / "last.pt")).eval()
        batch = collate([DepthDataset(conf_ds, "val", input_mode="rgbdc")[0]])
        rgb, sparse, extra = batch_inputs(batch, torch.device("cpu"))
        with torch.no_grad():
            if mode == "d":
                a = model.depth_of(rgb, sparse)
                b = model.depth_of(torch.rand_like(rgb), sparse)
                assert torch.equal(a, b)
            else:
                a = model.depth_of(rgb, sparse, **extra)
                b = model.depth_of(rgb, sparse, confidence=1 - extra["confidence"])
                assert not torch.equal(a, b)


# -- the real dataset routes ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def nuscenes_root(real_dir, tmp_path_factory):
    from _nuscenes_tree import build_tree

    root = tmp_path_factory.mktemp("nuscenes")
    build_tree(real_dir, root)
    return root


def _nuscenes_dataset(root: Path, out: Path, *extra) -> Path:
    r = cli_run("-q", "dataset", "nuscenes", root, "-o", out, "--sweeps", "1", "--resize",
                "0.5", "--crop", "800x350+0+100", *extra)  # fmt: skip
    assert r.exit_code == 0, r.output
    return out


ONE_STEP = [*TINY, "--batch-size", "1", "--max-steps", "1", "--crop-size", "128x64"]


@pytest.mark.real
@pytest.mark.parametrize(("mode", "channels"), [("d", 1), ("rgbdc", 5)])
def test_nuscenes_radar_with_jbf_trains_one_step(nuscenes_root, tmp_path, mode, channels):
    ds = _nuscenes_dataset(nuscenes_root, tmp_path / "ds", "--jbf")
    run = tmp_path / "run"
    r = cli_run("-q", "train", ds, "-o", run, "--input", mode, *ONE_STEP,
                "--val-split", "train", "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["steps"] == 1
    ckpt = load_checkpoint(run / "best.pt")
    assert ckpt.input_mode == mode and stem_channels(run) == channels
    r = cli_run("-q", "eval", "--checkpoint", run, ds, "--split", "train", "--json")
    assert r.exit_code == 0, r.output
    res = json.loads(r.stdout)
    assert res["input_mode"] == mode and res["metrics"]["n_images"] == 1
    assert np.isfinite(res["metrics"]["rmse"]) and res["metrics"]["n_pixels"] > 1000


@pytest.mark.real
def test_nuscenes_radar_without_jbf_has_no_confidence_for_rgbdc(nuscenes_root, tmp_path):
    ds = _nuscenes_dataset(nuscenes_root, tmp_path / "ds")
    r = cli_run("train", ds, "-o", tmp_path / "run", "--input", "rgbdc", *ONE_STEP,
                "--val-split", "train")  # fmt: skip
    line = one_error_line(r)
    assert "--input rgbdc needs a confidence map" in line and "dataset nuscenes --jbf" in line
    # the radar-only baseline needs none
    r = cli_run("-q", "train", ds, "-o", tmp_path / "run_d", "--input", "d", *ONE_STEP,
                "--val-split", "train")  # fmt: skip
    assert r.exit_code == 0, r.output


@pytest.fixture(scope="module")
def kitti_trees(raw_root, tmp_path_factory):  # noqa: F811
    """The KITTI raw date folder of tests/test_real_trees.py (2 drives, colliding frame names)
    and its depth-completion tree (drive 1 train, drive 2 val)."""
    import test_real_trees as trees

    root = tmp_path_factory.mktemp("kitti")
    raw = raw_root
    full, b4 = root / "full", root / "b4"
    for args in (("project", raw / trees.DATE, "-o", full),
                 ("beams", raw / trees.DATE, "--n", "4", "-o", root / "b4c"),
                 ("project", root / "b4c", "--calib", raw / trees.DATE, "-o", b4)):  # fmt: skip
        assert trees.run(*args).exit_code == 0
    return raw / trees.DATE, trees._dc_tree(root, sparse=b4, gt=full)


KITTI_STEP = [*TINY, "--batch-size", "1", "--max-steps", "1", "--crop-size", "256x128"]


@pytest.mark.real
def test_kitti_depth_completion_tree_trains_one_step(kitti_trees, tmp_path):
    date, dc = kitti_trees
    r = cli_run("-q", "dataset", "kitti-dc", dc, "--raw", date, "-o", tmp_path / "ds")
    assert r.exit_code == 0, r.output
    run = tmp_path / "run"
    r = cli_run("-q", "train", tmp_path / "ds", "-o", run, "--input", "rgbd", *KITTI_STEP,
                "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["steps"] == 1 and stem_channels(run) == 4
    r = cli_run("-q", "eval", "--checkpoint", run, tmp_path / "ds", "--split", "val", "--json")
    assert r.exit_code == 0, r.output
    m = json.loads(r.stdout)["metrics"]
    assert m["n_images"] == 3 and np.isfinite(m["rmse"]) and m["n_pixels"] > 1000


@pytest.mark.real
def test_kitti_raw_date_folder_trains_one_step(kitti_trees, tmp_path):
    date, _ = kitti_trees
    r = cli_run("-q", "dataset", "kitti-raw", date, "-o", tmp_path / "ds", "--beams", "4",
                "--splits", "train=0.5,val=0.5", "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["splits"] == {"train": 3, "val": 3}  # one drive each
    run = tmp_path / "run"
    r = cli_run("-q", "train", tmp_path / "ds", "-o", run, *KITTI_STEP, "--json")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["steps"] == 1 and summary["input_mode"] == "rgbd" and stem_channels(run) == 4
    assert np.isfinite(summary["last_rmse"])
