"""The LiDAR branch in training (``--lidar-encoder sfe|dense``, ``--pose-lidar-encoder``).

The fusion rule (docs/sfe.md): level i of the LiDAR encoder is ADDED to the output of U-Net
encoder level i, before it becomes the skip and before the max pooling; the pose network adds
its branch to its first five convolutions. References below: a forward pass written out in
the test with the model's own layers, and the camera-only network of the same seed (the SFE's
output is exactly zero without LiDAR sites, so an empty map must give that network's output
bit for bit).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import ParameterError
from sparsetools.ops.metrics import METRIC_NAMES, depth_metrics
from sparsetools.train.checkpoint import load_checkpoint, model_from_checkpoint
from sparsetools.train.config import SelfSupSettings, TrainConfig
from sparsetools.train.data import collate
from sparsetools.train.evaluate import evaluate_checkpoint
from sparsetools.train.loop import train
from sparsetools.train.model import DepthCompletionUNet, build_model, model_inputs
from sparsetools.train.selfsup.data import TripletDataset
from sparsetools.train.selfsup.pose_net import (
    PoseNet,
    build_pose_net,
    source_transforms,
)
from sparsetools.train.sfe import DenseLidarEncoder, SparseFeatureExtractor
from test_selfsup_scene import video, write_video_dataset
from test_train import make_dataset, read_rows, state_equal

H, W = 37, 53  # not multiples of 16: the padding path


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread: on a shared machine two OpenMP threads mostly wait for each other."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def batch(seed=0, B=2, h=H, w=W, density=0.05):
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(B, 3, h, w, generator=g)
    mask = torch.rand(B, 1, h, w, generator=g) < density
    sparse = torch.where(mask, 2 + 60 * torch.rand(B, 1, h, w, generator=g), 0.0)
    return rgb, sparse


def unet(encoder, seed=0, **kw):
    torch.manual_seed(seed)
    return DepthCompletionUNet("rgb", width=4, lidar_encoder=encoder, **kw)


def live_head(model: DepthCompletionUNet) -> DepthCompletionUNet:
    """The depth head starts at zero weights (a constant 10 m): give it seeded random ones, so
    the prediction shows what reaches it."""
    if model.output == "depth":
        g = torch.Generator().manual_seed(99)
        with torch.no_grad():
            model.head.weight.copy_(0.5 * torch.randn(model.head.weight.shape, generator=g))
    return model


def unet_part(state: dict) -> dict:
    return {k: v for k, v in state.items() if not k.startswith("lidar_branch.")}


# -- the depth network ----------------------------------------------------------------------------
@pytest.mark.parametrize("encoder", ["none", "sfe", "dense"])
@pytest.mark.parametrize("output", ["depth", "disparity"])
def test_each_encoder_trains_one_step_with_the_right_shapes(encoder, output):
    model = unet(encoder, output=output)
    rgb, sparse = batch()
    out = model.run(rgb, sparse)
    if output == "depth":
        assert out.shape == (2, 1, H, W)
        loss = out.mean()
    else:
        assert [tuple(o.shape) for o in out] == [
            (2, 1, -(-H // 2**s), -(-W // 2**s)) for s in range(4)
        ]
        loss = sum(o.mean() for o in out)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    loss.backward()
    opt.step()
    # the depth head starts at zero weights: a second step reaches the layers below it
    opt.zero_grad()
    out = model.run(rgb, sparse)
    (out.mean() if output == "depth" else sum(o.mean() for o in out)).backward()
    opt.step()
    after = model.state_dict()
    changed = [
        k
        for k in after
        if after[k].dtype.is_floating_point and not torch.equal(after[k], before[k])
    ]
    assert any(k.startswith("stem.") for k in changed)
    if encoder != "none":
        assert any(k.startswith("lidar_branch.stem.") for k in changed)
    depth = model.depth_of(rgb, sparse)
    assert depth.shape == (2, 1, H, W) and torch.isfinite(depth).all()


def test_sfe_and_dense_have_the_same_shapes_and_parameter_layout():
    sfe, dense, none = unet("sfe"), unet("dense"), unet("none")
    n = [p.numel() for p in sfe.parameters()]
    assert n == [p.numel() for p in dense.parameters()]
    assert sum(n) > sum(p.numel() for p in none.parameters())
    assert isinstance(sfe.lidar_branch, SparseFeatureExtractor)
    assert isinstance(dense.lidar_branch, DenseLidarEncoder)
    # the branch's widths are the widths of the U-Net levels it feeds (1/2 .. 1/16 by
    # default, EffisDepth's levels: never full resolution); the U-Net itself is unchanged
    assert sfe.lidar_scales == sfe.lidar_branch.scales == (2, 4, 8, 16)
    assert sfe.lidar_branch.out_channels == dense.lidar_branch.out_channels == sfe.widths[1:]
    shapes = {k: v.shape for k, v in unet_part(none.state_dict()).items()}
    for m in (sfe, dense):
        assert {k: v.shape for k, v in unet_part(m.state_dict()).items()} == shapes
    rgb, sparse = batch(1)
    padded = F.pad(sparse, (0, (-W) % 16, 0, (-H) % 16))
    assert [o.shape for o in sfe.lidar_branch(padded)] == [
        o.shape for o in dense.lidar_branch(padded)
    ]
    assert sfe.run(rgb, sparse).shape == dense.run(rgb, sparse).shape


def test_the_unet_starts_alike_whatever_the_lidar_encoder():
    """The branch draws its weights from its own stream and leaves the global RNG alone."""
    ref = unet_part(unet("none", seed=3).state_dict())
    after_none = torch.rand(3)
    for encoder in ("sfe", "dense"):
        m = unet(encoder, seed=3)
        assert torch.equal(torch.rand(3), after_none)
        state = unet_part(m.state_dict())
        assert state.keys() == ref.keys() and all(torch.equal(state[k], ref[k]) for k in ref)
    # the branch itself depends on the seed
    a, b = unet("sfe", seed=3).lidar_branch, unet("sfe", seed=4).lidar_branch
    assert not torch.equal(a.stem[0].weight, b.stem[0].weight)


@pytest.mark.parametrize("output", ["depth", "disparity"])
def test_an_empty_lidar_map_gives_the_camera_only_network_exactly(output):
    camera = live_head(unet("none", seed=5, output=output)).eval()
    fused = live_head(unet("sfe", seed=5, output=output)).eval()
    rgb, sparse = batch(2)
    empty = torch.zeros_like(sparse)
    nan = torch.full_like(sparse, float("nan"))  # NaN is empty too
    with torch.no_grad():
        ref = camera.depth_of(rgb, None)
        assert torch.equal(fused.depth_of(rgb, empty), ref)
        assert torch.equal(fused.depth_of(rgb, nan), ref)
        real = fused.depth_of(rgb, sparse)
    assert (real - ref).abs().max() > 1e-4


@pytest.mark.parametrize("encoder", ["sfe", "dense"])
def test_the_lidar_branch_changes_the_prediction_and_gets_gradients(encoder):
    model = live_head(unet(encoder, seed=6)).eval()
    rgb, sparse = batch(3)
    with torch.no_grad():
        zeroed = model.depth_of(rgb, torch.zeros_like(sparse))
        real = model.depth_of(rgb, sparse)
        moved = model.depth_of(rgb, sparse * 1.5)
    assert (real - zeroed).abs().max() > 1e-4 and (moved - real).abs().max() > 1e-5
    model.train()
    model.depth_of(rgb, sparse).mean().backward()
    for name, p in model.lidar_branch.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert model.lidar_branch.stem[0].weight.grad.abs().sum() > 0
    # the camera-only model ignores the map
    camera = live_head(unet("none", seed=6)).eval()
    with torch.no_grad():
        assert torch.equal(camera.depth_of(rgb, sparse), camera.depth_of(rgb, None))


def reference_forward(model: DepthCompletionUNet, rgb, sparse):
    """The fused U-Net written out: pad both, add LiDAR level i after encoder level i."""
    h, w = rgb.shape[-2:]
    pad = (0, (-w) % 16, 0, (-h) % 16)
    x = F.pad(model_inputs(rgb, None, "rgb"), pad)
    lidar = dict(zip(model.lidar_scales, model.lidar_branch(F.pad(sparse, pad)), strict=True))
    y = model.stem(x)
    skips = []
    for i, block in enumerate(model.encoder):
        y = block(F.max_pool2d(y, 2) if i else y)
        if 2**i in lidar:
            y = y + lidar[2**i]
        skips.append(y)
    y = skips[-1]
    for stage, skip in zip(model.decoder, reversed(skips[:-1]), strict=True):
        y = stage(y, skip)
    return (20.0 * F.softplus(model.head(y)))[:, :, :h, :w]


@pytest.mark.parametrize("scales", [(2, 4, 8, 16), (1, 2, 4, 8, 16), (4, 16)])
@pytest.mark.parametrize("encoder", ["sfe", "dense"])
def test_fusion_equals_the_written_out_reference(encoder, scales):
    model = live_head(unet(encoder, seed=7, lidar_scales=scales)).double().eval()
    rgb, sparse = (t.double() for t in batch(4))
    with torch.no_grad():
        got = model.run(rgb, sparse)
        want = reference_forward(model, rgb, sparse)
    assert got.shape == (2, 1, H, W)
    assert (got - want).abs().max().item() < 1e-10
    assert want.std() > 1e-3


def test_lidar_argument_and_config_errors():
    rgb, sparse = batch()
    model = unet("sfe")
    x = model_inputs(rgb, None, "rgb")
    with pytest.raises(ParameterError, match="needs lidar"):
        model(x)
    with pytest.raises(ParameterError, match="needs lidar"):
        model(x, sparse[:, 0])
    with pytest.raises(ParameterError, match="does not match"):
        model(x, sparse[:, :, :-1])
    with pytest.raises(ParameterError, match="LiDAR encoder") as err:
        DepthCompletionUNet("rgb", lidar_encoder="sparse")
    assert err.value.param == "lidar_encoder"
    # the configuration records it; configurations from before it mean 'none'
    cfg = model.config()
    assert cfg["lidar_encoder"] == "sfe"
    clone = build_model(cfg)
    assert clone.lidar_encoder == "sfe" and clone.state_dict().keys() == model.state_dict().keys()
    assert "lidar_encoder" not in unet("none").config()
    old = {"input_mode": "rgbd", "width": 4, "final_layer": False}
    assert build_model(old).lidar_encoder == "none" and build_model(old).lidar_branch is None
    # the fused levels are recorded; checkpoints from before (no key) fed every level
    assert cfg["lidar_scales"] == [2, 4, 8, 16] and clone.lidar_scales == (2, 4, 8, 16)
    legacy = {k: v for k, v in cfg.items() if k != "lidar_scales"}
    assert build_model(legacy).lidar_scales == (1, 2, 4, 8, 16)
    for bad in ((), (2, 2), (4, 2), (3,), (32,), (True,)):
        with pytest.raises(ParameterError, match="lidar_scales") as err:
            DepthCompletionUNet("rgb", width=4, lidar_encoder="sfe", lidar_scales=bad)
        assert err.value.param == "lidar_scales"


# -- the pose network -------------------------------------------------------------------------------
def pose(encoder, seed=0):
    torch.manual_seed(seed)
    return PoseNet(width=4, lidar_encoder=encoder)


def test_pose_lidar_branch_shapes_empty_map_and_gradients():
    rgb_a, sparse_a = batch(10, h=48, w=64)
    rgb_b, sparse_b = batch(11, h=48, w=64)
    lidar = torch.cat([sparse_a, sparse_b], dim=1)
    camera = pose("none", seed=1).eval()
    for encoder in ("sfe", "dense"):
        net = pose(encoder, seed=1).eval()
        assert net.uses_lidar and not camera.uses_lidar
        scales = net.lidar_branch.scales
        assert scales == (2, 4, 8, 16, 32) and net.lidar_branch.layout.depth_channels == 2
        # the pose encoder's own weights are those of the camera-only network
        own = {k: v for k, v in net.state_dict().items() if not k.startswith("lidar_branch.")}
        assert all(torch.equal(v, camera.state_dict()[k]) for k, v in own.items())
        with torch.no_grad():
            aa, t = net(rgb_a, rgb_b, lidar)
            assert aa.shape == (2, 3) and t.shape == (2, 3)
            ref = camera(rgb_a, rgb_b)
            changed = net(rgb_a, rgb_b, lidar)
            assert not torch.allclose(changed[1], ref[1])
            if encoder == "sfe":  # zero features without sites
                empty = net(rgb_a, rgb_b, torch.zeros_like(lidar))
                assert torch.equal(empty[0], ref[0]) and torch.equal(empty[1], ref[1])
        net.train()
        sum(o.sum() for o in net(rgb_a, rgb_b, lidar)).backward()
        assert net.lidar_branch.stem[0].weight.grad.abs().sum() > 0
        with pytest.raises(ParameterError, match="both frames"):
            net(rgb_a, rgb_b)
        with pytest.raises(ParameterError, match="both frames"):
            net(rgb_a, rgb_b, sparse_a)
        clone = build_pose_net(net.config())
        assert clone.lidar_encoder == encoder
        assert clone.state_dict().keys() == net.state_dict().keys()
    assert build_pose_net({"width": 4}).lidar_encoder == "none"
    with pytest.raises(ParameterError) as err:
        PoseNet(lidar_encoder="x")
    assert err.value.param == "pose_lidar_encoder"


def test_source_transforms_feed_each_pair_its_two_maps():
    net = pose("sfe", seed=2).eval()
    frames = [batch(20 + i, h=32, w=48) for i in range(3)]
    rgbs = [f[0] for f in frames]
    lidar = torch.cat([f[1] for f in frames], dim=1)  # (B, 3, H, W): prev, target, next
    with torch.no_grad():
        to_prev, to_next = source_transforms(net, *rgbs, lidar=lidar)
        want_prev = torch.linalg.inv(net.transform(rgbs[0], rgbs[1], lidar[:, 0:2]))
        want_next = net.transform(rgbs[1], rgbs[2], lidar[:, 1:3])
    assert torch.allclose(to_prev, want_prev, atol=1e-6)
    assert torch.allclose(to_next, want_next, atol=1e-6)


# -- data and settings -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def videos(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("lidar_ds")
    seqs = {
        f"s{i}": video(6, 32, 48, speed=0.5 + 0.15 * i, yaw_rate=0.01 * (i - 2), start=2.0 * i)
        for i in range(5)
    }
    splits = {"s0": "train", "s1": "train", "s2": "train", "s3": "val", "s4": "test"}
    return write_video_dataset(root / "ds", seqs, splits)


def test_triplets_carry_all_three_sparse_maps_cropped_and_flipped(videos):
    plain = TripletDataset(videos, "train", augment=True, crop=(24, 40), seed=3)
    lidar = TripletDataset(videos, "train", augment=True, crop=(24, 40), seed=3, sparse_frames=True)
    unaugmented = TripletDataset(videos, "train", crop=(24, 40))
    reader = lidar.reader
    flips = 0
    for i in range(len(lidar)):
        a, b = plain[i], lidar[i]
        assert "sparse_frames" not in a and b["sparse_frames"].shape == (3, 24, 40)
        for k in ("frames", "inputs", "sparse", "K"):
            assert torch.equal(a[k], b[k]), k
        assert torch.equal(b["sparse_frames"][1], b["sparse"][0])
        t = lidar.triplets[i]
        # reference: each frame's map read on its own, bottom-centre crop, the item's flip
        flipped = not torch.equal(b["frames"][1], unaugmented[i]["frames"][1])
        flips += flipped
        for k, pos in enumerate((t.previous, t.target, t.following)):
            m = reader.sample(pos)["sparse"][32 - 24 :, 4:44]
            m = m[:, ::-1] if flipped else m
            assert np.array_equal(b["sparse_frames"][k].numpy(), m), (i, k)
    assert 0 < flips < len(lidar)
    out = collate([lidar[0], lidar[1]])
    assert out["sparse_frames"].shape == (2, 3, 24, 40)


def test_settings_rules_and_round_trip():
    base = dict(dataset="x", out_dir="y")
    with pytest.raises(ParameterError, match="--input rgb") as err:
        TrainConfig(**base, lidar_encoder="sfe", input_mode="rgbd").validate()
    assert err.value.param == "input_mode"
    with pytest.raises(ParameterError) as err:
        TrainConfig(**base, lidar_encoder="minkowski", input_mode="rgb").validate()
    assert err.value.param == "lidar_encoder"
    with pytest.raises(ParameterError) as err:
        SelfSupSettings(pose_lidar_encoder="sparse").validate()
    assert err.value.param == "pose_lidar_encoder"
    c = TrainConfig(
        **base,
        input_mode="rgb",
        lidar_encoder="dense",
        selfsup=SelfSupSettings(pose_lidar_encoder="sfe"),
    )
    c.validate()
    again = TrainConfig.from_dict(json.loads(json.dumps(c.to_dict())))
    assert again == c
    old = c.to_dict()
    del old["lidar_encoder"], old["selfsup"]["pose_lidar_encoder"]
    old_cfg = TrainConfig.from_dict(old)
    assert old_cfg.lidar_encoder == "none" and old_cfg.selfsup.pose_lidar_encoder == "none"


# -- training, resume, evaluation ----------------------------------------------------------------------
def selfsup_config(dataset, out, **kw) -> TrainConfig:
    selfsup = {"pose_width": 4, "sparse_loss": "silog", "pose_lidar_encoder": "sfe"}
    selfsup.update(kw.pop("selfsup", {}))
    base = dict(
        dataset=str(dataset),
        out_dir=str(out),
        input_mode="rgb",
        lidar_encoder="sfe",
        width=4,
        epochs=2,
        batch_size=4,
        lr=1e-3,
        threads=1,
        pictures=1,
        selfsup=SelfSupSettings(**selfsup),
    )
    base.update(kw)
    return TrainConfig(**base)


def test_selfsup_sfe_is_deterministic_and_resumes_exactly(videos, tmp_path):
    train(selfsup_config(videos, tmp_path / "a"))
    train(selfsup_config(videos, tmp_path / "b"))
    rows = read_rows(tmp_path / "a")
    assert len(rows) == 2 and rows == read_rows(tmp_path / "b")
    a, b = load_checkpoint(tmp_path / "a" / "last.pt"), load_checkpoint(tmp_path / "b" / "last.pt")
    assert a.lidar_encoder == "sfe" and a.pose_config["lidar_encoder"] == "sfe"
    assert any(k.startswith("lidar_branch.") for k in a.model)
    assert any(k.startswith("lidar_branch.") for k in a.pose_model)
    assert state_equal(a.model, b.model) and state_equal(a.pose_model, b.pose_model)
    # 12 training triplets / batch 4 = 3 steps per epoch: stop mid-epoch 2, resume
    cut = train(selfsup_config(videos, tmp_path / "cut", max_steps=4))
    assert cut.steps == 4
    train(selfsup_config(videos, tmp_path / "cut"), resume=True)
    assert read_rows(tmp_path / "cut") == rows
    c = load_checkpoint(tmp_path / "cut" / "last.pt")
    assert state_equal(c.model, a.model) and state_equal(c.pose_model, a.pose_model)
    ma, mb = c.optimizer["state"], a.optimizer["state"]
    assert all(torch.equal(ma[k]["exp_avg_sq"], mb[k]["exp_avg_sq"]) for k in ma)
    # --resume keeps the encoders
    with pytest.raises(ParameterError, match="lidar_encoder"):
        train(
            selfsup_config(videos, tmp_path / "cut", lidar_encoder="dense", epochs=3),
            resume=True,
            explicit={"lidar_encoder"},
        )
    with pytest.raises(ParameterError, match="pose_lidar_encoder"):
        train(
            selfsup_config(videos, tmp_path / "cut", selfsup={"pose_lidar_encoder": "none"}),
            resume=True,
            explicit={"selfsup.pose_lidar_encoder"},
        )


def test_eval_of_an_sfe_checkpoint_equals_a_direct_prediction(videos, tmp_path):
    run = tmp_path / "run"
    train(selfsup_config(videos, run, epochs=1))
    res = evaluate_checkpoint(run / "best.pt", videos, split="test")
    assert res.lidar_encoder == "sfe" and not res.median_scaling and res.kind == "self-supervised"
    assert res.pose is not None and res.pose.n_snippets == 2 and np.isfinite(res.pose.ate_mean)
    # reference: the checkpoint's network on each test frame, metrics per image, averaged
    from sparsetools.io.dataset_reader import DatasetReader

    model = model_from_checkpoint(load_checkpoint(run / "best.pt")).eval()
    test = DatasetReader(videos).split("test")
    per = []
    for i in range(len(test)):
        s = test.sample(i)
        rgb = torch.from_numpy(s["rgb"].transpose(2, 0, 1).astype(np.float32) / 255)[None]
        sparse = torch.from_numpy(s["sparse"])[None, None]
        with torch.no_grad():
            d = model.depth_of(rgb, sparse)[0, 0].numpy()
        per.append(depth_metrics(d, s["gt"]))
    for k in ("abs_rel", "rmse", "delta1"):
        assert res.metrics[k] == pytest.approx(np.mean([m[k] for m in per]), rel=1e-5), k
    # without the LiDAR the same network predicts something else
    with torch.no_grad():
        s = test.sample(0)
        rgb = torch.from_numpy(s["rgb"].transpose(2, 0, 1).astype(np.float32) / 255)[None]
        sparse = torch.from_numpy(s["sparse"])[None, None]
        assert not torch.equal(
            model.depth_of(rgb, sparse), model.depth_of(rgb, torch.zeros_like(sparse))
        )


@pytest.fixture(scope="module")
def supervised_ds(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("lidar_sup_ds"))


def test_supervised_sfe_trains_resumes_and_best_reproduces_validation(supervised_ds, tmp_path):
    def cfg(out, **kw):
        base = dict(
            dataset=str(supervised_ds),
            out_dir=str(out),
            input_mode="rgb",
            lidar_encoder="sfe",
            width=4,
            epochs=2,
            batch_size=4,
            lr=3e-3,
            threads=1,
            pictures=1,
        )
        return TrainConfig(**{**base, **kw})

    train(cfg(tmp_path / "full"))
    train(cfg(tmp_path / "cut", max_steps=2))
    train(cfg(tmp_path / "cut"), resume=True)
    rows = read_rows(tmp_path / "full")
    assert read_rows(tmp_path / "cut") == rows
    full = load_checkpoint(tmp_path / "full" / "last.pt")
    assert state_equal(full.model, load_checkpoint(tmp_path / "cut" / "last.pt").model)
    assert full.config.lidar_encoder == "sfe" and full.model_config["lidar_encoder"] == "sfe"
    best = min(rows, key=lambda r: float(r["rmse"]))
    res = evaluate_checkpoint(tmp_path / "full" / "best.pt", supervised_ds, split="val")
    for k in METRIC_NAMES:
        assert res.metrics[k] == pytest.approx(float(best[k]), rel=1e-5), k


def test_a_checkpoint_from_before_the_lidar_encoder_loads_and_resumes(supervised_ds, tmp_path):
    """Runs saved before ``lidar_encoder`` existed have no such keys: they are 'none'."""
    run = tmp_path / "old"
    cfg = TrainConfig(
        dataset=str(supervised_ds), out_dir=str(run), width=4, epochs=1, batch_size=4, threads=1
    )
    train(cfg)
    for name in ("last.pt", "best.pt"):
        raw = torch.load(run / name, weights_only=True)
        del raw["config"]["lidar_encoder"]
        assert "lidar_encoder" not in raw["model_config"]
        torch.save(raw, run / name)
    ckpt = load_checkpoint(run / "last.pt")
    assert ckpt.lidar_encoder == "none" and ckpt.config.lidar_encoder == "none"
    assert model_from_checkpoint(ckpt).lidar_branch is None
    s = train(TrainConfig(**{**cfg.to_dict(), "epochs": 2}), resume=True, explicit={"epochs"})
    assert s.epochs_done == 2
    assert evaluate_checkpoint(run / "best.pt", supervised_ds, split="test").lidar_encoder == "none"


def test_cli_lidar_encoder_options(videos, tmp_path):
    runner = CliRunner()
    tiny = ["--width", "4", "--pose-width", "4", "--batch-size", "4", "--epochs", "1"]
    tiny += ["--threads", "1", "--pictures", "1"]
    run = tmp_path / "run"
    r = runner.invoke(
        cli,
        [
            *("train", str(videos), "-o", str(run), "--self-supervised", "--sparse-loss", "silog"),
            *("--lidar-encoder", "sfe", "--pose-lidar-encoder", "dense", *tiny, "--json"),
        ],
    )
    assert r.exit_code == 0, r.output
    saved = json.loads((run / "config.json").read_text())
    # --lidar-encoder makes the U-Net's input the image alone unless --input says otherwise
    assert saved["input_mode"] == "rgb" and saved["lidar_encoder"] == "sfe"
    assert saved["selfsup"]["pose_lidar_encoder"] == "dense"
    r = runner.invoke(cli, ["eval", "--checkpoint", str(run), str(videos), "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["lidar_encoder"] == "sfe" and out["pose"]["n_snippets"] == 2
    # early fusion and a LiDAR branch at once: a one-line error naming --input
    r = runner.invoke(
        cli,
        [
            *("train", str(videos), "-o", str(tmp_path / "x"), "--input", "rgbd"),
            *("--lidar-encoder", "dense", "--width", "4", "--epochs", "1"),
        ],
    )
    assert r.exit_code != 0 and "Traceback" not in r.output and "--input rgb" in r.output
    # the pose network's branch is an option of self-supervised training
    r = runner.invoke(
        cli, ["train", str(videos), "-o", str(tmp_path / "y"), "--pose-lidar-encoder", "sfe"]
    )
    assert r.exit_code == 2 and "--self-supervised" in r.output
    # --resume refuses another encoder, continues with the run's own
    r = runner.invoke(
        cli, ["train", str(videos), "-o", str(run), "--resume", "--lidar-encoder", "dense"]
    )
    assert r.exit_code != 0 and "lidar_encoder" in r.output
    r = runner.invoke(cli, ["train", str(videos), "-o", str(run), "--resume", "--epochs", "2"])
    assert r.exit_code == 0, r.output
    assert load_checkpoint(run / "last.pt").state.epoch == 2
