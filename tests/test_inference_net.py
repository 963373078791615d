"""The inference-only network (denoise.inference_net) equals the training module in eval mode.

Tolerances: transfer-space outputs of the folded network within 2e-5 absolute of the eager
module (float32 rounding of the folded weights, a different summation order); the radiance y of the
whole chain (Denoiser) within 2e-4 x (1 + y): the log transfer's inverse multiplies an absolute
transfer-space error by 11.1 x (1 + y), so near black the bound is absolute (on an Intel Xeon
with AVX-512 one pixel of radiance 0.0025 differed by 2e-6, over the 1e-6 this test once allowed).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from model.checkpoint import save_checkpoint
from model.config import ModelConfig
from denoise.folded import prepare_for_inference
from denoise.inference_net import _ClampConv1x1, bn_affine, fold_conv_bn, relu_affine_as_clamp
from model.architectures import build_model
from imaging.errors import DenoiserError
from denoise.denoiser import Denoiser
from tests.nets import randomize_batchnorm

NET_ATOL = 2e-5
CHAIN_RTOL = 2e-4


def _trained_like(config: ModelConfig, seed: int = 0, positive: bool = False) -> torch.nn.Module:
    """A random model with BN statistics and affine parameters of both signs, as after training."""
    torch.manual_seed(seed)
    model = build_model(config)
    randomize_batchnorm(model, 0.2, (0.3, 2.0), bias=0.2, positive=positive)
    with torch.no_grad():
        torch.nn.init.normal_(model.tail[-1].weight, std=0.05)  # not the identity at init
    return model.eval()


def test_relu_affine_as_clamp_is_exact(rng: np.random.Generator) -> None:
    scale = torch.tensor([2.0, -0.5, 0.0, 0.0, 1e-3, 1e-45], dtype=torch.float64)
    shift = torch.tensor([0.3, 0.2, 0.7, -0.4, -0.1, 0.5], dtype=torch.float64)
    s, lo, hi, const = relu_affine_as_clamp(scale, shift)
    assert s[-1] == 0 and torch.isfinite(const).all()  # a near-zero scale: a constant channel
    x = torch.from_numpy(rng.normal(0, 200, (1, 6, 7, 7)))
    want = torch.relu(scale.view(1, -1, 1, 1) * x + shift.view(1, -1, 1, 1))
    got = s.double().view(1, -1, 1, 1) * torch.clamp(x, lo.double(), hi.double()) + const.double()
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)


def test_fold_conv_bn_equals_conv_then_bn() -> None:
    model = _trained_like(ModelConfig(layers=2, growth=4, init_features=8))
    conv, bn, _ = model.head
    x = torch.rand(1, 9, 11, 13)
    weight, bias = fold_conv_bn(conv, bn)
    with torch.no_grad():
        torch.testing.assert_close(torch.nn.functional.conv2d(x, weight, bias, padding=3), bn(conv(x)),
                                   rtol=1e-5, atol=1e-5)
    scale, shift = bn_affine(bn)
    with torch.no_grad():
        y = torch.rand(1, 8, 5, 5)
        torch.testing.assert_close(scale.view(1, -1, 1, 1) * y + shift.view(1, -1, 1, 1), bn(y))


@pytest.mark.parametrize("config", [
    ModelConfig(layers=4, growth=4, init_features=8),
    ModelConfig(layers=3, growth=6, init_features=8, output="direct", transfer="pu"),
    ModelConfig(layers=3, growth=4, init_features=8, arch="plaincnn"),
    ModelConfig(layers=2, growth=4, init_features=8, aux_inputs=True),
], ids=["densenet", "direct", "plaincnn", "aux"])
@pytest.mark.parametrize("positive", [False, True], ids=["any-bn-scale", "positive-bn-scales"])
def test_inference_net_equals_eager_model(config: ModelConfig, positive: bool) -> None:
    """Both ways of the clamp: BN scales of both signs (clamp) and all positive (one maximum)."""
    model = _trained_like(config, positive=positive)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    net = prepare_for_inference(model)
    torch.manual_seed(1)
    for h, w in ((1, 1), (17, 29), (32, 24)):
        x = torch.rand(1, config.image_channels, h, w) * 0.4
        with torch.inference_mode():
            want, got = model(x), net(x)
        assert got.shape == want.shape
        assert float((got - want).abs().max()) < NET_ATOL
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # original untouched


def test_denoiser_optimized_equals_plain(tmp_path: Path, rng: np.random.Generator) -> None:
    config = ModelConfig(layers=5, growth=4, init_features=8)
    path = tmp_path / "m.ckpt"
    save_checkpoint(path, _trained_like(config), step=0)
    img = (rng.random((40, 36, 3)) ** 3 * 20).astype(np.float32)
    fast = Denoiser(path, max_memory_mb=0.2, precision="float32").denoise_array(img)
    plain = Denoiser(path, max_memory_mb=0.2, optimize=False).denoise_array(img)
    assert fast.tiles > 1
    np.testing.assert_allclose(fast.image, plain.image, rtol=CHAIN_RTOL, atol=CHAIN_RTOL)


def test_denoiser_refuses_flips_for_a_model_with_aux_inputs(tmp_path: Path) -> None:
    path = tmp_path / "aux.ckpt"
    save_checkpoint(path, _trained_like(ModelConfig(layers=2, growth=4, init_features=8, aux_inputs=True)), step=0)
    assert Denoiser(path).flips == 1
    with pytest.raises(DenoiserError, match="flips need a model without albedo/normal"):
        Denoiser(path, flips=2)


@pytest.mark.parametrize("order", [None, torch.tensor([3, 0, 2, 1, 7, 5, 6, 4])], ids=["in-order", "permuted"])
def test_affine_pre_activation_is_precise_in_bfloat16(order: torch.Tensor | None) -> None:
    """Features far from 0 with a small spread (BN mean 50, std 0.1, as a dense buffer's channels
    can be): in bfloat16 the clamp form's (W*s) @ clamp(x) and bias W @ c are terms of ~10^2 that
    cancel to outputs of ~1, and their rounding stays; the affine form rounds relu(s*x + t) itself.
    The inputs are exact in bfloat16 (multiples of 1/4 near 50), so only the two forms differ."""
    torch.manual_seed(0)
    bn1, conv, bn2 = torch.nn.BatchNorm2d(8).eval(), torch.nn.Conv2d(8, 6, 1, bias=False), torch.nn.BatchNorm2d(6).eval()
    with torch.no_grad():
        bn1.running_mean.fill_(50.0)
        bn1.running_var.fill_(0.01)
    x = (50.0 + torch.randint(-8, 9, (1, 8, 9, 7)) / 4).contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        want = bn2(conv(torch.relu(bn1(x)))).relu()  # x - 50 is exact in float32
    seen = x if order is None else x[:, order]  # the channels as the folded net receives them
    errors = {}
    for affine in (False, True):
        exact = _ClampConv1x1(bn1, conv, bn2, order, affine=affine)
        half = _ClampConv1x1(bn1, conv, bn2, order, affine=affine).to(torch.bfloat16)
        with torch.inference_mode():
            assert float((exact(seen) - want).abs().max()) < 1e-3  # both exact in float32
            errors[affine] = float((half(seen.bfloat16()).float() - want).abs().max())
    # outputs of up to ~12: the affine form within bfloat16's rounding of them, the clamp form ~20x off
    assert errors[True] < 0.1 and errors[False] > 10 * errors[True], errors
