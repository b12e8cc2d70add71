"""Early-fusion U-Net: shapes per input mode, odd sizes, widths, input stacking."""

from __future__ import annotations

import pytest
import torch

from sparsetools.errors import ParameterError
from sparsetools.train.model import (
    INPUT_CHANNELS,
    DepthCompletionUNet,
    build_model,
    disparity_to_depth,
    model_inputs,
)


@pytest.mark.parametrize("mode", ["rgb", "rgbd", "rgbdm"])
@pytest.mark.parametrize("size", [(32, 48), (37, 51), (1, 1), (17, 16)])
def test_shapes_each_mode_and_odd_sizes(mode, size):
    torch.manual_seed(0)
    model = DepthCompletionUNet(mode, width=4, final_layer=True).eval()
    x = torch.rand(2, INPUT_CHANNELS[mode], *size)
    with torch.no_grad():
        y = model(x)
    assert y.shape == (2, 1, *size)
    assert torch.isfinite(y).all()
    assert (y > 0).all()  # softplus head: positive depth


def test_widths_scale_with_width():
    assert DepthCompletionUNet("rgb", width=32).widths == (32, 64, 128, 256, 512)
    assert DepthCompletionUNet("rgb", width=8).widths == (8, 16, 32, 64, 128)
    n8 = sum(p.numel() for p in DepthCompletionUNet("rgb", width=8).parameters())
    n16 = sum(p.numel() for p in DepthCompletionUNet("rgb", width=16).parameters())
    assert 3.5 < n16 / n8 < 4.1  # conv weights grow with width^2


def test_encoder_is_five_levels_down_to_one_sixteenth():
    model = DepthCompletionUNet("rgbd", width=4)
    shapes = []
    hooks = [b.register_forward_hook(lambda m, i, o: shapes.append(o.shape)) for b in model.encoder]
    model(torch.rand(1, 4, 64, 96))
    for h in hooks:
        h.remove()
    assert [s[-2:] for s in shapes] == [(64, 96), (32, 48), (16, 24), (8, 12), (4, 6)]
    assert [s[1] for s in shapes] == [4, 8, 16, 32, 64]


def test_initial_prediction_is_constant_ten_metres():
    model = DepthCompletionUNet("rgbdm", width=4).eval()
    with torch.no_grad():
        y = model(torch.rand(1, 5, 20, 30))
    assert torch.allclose(y, torch.full_like(y, 10.0), atol=1e-4)


def test_padding_does_not_leak_into_prediction_region():
    # Bottom/right zero padding: the output for an odd-size input equals the top-left of the
    # output for the same input explicitly zero-padded to a multiple of 16.
    torch.manual_seed(1)
    model = DepthCompletionUNet("rgbd", width=4, final_layer=True).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.1)
        x = torch.rand(1, 4, 30, 45)
        padded = torch.nn.functional.pad(x, (0, 3, 0, 2))
        assert torch.allclose(model(x), model(padded)[:, :, :30, :45], atol=1e-6)


def test_gradients_reach_the_input_layer():
    torch.manual_seed(2)
    model = DepthCompletionUNet("rgbd", width=4)
    x = torch.rand(2, 4, 32, 32)
    for _ in range(2):  # the zero-initialised head passes gradients from the 2nd step on
        model.zero_grad()
        y = model(x)
        (y - 20).abs().mean().backward()
        with torch.no_grad():
            model.head.weight.add_(0.01)
    assert model.stem[0].weight.grad.abs().sum() > 0


def test_model_inputs_channels():
    rgb = torch.rand(2, 3, 5, 7)
    sparse = torch.zeros(2, 1, 5, 7)
    sparse[0, 0, 2, 3] = 40.0
    assert model_inputs(rgb, sparse, "rgb").shape == (2, 3, 5, 7)
    d = model_inputs(rgb, sparse, "rgbd")
    assert d.shape == (2, 4, 5, 7)
    assert d[0, 3, 2, 3] == pytest.approx(2.0)  # 40 m / 20 m
    m = model_inputs(rgb, sparse, "rgbdm")
    assert m.shape == (2, 5, 5, 7)
    assert m[:, 4].sum() == 1 and m[0, 4, 2, 3] == 1
    assert torch.allclose(m[:, :4], d)
    with pytest.raises(ParameterError, match="needs sparse"):
        model_inputs(rgb, None, "rgbd")
    with pytest.raises(ParameterError, match="unknown input mode"):
        model_inputs(rgb, sparse, "rgbx")


def test_wrong_channels_and_config_round_trip():
    model = DepthCompletionUNet("rgbd", width=4, final_layer=True)
    with pytest.raises(ParameterError, match="expects"):
        model(torch.rand(1, 3, 16, 16))
    clone = build_model(model.config())
    clone.load_state_dict(model.state_dict())
    assert clone.config() == {"input_mode": "rgbd", "width": 4, "final_layer": True}
    with pytest.raises(ParameterError):
        DepthCompletionUNet("depth")
    with pytest.raises(ParameterError):
        DepthCompletionUNet("rgb", width=0)
    with pytest.raises(ParameterError, match="lacks"):
        build_model({"input_mode": "rgb"})


def test_final_layer_can_put_measured_depth_in_place():
    # adjust = D + (S - M * D) at the centre tap: the measured depth wherever there is one,
    # the network's prediction elsewhere -- a linear function of the layer's inputs.
    torch.manual_seed(3)
    model = DepthCompletionUNet("rgbd", width=4, final_layer=True).eval()
    c_in = INPUT_CHANNELS["rgbd"]
    with torch.no_grad():
        model.adjust.weight.zero_()
        # inputs: [D/20, rgb (3), S/20, M, M*D/20]
        model.adjust.weight[0, 1 + 3, 1, 1] = 1.0  # + S
        model.adjust.weight[0, 1 + c_in + 1, 1, 1] = -1.0  # - M * D
        rgb = torch.rand(1, 3, 20, 24)
        sparse = torch.zeros(1, 1, 20, 24)
        sparse[0, 0, 5, 7], sparse[0, 0, 19, 23] = 33.0, 4.5
        out = model(model_inputs(rgb, sparse, "rgbd"))
        coarse = DepthCompletionUNet.forward(
            _without_final(model), model_inputs(rgb, sparse, "rgbd")
        )
    assert out[0, 0, 5, 7] == pytest.approx(33.0, rel=1e-5)
    assert out[0, 0, 19, 23] == pytest.approx(4.5, rel=1e-5)
    empty = sparse[0, 0] == 0
    assert torch.allclose(out[0, 0][empty], coarse[0, 0][empty], atol=1e-4)


def _without_final(model):
    clone = DepthCompletionUNet(model.input_mode, width=model.width, final_layer=False).eval()
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("adjust.")}
    clone.load_state_dict(state)
    return clone


def test_final_layer_inputs_per_mode():
    assert DepthCompletionUNet("rgb", width=4, final_layer=True).adjust.in_channels == 1 + 3
    assert DepthCompletionUNet("rgbd", width=4, final_layer=True).adjust.in_channels == 1 + 4 + 2
    assert DepthCompletionUNet("rgbdm", width=4, final_layer=True).adjust.in_channels == 1 + 5 + 2


# -- self-supervised (multi-scale disparity) output ----------------------------------------------
@pytest.mark.parametrize("size", [(32, 48), (37, 51)])
def test_disparity_output_four_scales(size):
    torch.manual_seed(0)
    model = DepthCompletionUNet("rgbd", width=4, output="disparity").eval()
    with torch.no_grad():
        x = torch.rand(2, 4, *size)
        out = model(x)
        depth = model.predict_depth(x)
    h, w = size
    assert [tuple(d.shape) for d in out] == [
        (2, 1, -(-h // 2**s), -(-w // 2**s)) for s in range(4)
    ]  # finest first, ceil(size / 2^s)
    assert all(((d > 0) & (d < 1)).all() for d in out)  # sigmoid
    assert depth.shape == (2, 1, h, w)
    torch.testing.assert_close(depth, disparity_to_depth(out[0], 0.1, 100.0))
    assert (depth >= 0.1).all() and (depth <= 100.0).all()


def test_disparity_to_depth_formula():
    sigma = torch.tensor([0.0, 1.0, 0.5, 0.25], dtype=torch.float64)
    d = disparity_to_depth(sigma, 0.1, 100.0)
    expected = [
        1 / (0.01 + (10 - 0.01) * s) for s in sigma.tolist()
    ]  # 1 / (1/max + (1/min - 1/max) s)
    torch.testing.assert_close(d, torch.tensor(expected, dtype=torch.float64))
    assert float(d[0]) == pytest.approx(100.0) and float(d[1]) == pytest.approx(0.1)


def test_disparity_initial_depth_and_config():
    model = DepthCompletionUNet("rgb", width=4, output="disparity", initial_depth=10.0).eval()
    with torch.no_grad():
        depth = model.predict_depth(torch.rand(1, 3, 16, 32))
    torch.testing.assert_close(depth, torch.full_like(depth, 10.0), rtol=1e-4, atol=0)
    clone = build_model(model.config())
    assert clone.output == "disparity" and clone.depth_range == (0.1, 100.0)
    assert clone.initial_depth == 10.0
    assert set(clone.state_dict()) == set(model.state_dict())
    # supervised models keep their three configuration keys (old checkpoints load unchanged)
    assert DepthCompletionUNet("rgb", width=4).config() == {
        "input_mode": "rgb",
        "width": 4,
        "final_layer": False,
    }
    with pytest.raises(ParameterError, match="final"):
        DepthCompletionUNet("rgb", output="disparity", final_layer=True)
    with pytest.raises(ParameterError):
        DepthCompletionUNet("rgb", output="logits")
    with pytest.raises(ParameterError, match="depth_range"):
        DepthCompletionUNet("rgb", output="disparity", depth_range=(5.0, 1.0))
