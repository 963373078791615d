"""The folded multi-scale network (denoise.inference_unet) equals the training module in eval mode.

Tolerance: transfer-space outputs within 2e-5 absolute (float32 rounding of the folded weights,
other summation orders), at odd sizes, 1x1, with and without the noise and aux inputs (each
``aux_mode``, the prefilter).
"""
from __future__ import annotations

import dataclasses

import pytest
import torch

from denoise.folded import prepare_for_inference
from model.config import AUX_MODES, ModelConfig
from denoise.inference_unet import InferenceUNet, _upsample_into, shuffle_order, shuffled_output, unshuffled_input
from model.network import network_input
from model.unet import pad_to_alignment
from tests.test_model_unet import TINY, trained_like

NET_ATOL = 2e-5


@pytest.mark.parametrize("config", [
    TINY,
    dataclasses.replace(TINY, levels=3, layers=2, noise_input=True),
    dataclasses.replace(TINY, arch="plain_unet", noise_input=True),
    dataclasses.replace(TINY, output="direct", aux_inputs=True, noise_input=True),
    dataclasses.replace(TINY, levels=3, noise_input=True, head=6),
    dataclasses.replace(TINY, levels=3, noise_input=True, kernel=5),
    dataclasses.replace(TINY, arch="plain_unet", kernel=3),
    *(dataclasses.replace(TINY, levels=3, kernel=3, noise_input=True, aux_inputs=True, aux_mode=mode,
                          aux_prefilter="bilateral") for mode in AUX_MODES),
    dataclasses.replace(TINY, arch="plain_unet", kernel=3, aux_inputs=True, aux_mode="levels"),
    dataclasses.replace(TINY, arch="plain_unet", kernel=3, aux_inputs=True, aux_mode="kernel"),
], ids=["dense", "dense-noise", "plain-noise", "direct-aux-noise", "dense-noise-head", "dense-noise-kernel",
        "plain-kernel", *(f"dense-noise-aux-{mode}-prefiltered" for mode in AUX_MODES), "plain-aux-levels",
        "plain-aux-kernel"])
@pytest.mark.parametrize("positive", [False, True], ids=["any-bn-scale", "positive-bn-scales"])
def test_folded_unet_equals_the_training_module(config: ModelConfig, positive: bool) -> None:
    """Both ways of the clamp: BN scales of both signs (clamp) and all positive (one maximum)."""
    model = trained_like(config, positive=positive)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    net = prepare_for_inference(model)
    assert isinstance(net, InferenceUNet) and not net.training
    torch.manual_seed(1)
    for h, w in ((1, 1), (19, 45), (32, 24)):
        x = torch.rand(2, config.image_channels, h, w)
        with torch.no_grad():
            want, got = model(x), net(x)
        assert got.shape == (2, 3, h, w)
        torch.testing.assert_close(got, want, rtol=0, atol=NET_ATOL)
    for key, value in model.state_dict().items():  # folding copies, never changes the model
        assert torch.equal(value, before[key])


def test_upsample_into_a_strided_slice() -> None:
    buf = torch.zeros(1, 5, 4, 6).contiguous(memory_format=torch.channels_last)
    low = torch.arange(1 * 2 * 2 * 3, dtype=torch.float32).view(1, 2, 2, 3)
    _upsample_into(buf[:, 1:3], low)
    torch.testing.assert_close(buf[:, 1:3], torch.nn.functional.interpolate(low, scale_factor=2.0))
    assert buf[:, 0].eq(0).all() and buf[:, 3:].eq(0).all()


@pytest.mark.parametrize("channels", [3, 7, 13])
@pytest.mark.parametrize("h, w", [(1, 1), (19, 45), (32, 24), (2, 3)])
@pytest.mark.parametrize("channels_last", [False, True])
def test_unshuffled_input_is_torch_s_unshuffle_of_the_padded_input(channels: int, h: int, w: int,
                                                                   channels_last: bool) -> None:
    """The strided copies give exactly pad_to_alignment(network_input) and its pixel_unshuffle,
    the channels in shuffle_order, from an NCHW or a channels_last image, in float32 and bfloat16."""
    torch.manual_seed(2)
    image = torch.rand(2, channels, h, w) * 4 - 1
    if channels_last:
        image = image.contiguous(memory_format=torch.channels_last)
    want_padded = pad_to_alignment(network_input(image), 8)
    want = torch.nn.functional.pixel_unshuffle(want_padded, 2)[:, shuffle_order(channels + 6)]
    for dtype in (torch.float32, torch.bfloat16):
        padded, raw = unshuffled_input(image, 8, dtype)
        assert torch.equal(padded.permute(0, 3, 1, 2), want_padded)
        assert raw.dtype == dtype and torch.equal(raw, want.to(dtype))
        assert raw.is_contiguous(memory_format=torch.channels_last)


def test_shuffle_order_is_a_permutation_that_shuffled_output_undoes() -> None:
    assert sorted(shuffle_order(9).tolist()) == list(range(36))
    assert shuffle_order(3).tolist() == [0, 4, 8, 1, 5, 9, 2, 6, 10, 3, 7, 11]
    torch.manual_seed(3)
    y = torch.rand(2, 12, 5, 7)
    for dtype, memory in ((torch.float32, torch.contiguous_format), (torch.bfloat16, torch.channels_last)):
        block_major = y.to(dtype)[:, shuffle_order(3)].contiguous(memory_format=memory)
        want = torch.nn.functional.pixel_shuffle(y.to(dtype).float(), 2)[..., :9, :13]
        got = shuffled_output(block_major, 9, 13)
        assert got.dtype == torch.float32 and torch.equal(got, want)
