"""Networks: gradient channels, shapes for every preset, residual/direct modes, init."""
from __future__ import annotations

import pytest
import torch

from model.architectures import build_model
from model.config import PRESETS, ModelConfig, preset
from model.network import FlatDenseNet, DenseBlock, PlainStack, gradient_channels, network_input

TINY = ModelConfig(layers=2, growth=4, init_features=8)


def test_gradient_channels_on_ramp() -> None:
    h, w = 5, 6
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                          indexing="ij")
    img = torch.stack([2.0 * x, 3.0 * y, x + y]).unsqueeze(0)  # 1x3xHxW
    grads = gradient_channels(img)
    assert grads.shape == (1, 6, h, w)
    dx, dy = grads[0, :3], grads[0, 3:]
    expect_dx = torch.tensor([2.0, 0.0, 1.0]).view(3, 1, 1).expand(3, h, w).clone()
    expect_dx[:, :, -1] = 0.0
    expect_dy = torch.tensor([0.0, 3.0, 1.0]).view(3, 1, 1).expand(3, h, w).clone()
    expect_dy[:, -1, :] = 0.0
    torch.testing.assert_close(dx, expect_dx, rtol=0, atol=1e-6)
    torch.testing.assert_close(dy, expect_dy, rtol=0, atol=1e-6)


def test_network_input_layout() -> None:
    img = torch.rand(2, 9, 7, 8)
    inp = network_input(img)
    assert inp.shape == (2, 15, 7, 8)
    torch.testing.assert_close(inp[:, :3], img[:, :3])
    torch.testing.assert_close(inp[:, 3:9], gradient_channels(img[:, :3]))
    torch.testing.assert_close(inp[:, 9:], img[:, 3:])


@pytest.mark.parametrize("name", sorted(n for n in PRESETS if not PRESETS[n].multiscale))
@pytest.mark.parametrize("arch", ["densenet", "plaincnn"])
@pytest.mark.parametrize("aux", [False, True])
def test_shapes_every_preset(name: str, arch: str, aux: bool) -> None:
    torch.manual_seed(0)
    config = preset(name, arch=arch, aux_inputs=aux)
    model = build_model(config).eval()
    assert model.head[0].in_channels == (15 if aux else 9)
    assert model.tail[-1].out_channels == 3
    with torch.no_grad():
        out = model(torch.rand(2, config.image_channels, 11, 13))
    assert out.shape == (2, 3, 11, 13) and bool(torch.isfinite(out).all())


def test_dense_block_structure() -> None:
    model = build_model(preset("paper"))
    block = model.body
    assert isinstance(block, DenseBlock) and len(block.layers) == 20
    assert block.out_channels == 24 + 20 * 12
    first = block.layers[0].body
    assert [type(m).__name__ for m in first] == ["BatchNorm2d", "ReLU", "Conv2d", "BatchNorm2d", "ReLU", "Conv2d"]
    assert first[2].kernel_size == (1, 1) and first[2].out_channels == 48
    assert first[5].kernel_size == (3, 3) and first[5].out_channels == 12
    assert model.head[0].kernel_size == (7, 7) and model.tail[-1].kernel_size == (3, 3)
    assert isinstance(build_model(preset("paper", arch="plaincnn")).body, PlainStack)


def test_residual_and_direct_modes() -> None:
    torch.manual_seed(0)
    img = torch.rand(1, 3, 9, 9)
    for output in ("residual", "direct"):
        model = FlatDenseNet(ModelConfig(layers=2, growth=4, init_features=8, output=output)).eval()
        torch.nn.init.zeros_(model.tail[-1].weight)
        with torch.no_grad():
            out = model(img)
        expected = img if output == "residual" else torch.zeros_like(img)
        torch.testing.assert_close(out, expected)


def test_he_init() -> None:
    torch.manual_seed(0)
    model = build_model(preset("paper"))
    conv = model.body.layers[19].body[2]  # 1x1 conv with 252 inputs
    fan_in = conv.weight[0].numel()
    assert float(conv.weight.detach().std()) == pytest.approx((2.0 / fan_in) ** 0.5, rel=0.1)
    norms = [m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert all(float(m.weight.detach().min()) == 1.0 and float(m.bias.detach().abs().max()) == 0.0 for m in norms)


def test_channels_last_same_output() -> None:
    torch.manual_seed(0)
    model = build_model(TINY).eval()
    img = torch.rand(2, 3, 10, 10)
    with torch.no_grad():
        ref = model(img)
        out = model.to(memory_format=torch.channels_last)(img.contiguous(memory_format=torch.channels_last))
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)


def test_untrained_residual_model_is_identity_direct_is_not() -> None:
    torch.manual_seed(0)
    img = torch.rand(1, 3, 12, 12) * 0.1
    with torch.no_grad():
        assert torch.equal(build_model(TINY).eval()(img), img)
        direct = build_model(ModelConfig(layers=2, growth=4, init_features=8, output="direct")).eval()
        assert float(direct.tail[-1].weight.abs().max()) > 0
