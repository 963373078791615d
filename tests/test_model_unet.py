"""The multi-scale networks (model.unet): shapes at any size, reach, alignment, plain-vs-dense cost."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from imaging.errors import ConfigError
from model.architectures import alignment, build_model, receptive_radius
from model.config import PRESETS, ModelConfig
from denoise.chain import denoise_image
from model.unet import MultiScaleDenoiser, add_kernel_, apply_kernel, conv_macs_per_pixel, kernel_offsets, pad_to_alignment
from tests.nets import randomize_batchnorm

TINY = ModelConfig(arch="dense_unet", layers=1, growth=4, init_features=8, levels=2, transfer="pu")


def trained_like(config: ModelConfig, seed: int = 0, positive: bool = False) -> torch.nn.Module:
    """A random multi-scale model with BN statistics of both signs and a non-zero tail (and
    albedo/normal branches, model.aux_input), in eval mode."""
    torch.manual_seed(seed)
    model = build_model(config)
    randomize_batchnorm(model, 0.3, (0.3, 2.0), bias=0.3, positive=positive)
    with torch.no_grad():
        torch.nn.init.normal_(model.tail.weight, std=0.05)
        torch.nn.init.normal_(model.skip.weight, std=0.05)
        if model.head is not None:
            torch.nn.init.normal_(model.head[2].weight, std=0.05)
            torch.nn.init.uniform_(model.head[0].bias, -0.2, 0.2)
            torch.nn.init.uniform_(model.head[2].bias, -0.02, 0.02)
        if model.kernel is not None:
            torch.nn.init.normal_(model.kernel.weight, std=0.05)
            torch.nn.init.uniform_(model.kernel.bias, -0.05, 0.05)
        for conv in [*(model.aux_levels.convs if model.aux_levels is not None else ()),
                     *((model.aux_kernel.out,) if model.aux_kernel is not None else ())]:
            torch.nn.init.normal_(conv.weight, std=0.05)
    return model.eval()


MULTISCALE_PRESETS = [name for name, cfg in PRESETS.items() if cfg.multiscale]


@pytest.mark.parametrize("name", MULTISCALE_PRESETS)
def test_every_multiscale_preset_keeps_the_shape(name: str) -> None:
    config = dataclasses.replace(PRESETS[name], noise_input=True)
    model = build_model(config).eval()
    for h, w in ((1, 1), (33, 70)):
        x = torch.rand(1, config.image_channels, h, w)
        with torch.no_grad():
            assert model(x).shape == (1, 3, h, w)


@pytest.mark.parametrize("h,w", [(1, 1), (1, 9), (9, 1), (5, 7), (16, 16), (31, 17)])
@pytest.mark.parametrize("arch,head,kernel", [("dense_unet", 0, 0), ("plain_unet", 0, 0), ("dense_unet", 5, 0),
                                              ("dense_unet", 0, 3), ("plain_unet", 0, 5)])
def test_any_size_and_residual_identity_at_init(arch: str, head: int, kernel: int, h: int, w: int) -> None:
    config = dataclasses.replace(TINY, arch=arch, head=head, kernel=kernel)
    model = build_model(config).eval()
    x = torch.rand(2, 3, h, w)
    with torch.no_grad():
        assert torch.equal(model(x), x)  # zero-initialised correction: the untrained model is the identity
    if kernel:
        return  # the filter needs the residual output
    direct = build_model(dataclasses.replace(config, output="direct")).eval()
    with torch.no_grad():
        out = direct(x)
    assert out.shape == (2, 3, h, w) and torch.isfinite(out).all()


def test_padding_replicates_the_edges() -> None:
    x = torch.arange(6.0).view(1, 1, 2, 3)
    padded = pad_to_alignment(x, 4)
    assert padded.shape == (1, 1, 4, 4)
    assert torch.equal(padded[..., :2, :3], x)
    assert torch.equal(padded[0, 0, 3, :3], x[0, 0, 1]) and torch.equal(padded[0, 0, :2, 3], x[0, 0, :, 2])
    assert pad_to_alignment(x[..., :1, :1], 8).eq(0.0).all()  # 1x1 -> 8x8 of its value


@pytest.mark.parametrize("head,kernel", [(0, 0), (4, 0), (0, 5)])
def test_receptive_radius_bounds_the_influence_of_a_pixel(head: int, kernel: int) -> None:
    config = dataclasses.replace(TINY, layers=1, levels=2, head=head, kernel=kernel)
    model = trained_like(config)
    r = receptive_radius(config)
    size = 2 * r + 40
    base = torch.rand(1, 3, size, size)
    changed = base.clone()
    y, x = 20, 20  # aligned far from the borders of the output pixel examined below
    changed[0, :, y, x] += 5.0
    with torch.no_grad():
        diff = (model(changed) - model(base)).abs()[0].amax(dim=0)
    reach = torch.nonzero(diff > 0)
    dist = (reach - torch.tensor([y, x])).abs().amax(dim=1)
    assert int(dist.max()) <= r  # nothing beyond the bound moves
    assert int(dist.max()) >= r // 4  # and the bound is not wildly loose


@pytest.mark.parametrize("kernel", [0, 5])
def test_tiled_inference_on_the_alignment_grid_equals_whole_image(kernel: int) -> None:
    config = dataclasses.replace(TINY, noise_input=True, noise_radius=2, kernel=kernel)
    model = trained_like(config)
    rng = np.random.default_rng(3)
    h, w = 2 * receptive_radius(config) + 37, receptive_radius(config) + 51
    color = (rng.random((h, w, 3)) * 4).astype(np.float32)
    variance = (rng.random((h, w, 3)) * 0.1).astype(np.float32)
    whole = denoise_image(model, color, core=4096, variance=variance)
    tiled = denoise_image(model, color, core=alignment(config) * 6, variance=variance)
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-6)


def test_head_is_validated() -> None:
    with pytest.raises(ConfigError, match="head must be 0 for the flat"):
        ModelConfig(head=8)
    with pytest.raises(ConfigError, match="head must be an integer"):
        dataclasses.replace(TINY, head=-1)


def test_kernel_is_validated() -> None:
    for bad in (1, 2, 4, 17, -3, True):
        with pytest.raises(ConfigError, match="kernel must be 0 or an odd"):
            dataclasses.replace(TINY, kernel=bad)
    for other in ({"arch": "densenet", "levels": 0}, {"output": "direct"}, {"head": 4}):
        with pytest.raises(ConfigError, match="kernel needs a multi-scale arch"):
            dataclasses.replace(TINY, kernel=3, **other)


def window_sum(rgb: torch.Tensor, coefficients: torch.Tensor, size: int) -> torch.Tensor:
    """``(1 - sum_j a_j) x(p) + sum_j a_j x(p + o_j)`` over the size x size window, edges replicated,
    computed directly (autograd flows to the coefficients): what ``x + apply_kernel`` must give."""
    r = size // 2
    h, w = rgb.shape[-2:]
    padded = torch.nn.functional.pad(rgb, (r, r, r, r), mode="replicate")
    out = (1 - coefficients.sum(dim=1, keepdim=True)) * rgb
    for j, (dy, dx) in enumerate(kernel_offsets(size)):
        out = out + coefficients[:, j:j + 1] * padded[..., r + dy:r + dy + h, r + dx:r + dx + w]
    return out


def test_the_predicted_filter_is_a_per_pixel_filter_of_the_input_whose_weights_sum_to_one() -> None:
    torch.manual_seed(0)
    rgb = torch.rand(2, 3, 6, 7)
    offsets = kernel_offsets(3)
    assert len(offsets) == 8 and (0, 0) not in offsets
    # one coefficient of 1 on the right-hand neighbour: the output is the neighbour minus the pixel
    coefficients = torch.zeros(2, 8, 6, 7)
    coefficients[:, offsets.index((0, 1))] = 1.0
    right = torch.cat([rgb[..., 1:], rgb[..., -1:]], dim=-1)  # beyond the edge: the edge pixel
    torch.testing.assert_close(apply_kernel(rgb, coefficients, 3), right - rgb)
    # random coefficients: x + the filter = the normalised sum over the 3x3 window, computed directly
    coefficients = torch.randn(2, 8, 6, 7)
    want = window_sum(rgb, coefficients, 3)
    torch.testing.assert_close(rgb + apply_kernel(rgb, coefficients, 3), want, rtol=1e-5, atol=1e-5)
    # the in-place banded version adds the same, with channels_last coefficients and any band height
    for rows in (1, 4, 16):
        out = torch.ones(2, 3, 6, 7)
        add_kernel_(out, rgb, coefficients.contiguous(memory_format=torch.channels_last), 3, rows=rows)
        torch.testing.assert_close(out, 1 + apply_kernel(rgb, coefficients, 3), rtol=1e-5, atol=1e-5)
    # and from half-resolution coefficients in pixel_shuffle's order, larger than half the image (padded)
    half = torch.randn(2, 32, 4, 5).contiguous(memory_format=torch.channels_last)
    full = torch.nn.functional.pixel_shuffle(half, 2)[..., :6, :7]
    for rows in (1, 2, 3, 64):
        out = torch.zeros(2, 3, 6, 7)
        add_kernel_(out, rgb, half.to(torch.bfloat16), 3, rows=rows, scale=2)
        torch.testing.assert_close(out, apply_kernel(rgb, full.to(torch.bfloat16), 3), rtol=1e-5, atol=1e-5)
    # images narrower and lower than the filter: the banded edges repeat as apply_kernel's do
    for h, w in ((1, 1), (1, 5), (3, 1), (2, 2)):
        small, coef = rgb[..., :h, :w].contiguous(memory_format=torch.channels_last), torch.randn(2, 24, h, w)
        out = torch.zeros(2, 3, h, w)
        add_kernel_(out, small, coef, 5, rows=1)
        torch.testing.assert_close(out, apply_kernel(small, coef, 5), rtol=1e-5, atol=1e-5)
    # a constant image passes unchanged whatever the coefficients; a 1x1 image too
    flat = torch.full((1, 3, 4, 4), 0.7)
    assert apply_kernel(flat, torch.randn(1, 24, 4, 4), 5).abs().max() < 1e-6
    assert apply_kernel(rgb[..., :1, :1], torch.randn(2, 24, 1, 1), 5).abs().max() < 1e-6


@pytest.mark.parametrize("size", [3, 5])
def test_the_filters_hand_written_gradient_is_autograds_through_the_direct_sum(size: int) -> None:
    torch.manual_seed(1)
    rgb = torch.rand(2, 3, 7, 6)
    coefficients = torch.randn(2, size * size - 1, 7, 6, requires_grad=True)
    weight = torch.randn(2, 3, 7, 6)  # a loss that weighs every output differently
    (apply_kernel(rgb, coefficients, size) * weight).sum().backward()
    got, coefficients.grad = coefficients.grad, None
    ((window_sum(rgb, coefficients, size) - rgb) * weight).sum().backward()
    torch.testing.assert_close(got, coefficients.grad, rtol=1e-5, atol=1e-5)
    # bfloat16 coefficients (autocast) get a bfloat16 gradient; the input gets none
    half = coefficients.detach().to(torch.bfloat16).requires_grad_()
    apply_kernel(rgb, half, size).sum().backward()
    assert half.grad.dtype == torch.bfloat16
    with pytest.raises(ValueError, match="no gradient to rgb"):
        apply_kernel(rgb.requires_grad_(), coefficients, size)


def test_levels_are_validated() -> None:
    with pytest.raises(ConfigError, match="levels must be in"):
        ModelConfig(arch="dense_unet", levels=0)
    with pytest.raises(ConfigError, match="levels must be 0"):
        ModelConfig(arch="densenet", levels=2)
    with pytest.raises(ValueError, match="not a multi-scale"):
        MultiScaleDenoiser(ModelConfig())


def test_plain_unet_costs_about_as_much_as_the_dense_one() -> None:
    dense = conv_macs_per_pixel(build_model(TINY), 64, 64)
    plain = conv_macs_per_pixel(build_model(dataclasses.replace(TINY, arch="plain_unet")), 64, 64)
    assert plain == pytest.approx(dense, rel=0.1)


def test_nothing_heavy_runs_at_full_resolution() -> None:
    """Every convolution of the multi-scale net works at half resolution or below."""
    model = build_model(dataclasses.replace(TINY, levels=3)).eval()
    sizes = []
    hooks = [m.register_forward_hook(lambda m, i, o: sizes.append(o.shape[-1]))
             for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        model(torch.rand(1, 3, 64, 64))
    for h in hooks:
        h.remove()
    assert max(sizes) == 32 and min(sizes) == 4


def test_the_head_is_the_only_full_resolution_work() -> None:
    """With a head, exactly its two convolutions run at full resolution, on the RGB estimate
    and the network input."""
    config = dataclasses.replace(TINY, levels=3, head=6)
    model = build_model(config).eval()
    full = []
    hooks = [m.register_forward_hook(lambda m, i, o: full.append((i[0].shape[1], o.shape[1])) if o.shape[-1] == 64
                                     else None)
             for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        model(torch.rand(1, 3, 64, 64))
    for h in hooks:
        h.remove()
    assert full == [(3 + config.in_channels, 6), (6, 3)]


@pytest.mark.parametrize("arch,head,kernel", [("dense_unet", 0, 0), ("plain_unet", 0, 0), ("dense_unet", 7, 0),
                                              ("dense_unet", 0, 5), ("plain_unet", 0, 3)])
def test_macs_counted_from_the_plan_match_the_convolutions_run(arch: str, head: int, kernel: int) -> None:
    from model.unet import macs_per_pixel

    config = dataclasses.replace(TINY, arch=arch, levels=3, layers=2, noise_input=True, head=head, kernel=kernel)
    measured = conv_macs_per_pixel(build_model(config), 64, 64)
    assert macs_per_pixel(config, pool_first=False) == pytest.approx(measured, rel=1e-9)
    assert macs_per_pixel(config) < measured  # the folded net pools before the transition's conv
