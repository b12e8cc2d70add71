"""Typed records of training: TrainConfig round trips and the resume rule; checkpoint files."""

from __future__ import annotations

import math

import pytest
import torch

from sparsetools.errors import FormatError, ParameterError
from sparsetools.train.checkpoint import (
    BestRecord,
    TrainingState,
    load_checkpoint,
    save_checkpoint,
)
from sparsetools.train.config import SelfSupSettings, TrainConfig, resumed_config
from sparsetools.train.model import DepthCompletionUNet
from sparsetools.train.selfsup.pose_net import PoseNet


def test_config_round_trip_with_and_without_selfsup():
    for selfsup in (None, SelfSupSettings(sparse_loss="silog", depth_range=(0.5, 80.0), sbm=True)):
        c = TrainConfig(dataset="d", out_dir="o", crop=(32, 64), selfsup=selfsup)
        d = c.to_dict()
        assert d["crop"] == [32, 64]
        back = TrainConfig.from_dict(d)
        assert back == c and back.self_supervised == (selfsup is not None)
    assert TrainConfig.from_dict({"dataset": "d", "out_dir": "o", "unknown": 1}).selfsup is None


def test_config_checks_come_from_the_field_annotations():
    from dataclasses import dataclass, fields

    from sparsetools.train import config as cfg

    # every field is checked, in field order (the first wrong one is the one named)
    assert list(cfg._CONFIG_KINDS) == [f.name for f in fields(TrainConfig) if f.name != "selfsup"]
    assert list(cfg._SELFSUP_KINDS) == [f.name for f in fields(SelfSupSettings)]
    # the messages of 0.2.0's hand-written tables
    for kw, message in (
        ({"crop": [1, 2, 3]}, "crop must be null or two integers, got (1, 2, 3)"),
        ({"max_steps": 2.5}, "max_steps must be an integer or null, got 2.5"),
        ({"lr": "0.1"}, "lr must be a number, got '0.1'"),
        ({"final_layer": 1}, "final_layer must be true or false, got 1"),
        ({"scale_range": [1, "a"]}, "scale_range must be two numbers, got (1, 'a')"),
    ):
        with pytest.raises(ParameterError) as info:
            TrainConfig.from_dict({"dataset": "d", "out_dir": "o", **kw})
        # the error names the field's option (crop -> --crop-size)
        assert info.value.message == message
        assert info.value.param == cfg.option_of(next(iter(kw)))
    with pytest.raises(ParameterError) as info:
        SelfSupSettings.from_dict({"pose_width": "4"})
    assert info.value.message == "pose_width must be an integer, got '4'"

    @dataclass
    class WithANewField:
        size: int = 1
        ratio: complex = 1j

    # a field of a type nobody said how to check stops the import, not a run
    with pytest.raises(TypeError, match=r"WithANewField.ratio: no check .*complex"):
        cfg._field_kinds(WithANewField)


def test_resume_rule():
    saved = TrainConfig(dataset="d", out_dir="o", lr=1e-3, epochs=2, selfsup=SelfSupSettings())
    # resumable fields come from the new configuration, everything else from the run
    mine = TrainConfig(dataset="d2", out_dir="o", lr=5e-3, epochs=9, threads=1)
    got = resumed_config(mine, saved, explicit={"epochs"})
    assert got.epochs == 9 and got.threads == 1 and got.lr == 1e-3 and got.dataset == "d2"
    assert got.selfsup == saved.selfsup
    with pytest.raises(ParameterError, match="lr is 0.001 there") as info:
        resumed_config(mine, saved, explicit={"lr"})
    assert info.value.option == "--lr"
    changed = TrainConfig(dataset="d", out_dir="o", selfsup=SelfSupSettings(sbm=True))
    with pytest.raises(ParameterError, match="selfsup.sbm") as info:
        resumed_config(changed, saved, explicit={"selfsup.sbm"})
    assert info.value.option == "--sbm"
    with pytest.raises(ParameterError, match="self-supervised run"):
        resumed_config(TrainConfig(dataset="d", out_dir="o"), saved, explicit={"self_supervised"})
    # no explicit set: every non-resumable field is compared
    with pytest.raises(ParameterError):
        resumed_config(mine, saved, explicit=None)


def test_training_state_counts():
    s = TrainingState()
    s.add_batch({"loss": 2.0, "photometric": 0.5}, 4)
    s.add_batch({"loss": 1.0, "photometric": 0.25}, 2)
    assert s.step == 2 and s.batch_in_epoch == 2 and s.epoch_samples == 6
    assert s.epoch_mean("loss") == pytest.approx((8 + 2) / 6)
    assert s.epoch_mean("photometric") == pytest.approx((2 + 0.5) / 6)
    back = TrainingState.from_dict(s.to_dict())
    assert back == s
    s.start_epoch()
    assert s.epoch == 1 and s.batch_in_epoch == 0 and s.epoch_sums == {} and s.step == 2
    assert BestRecord().improves(1e9) and not BestRecord(value=1.0).improves(1.0)
    assert math.isinf(BestRecord().value)


def test_checkpoint_files(tmp_path):
    torch.manual_seed(0)
    config = TrainConfig(
        dataset="d", out_dir="o", input_mode="rgb", width=4, selfsup=SelfSupSettings(pose_width=2)
    )
    model = DepthCompletionUNet("rgb", width=4, output="disparity")
    pose = PoseNet(width=2)
    opt = torch.optim.Adam([*model.parameters(), *pose.parameters()])
    state = TrainingState(step=3, epoch_sums={"loss": 1.5}, epoch_samples=3)
    save_checkpoint(
        tmp_path / "a.pt",
        config=config,
        model=model,
        optimizer=opt,
        state=state,
        pose_model=pose,
        sbm_threshold=0.25,
    )
    ck = load_checkpoint(tmp_path / "a.pt")
    assert ck.kind == "self-supervised" and ck.config == config and ck.state == state
    assert ck.sbm_threshold == 0.25 and ck.pose_config == {"width": 2}
    assert all(torch.equal(ck.model[k], v) for k, v in model.state_dict().items())
    # a version-1 file (before self-supervised training) still loads
    raw = torch.load(tmp_path / "a.pt", weights_only=True)
    sup = TrainConfig(dataset="d", out_dir="o", input_mode="rgb", width=4)
    raw.update(
        version=1, config=sup.to_dict(), model_config=DepthCompletionUNet("rgb", width=4).config()
    )
    raw["model"] = DepthCompletionUNet("rgb", width=4).state_dict()
    for key in ("kind", "epoch_sums", "pose_model", "pose_config", "sbm_threshold"):
        raw.pop(key)
    torch.save(raw, tmp_path / "v1.pt")
    old = load_checkpoint(tmp_path / "v1.pt")
    assert old.kind == "supervised" and old.state.epoch_mean("loss") == pytest.approx(0.5)
    # a self-supervised checkpoint without its pose network is refused
    raw = torch.load(tmp_path / "a.pt", weights_only=True)
    raw.pop("pose_model")
    torch.save(raw, tmp_path / "nopose.pt")
    with pytest.raises(FormatError, match="pose network"):
        load_checkpoint(tmp_path / "nopose.pt")
    raw = torch.load(tmp_path / "a.pt", weights_only=True)
    raw["version"] = 99
    torch.save(raw, tmp_path / "new.pt")
    with pytest.raises(FormatError, match="newer"):
        load_checkpoint(tmp_path / "new.pt")
