"""RNW's priors-based regularization (PBR) in self-supervised training: the PatchGAN
discriminator's geometry, its input, the LSGAN losses, the reference draws, training with it on
(deterministic, exact resume, finite losses) and off (bit for bit what it was before PBR), and
the command line's refusals."""

from __future__ import annotations

import csv
import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from _cli import one_line_error, run
from sparsetools.errors import FormatError, ParameterError
from sparsetools.train.checkpoint import load_checkpoint
from sparsetools.train.config import SelfSupSettings, TrainConfig
from sparsetools.train.loop import train
from sparsetools.train.selfsup.discriminator import (
    GRID,
    LAYERS,
    OUTPUT_SIZE,
    PATCH_STRIDE,
    RECEPTIVE_FIELD,
    PatchDiscriminator,
    area_matrix,
    coordinate_image,
    discriminator_input,
    lsgan_discriminator_loss,
    lsgan_generator_loss,
    patch_geometry,
)
from sparsetools.train.selfsup.pbr_reference import ReferenceDepths
from test_selfsup_scene import video, write_video_dataset

sys.path.insert(1, str(Path(__file__).resolve().parent / "golden"))

from train_cases import TIMING, checkpoint_digests, make_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """The golden tests' tiny video dataset: 3 training sequences, 1 validation, 32x48."""
    return make_dataset(tmp_path_factory.mktemp("pbr") / "ds")


def config(dataset, out, **kw) -> TrainConfig:
    selfsup = {"pose_width": 4, **kw.pop("selfsup", {})}
    base = dict(width=4, epochs=2, batch_size=4, lr=2e-3, threads=1, pictures=0, seed=5)
    return TrainConfig(
        dataset=str(dataset),
        out_dir=str(out),
        selfsup=SelfSupSettings(**selfsup),
        **{"input_mode": "rgb", **base, **kw},
    )


def rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [
            {k: v for k, v in r.items() if k not in TIMING | {"run_id"}} for r in csv.DictReader(f)
        ]


# -- the discriminator ------------------------------------------------------------------------------
def test_patch_geometry_follows_from_the_layers():
    # 62 -> 30 -> 14 -> 6 -> 3 cells; field 4, 10, 22, 46; stride 2, 4, 8, 8
    assert LAYERS == ((4, 2), (4, 2), (4, 2), (4, 1))
    assert patch_geometry(GRID) == (OUTPUT_SIZE, RECEPTIVE_FIELD, PATCH_STRIDE) == (3, 46, 8)
    assert [patch_geometry(GRID, LAYERS[:k])[1:] for k in (1, 2, 3)] == [(4, 2), (10, 4), (22, 8)]
    # the three patches of a row tile the grid: 0..45, 8..53, 16..61
    assert (OUTPUT_SIZE - 1) * PATCH_STRIDE + RECEPTIVE_FIELD == GRID
    with pytest.raises(ParameterError):
        patch_geometry(20)


@pytest.mark.parametrize("size", [(64, 208), (32, 48), (96, 320), (375, 1242)])
def test_output_is_a_3x3_patch_map_for_every_training_size(size):
    torch.manual_seed(0)
    h, w = size
    depth = torch.rand(2, 1, h, w) * 50 + 1
    valid = torch.ones_like(depth, dtype=torch.bool)
    for coordinates, channels in ((True, 3), (False, 1)):
        x = discriminator_input(depth, valid, coordinates=coordinates)
        assert x.shape == (2, channels, GRID, GRID)
        net = PatchDiscriminator(coordinates=coordinates)
        assert net.in_channels == channels and net.net[0].in_channels == channels
        assert net(x).shape == (2, 1, 3, 3)
    with pytest.raises(ParameterError, match="takes"):
        PatchDiscriminator()(torch.zeros(1, 1, GRID, GRID))  # coordinates expected


def test_receptive_field_measured_by_gradients():
    """Patch (i, j) depends on exactly the cells 8i..8i+45 x 8j..8j+45 (LeakyReLU passes a
    gradient everywhere, so the support of the input gradient is the receptive field)."""
    torch.manual_seed(1)
    net = PatchDiscriminator().double()
    x = torch.randn(1, 3, GRID, GRID, dtype=torch.float64, requires_grad=True)
    out = net(x)
    seen = torch.zeros(GRID, GRID, dtype=torch.bool)
    for i in range(3):
        for j in range(3):
            (grad,) = torch.autograd.grad(out[0, 0, i, j], x, retain_graph=True)
            support = grad.abs().sum(dim=(0, 1)) > 0
            rows = torch.nonzero(support.any(dim=1)).ravel()
            cols = torch.nonzero(support.any(dim=0)).ravel()
            assert (int(rows[0]), int(rows[-1])) == (8 * i, 8 * i + 45)
            assert (int(cols[0]), int(cols[-1])) == (8 * j, 8 * j + 45)
            assert bool(support[8 * i : 8 * i + 46, 8 * j : 8 * j + 46].all())
            seen |= support
    assert bool(seen.all())  # every cell is seen by some patch


# -- the input ---------------------------------------------------------------------------------------
def test_area_matrix_averages_and_copies():
    for n_in in (31, 48, 62, 124, 208, 1242):
        a = area_matrix(n_in, GRID)
        assert a.shape == (GRID, n_in) and bool((a >= 0).all())
        torch.testing.assert_close(a.sum(dim=1), torch.ones(GRID))
    v = torch.arange(124, dtype=torch.float32)
    torch.testing.assert_close(area_matrix(124, 62) @ v, v.view(62, 2).mean(dim=1))
    u = torch.arange(31, dtype=torch.float32)
    torch.testing.assert_close(area_matrix(31, 62) @ u, u.repeat_interleave(2))


def test_input_is_scale_free_masked_and_has_coordinates_by_the_option():
    torch.manual_seed(2)
    depth = torch.rand(2, 1, 64, 208) * 30 + 2
    valid = torch.ones_like(depth, dtype=torch.bool)
    valid[:, :, :20] = False  # "sky": no reference depth in the top 20 rows
    x = discriminator_input(depth, valid, coordinates=True)
    # mu(D) = D / mean(D): the same for a map 7 times deeper
    torch.testing.assert_close(x, discriminator_input(7 * depth, valid, coordinates=True))
    # I_p: the cell centres' row and column, fractions of the height and width
    torch.testing.assert_close(x[:, :2], coordinate_image(2))
    centres = (torch.arange(GRID) + 0.5) / GRID
    torch.testing.assert_close(x[0, 0, :, 5], centres)
    torch.testing.assert_close(x[0, 1, 5, :], centres)
    alone = discriminator_input(depth, valid, coordinates=False)
    assert alone.shape == (2, 1, GRID, GRID)
    torch.testing.assert_close(alone, x[:, 2:])
    # cells wholly in the hole are 0 (20 of 64 rows: cells 0..18 of 62 lie in rows < 20)
    assert bool((alone[:, :, :19] == 0).all()) and bool((alone[:, :, 20:] > 0).all())
    # a constant map is 1 wherever it is known, whatever the holes
    const = discriminator_input(torch.full_like(depth, 12.5), valid, coordinates=False)
    torch.testing.assert_close(const[:, :, 20:], torch.ones_like(const[:, :, 20:]))
    # a hole-free constant map is 1 everywhere
    known = torch.ones(1, 1, 32, 48, dtype=torch.bool)
    full = discriminator_input(torch.full((1, 1, 32, 48), 3.0), known, coordinates=False)
    torch.testing.assert_close(full, torch.ones_like(full))


def test_lsgan_losses_equal_hand_computed_values():
    real = (torch.arange(9, dtype=torch.float64) / 8).view(1, 1, 3, 3)  # 0, 1/8, ..., 1
    fake = torch.full((1, 1, 3, 3), 0.2, dtype=torch.float64)
    # L_D = 1/2 mean((r - 1)^2) + 1/2 mean(f^2) = 1/2 (204 / 64 / 9) + 1/2 0.04
    # (sum over k = 0..8 of ((8 - k) / 8)^2 = (0 + 1 + 4 + ... + 64) / 64 = 204 / 64)
    expected_d = 0.5 * (204 / 64 / 9) + 0.5 * 0.04
    assert float(lsgan_discriminator_loss(real, fake)) == pytest.approx(expected_d, abs=1e-15)
    # L_G = 1/2 mean((f - 1)^2) = 1/2 0.64
    assert float(lsgan_generator_loss(fake)) == pytest.approx(0.32, abs=1e-15)
    # the optimum of each: reference scored 1, generated 0 (D); generated scored 1 (G)
    ones, zeros = torch.ones(2, 1, 3, 3), torch.zeros(2, 1, 3, 3)
    assert float(lsgan_discriminator_loss(ones, zeros)) == 0.0
    assert float(lsgan_generator_loss(ones)) == 0.0
    assert float(lsgan_discriminator_loss(zeros, ones)) == 1.0


# -- the reference depths ----------------------------------------------------------------------------
def test_reference_draws_are_per_step_cropped_and_valid(dataset):
    ref = ReferenceDepths(dataset, split="train", size=(24, 40), max_depth=30.0, seed=5)
    assert len(ref) == 15  # the 15 training frames (the split of the run's name)
    a, b = ref.draw(step=3, batch=4), ref.draw(step=3, batch=4)
    assert a.shape == (4, 1, 24, 40) and torch.equal(a, b)
    assert not torch.equal(a, ref.draw(step=4, batch=4))
    assert float(a.max()) < 30.0 and float(a.min()) == 0.0  # sky and beyond max_depth: 0
    # every draw is the bottom-centre 40x24 crop of a frame's GT, flipped or not
    from sparsetools.io.depth_files import read_depth_file

    gts = []
    for i in ref.positions:
        gt = read_depth_file(ref.reader.path(ref.reader.row(i).gt_path))[8:, 4:44]
        gt = np.where(gt < 30.0, gt, 0.0)
        gts += [gt, gt[:, ::-1]]
    for m in a[:, 0].numpy():
        assert any(np.array_equal(m, g) for g in gts)


def test_reference_falls_back_to_dense_sparse_depth_and_refuses_the_rest(tmp_path):
    seqs = {"a": video(3, 32, 48)}
    dense = write_video_dataset(tmp_path / "dense", seqs, {"a": "train"}, gt=False, sparse_rows=1)
    ref = ReferenceDepths(dense, split="train", size=(32, 48), max_depth=80.0, seed=0)
    assert len(ref) == 3 and not any(ref.from_gt)
    assert float((ref.draw(step=0, batch=2) > 0).float().mean()) > 0.5
    lidar = write_video_dataset(tmp_path / "lidar", seqs, {"a": "train"}, gt=False)
    with pytest.raises(FormatError, match="no sample .* has depth"):
        ReferenceDepths(lidar, split="train", size=(32, 48), max_depth=80.0, seed=0)
    with pytest.raises(ParameterError, match="smaller than the 64x40"):
        ReferenceDepths(dense, split="train", size=(40, 64), max_depth=80.0, seed=0)
    with pytest.raises(ParameterError, match="does not exist"):
        ReferenceDepths(tmp_path / "nowhere", split="train", size=(8, 8), max_depth=80.0, seed=0)
    with pytest.raises(FormatError, match="--pbr: .*manifest"):
        ReferenceDepths(tmp_path, split="train", size=(8, 8), max_depth=80.0, seed=0)


# -- training ----------------------------------------------------------------------------------------
#: sha256 of the metrics rows and last.pt's tensors (models, optimizer, RNG, state) of two
#: runs without PBR, made by the code before PBR existed (commit d672579) with
#: :func:`_fingerprint`, one torch thread, on each kind of machine the tests ran on: torch's
#: CPU kernels round differently from one CPU to another (the first: the machine of
#: 2026-12-02; the second: a 2-core AVX-512 Xeon VM, 2026-12-03).
BEFORE_PBR = {
    "camera": {
        "1283647922197559f013f840c844628aa9334865e41bd38a2b387c9256d9e237",
        "06ec3957b314c5e1c84acaba5dc226abbc2a06ef6c2e7eb4e4be4519784ebebf",
    },
    "night_lidar": {
        "ceb13684f4d5e016f7ed9a7f85dce2ed0ea23ab227b6049a31095bbf5e0bf70e",
        "50987b4bc33182ac65a19b22304d45813a657d7403b086c65d44edc7f2e28b63",
    },
}
OFF_CASES = {
    "camera": dict(input_mode="rgb", selfsup={}),
    "night_lidar": dict(
        input_mode="rgbd",
        lr_schedule="cosine",
        selfsup=dict(mcie=True, sbm=True, sparse_loss="silog"),
    ),
}


def _fingerprint(run_dir: Path) -> str:
    digests = {k: v for k, v in checkpoint_digests(run_dir / "last.pt").items() if k != "run_id"}
    digests.pop("config")  # holds the new (null) PBR settings
    digests["metrics"] = hashlib.sha256(
        json.dumps(rows(run_dir), sort_keys=True).encode()
    ).hexdigest()
    return hashlib.sha256(json.dumps(digests, sort_keys=True).encode()).hexdigest()


@pytest.mark.parametrize("name", list(OFF_CASES))
def test_without_pbr_training_is_bit_for_bit_what_it_was(dataset, tmp_path, name):
    train(config(dataset, tmp_path / name, **OFF_CASES[name]))
    assert _fingerprint(tmp_path / name) in BEFORE_PBR[name]
    assert not any("pbr" in k for k in rows(tmp_path / name)[0])
    assert json.loads((tmp_path / name / "config.json").read_text())["selfsup"]["pbr"] is None
    raw = torch.load(tmp_path / name / "last.pt", weights_only=True)
    assert not any(k.startswith("discriminator") for k in raw)


def test_with_pbr_training_is_deterministic_resumes_exactly_and_is_finite(dataset, tmp_path):
    pbr = {"pbr": str(dataset)}
    a = train(config(dataset, tmp_path / "a", selfsup=pbr))
    train(config(dataset, tmp_path / "b", selfsup=pbr))
    ra = rows(tmp_path / "a")
    assert ra == rows(tmp_path / "b") and a.steps == 6
    for r in ra:
        values = [float(r[f"train_pbr_{k}"]) for k in ("generator", "discriminator", "real")]
        assert all(np.isfinite(v) and v >= 0 for v in values[:2]) and np.isfinite(values[2])
    ca, cb = (
        load_checkpoint(tmp_path / "a" / "last.pt"),
        load_checkpoint(tmp_path / "b" / "last.pt"),
    )
    assert ca.discriminator_config == {"coordinates": True, "width": 32, "grid": GRID}
    for k in ca.discriminator:
        assert torch.equal(ca.discriminator[k], cb.discriminator[k])
    assert ca.discriminator["net.0.weight"].shape[1] == 3  # I_p (2) + mu(D) (1)
    # stopped inside the second epoch and resumed: the same rows and discriminator
    train(config(dataset, tmp_path / "cut", max_steps=4, selfsup=pbr))
    train(config(dataset, tmp_path / "cut", selfsup=pbr), resume=True)
    assert rows(tmp_path / "cut") == ra
    cc = load_checkpoint(tmp_path / "cut" / "last.pt")
    for k in ca.discriminator:
        assert torch.equal(ca.discriminator[k], cc.discriminator[k])
    for k in ca.discriminator_optimizer["state"]:
        sa, sc = ca.discriminator_optimizer["state"][k], cc.discriminator_optimizer["state"][k]
        assert torch.equal(sa["exp_avg_sq"], sc["exp_avg_sq"])
    # the adversarial term changed the training: other weights than without PBR
    train(config(dataset, tmp_path / "off"))
    off = load_checkpoint(tmp_path / "off" / "last.pt")
    assert not torch.equal(off.model["stem.0.weight"], ca.model["stem.0.weight"])


def test_coordinates_option_and_networks_start_alike(dataset, tmp_path):
    from sparsetools.train.selfsup.task import SelfSupervisedTask

    nets = {}
    for name, selfsup in (
        ("off", {}),
        ("on", {"pbr": str(dataset)}),
        ("no_ip", {"pbr": str(dataset), "pbr_coordinates": False}),
    ):
        task = SelfSupervisedTask(config(dataset, tmp_path / name, selfsup=selfsup))
        torch.manual_seed(5)
        nets[name] = [n.state_dict() for n in task.build_networks(torch.device("cpu"))]
        if task.pbr is not None:
            first = task.pbr.discriminator.net[0]
            assert first.in_channels == (3 if selfsup.get("pbr_coordinates", True) else 1)
    # the discriminator draws from its own stream: depth and pose networks start alike
    for name in ("on", "no_ip"):
        for mine, theirs in zip(nets[name], nets["off"], strict=True):
            assert all(torch.equal(mine[k], theirs[k]) for k in mine)
    run_dir = tmp_path / "no_ip_run"
    train(
        config(dataset, run_dir, epochs=1, selfsup={"pbr": str(dataset), "pbr_coordinates": False})
    )
    ckpt = load_checkpoint(run_dir / "last.pt")
    assert ckpt.discriminator_config["coordinates"] is False
    assert ckpt.discriminator["net.0.weight"].shape[1] == 1


def test_checkpoint_without_its_discriminator_is_refused(dataset, tmp_path):
    from sparsetools.train.runtime import save_torch

    train(config(dataset, tmp_path / "run", epochs=1, selfsup={"pbr": str(dataset)}))
    raw = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    for key in ("discriminator", "discriminator_config", "discriminator_optimizer"):
        raw.pop(key)
    save_torch(raw, tmp_path / "bad.pt")
    with pytest.raises(FormatError, match="lacks a PBR discriminator"):
        load_checkpoint(tmp_path / "bad.pt")


def test_settings_and_cli_refuse_a_bad_reference_in_one_line(dataset, tmp_path):
    with pytest.raises(ParameterError, match="--pbr REFERENCE is missing"):
        SelfSupSettings(pbr_weight=0.1).validate()
    with pytest.raises(ParameterError, match="pbr_discriminator_weight"):
        SelfSupSettings(pbr="x", pbr_discriminator_weight=0.0).validate()
    common = ["--self-supervised", "--input", "rgb", "--width", "4", "--pose-width", "4"]
    common += ["--epochs", "1", "--threads", "1"]
    out = tmp_path / "run"
    line = one_line_error(run("train", dataset, "-o", out, *common, "--pbr", tmp_path / "none"))
    assert "--pbr" in line and "does not exist" in line
    line = one_line_error(run("train", dataset, "-o", out, *common, "--pbr", tmp_path))
    assert line.count("--pbr") == 1 and "manifest" in line
    no_depth = write_video_dataset(
        tmp_path / "lidar", {"a": video(3, 32, 48)}, {"a": "train"}, gt=False
    )
    line = one_line_error(run("train", dataset, "-o", out, *common, "--pbr", no_depth))
    assert "has depth to serve as reference" in line
    line = one_line_error(run("train", dataset, "-o", out, *common, "--no-pbr-coordinates"))
    assert line.startswith("Error: --pbr REFERENCE is missing")
    assert not out.exists()  # refused before the run folder is made
    r = run("train", dataset, "-o", tmp_path / "x", "--pbr", dataset)
    assert r.exit_code == 2 and "--self-supervised" in r.output
