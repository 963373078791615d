"""Where albedo and normal enter a multi-scale net (model.aux_input, ``ModelConfig.aux_mode``): the
arms' shapes and sizes, the warm start from an RGB net that computes it exactly, the checkpoint
round trip, the prefilter. Tolerances: exact (0) for the warm start and the round trip; the
folded copy within test_inference_unet's."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from denoise.chain import denoise_image
from imaging.errors import ConfigError
from model.architectures import build_model, count_parameters, receptive_radius
from model.aux_input import KERNEL_HIDDEN, PREFILTER_RADIUS, prefilter
from model.checkpoint import load_model, model_from_checkpoint, read_checkpoint, save_checkpoint
from model.config import AUX_MODES, ModelConfig
from model.grow import add_aux, grow_model
from model.unet import conv_macs_per_pixel, macs_per_pixel
from tests.test_model_unet import TINY, trained_like

SHIPPED = Path(__file__).resolve().parents[1] / "model" / "weights" / "unet-m-k5-lowspp.ckpt"
RGB_PARAMETERS = 702_484  # unet-m with the 5x5 filter, RGB only
# per arm: stem w0 = 32 and skip 12 channels on 24 more unshuffled input channels (3x3), or the branches
ARM_PARAMETERS = {
    "stem": RGB_PARAMETERS + 9 * 24 * (32 + 12),  # 711,988
    "noskip": RGB_PARAMETERS + 9 * 24 * 32,  # 709,396
    "levels": RGB_PARAMETERS + 9 * 24 * 32 + 9 * 6 * (48 + 64 + 80 + 96),  # 724,948
    "kernel": RGB_PARAMETERS + (112 + 1) * KERNEL_HIDDEN + 9 * 24 * KERNEL_HIDDEN + (KERNEL_HIDDEN + 1) * 96,
}


def _arm(base: ModelConfig, mode: str, **extra: object) -> ModelConfig:
    return dataclasses.replace(base, aux_inputs=True, aux_mode=mode, **extra)


@pytest.fixture(scope="module")
def shipped() -> torch.nn.Module:
    return model_from_checkpoint(read_checkpoint(SHIPPED)).eval()


def test_an_old_checkpoint_describes_itself_with_the_defaults(shipped: torch.nn.Module) -> None:
    header = read_checkpoint(SHIPPED).header["model_config"]
    assert "aux_mode" not in header  # written before the field existed
    config = shipped.config
    assert (config.aux_mode, config.aux_normals, config.aux_prefilter) == ("stem", "world", "none")
    assert count_parameters(shipped) == RGB_PARAMETERS


@pytest.mark.parametrize("mode", AUX_MODES)
def test_each_arm_s_inputs_and_parameters(shipped: torch.nn.Module, mode: str) -> None:
    config = _arm(shipped.config, mode)
    model = build_model(config)
    assert count_parameters(model) == ARM_PARAMETERS[mode]
    assert model.stem[0].in_channels == 4 * (15 if mode in ("stem", "noskip") else 9)
    assert model.skip.in_channels == 4 * (15 if mode == "stem" else 9)
    assert (model.aux_levels is not None, model.aux_kernel is not None) == (mode == "levels", mode == "kernel")
    x = torch.rand(2, 9, 19, 33)
    with torch.no_grad():
        assert model.eval()(x).shape == (2, 3, 19, 33)


@pytest.mark.parametrize("mode", AUX_MODES)
@pytest.mark.parametrize("options", [{}, {"aux_prefilter": "bilateral", "aux_normals": "camera"}],
                         ids=["noisy", "prefiltered-camera"])
def test_every_arm_warm_started_from_the_shipped_rgb_net_computes_it_exactly(
        shipped: torch.nn.Module, mode: str, options: dict) -> None:
    """At step 0 the net with buffers is the RGB net, bit for bit, whatever the buffers hold; and
    the weights that read them get a gradient from the first step."""
    torch.manual_seed(3)
    target = build_model(_arm(shipped.config, mode, **options))
    grow_model(target, shipped)
    x = torch.rand(2, 9, 16, 24)
    x[:, 6:9] = x[:, 6:9] * 2 - 1
    with torch.no_grad():
        assert torch.equal(target.eval()(x), shipped(x[:, :3]))
    target.train()(x).square().mean().backward()
    reading = {"stem": target.stem[0].weight.grad[:, 36:60], "noskip": target.stem[0].weight.grad[:, 36:60],
               "levels": target.aux_levels.convs[0].weight.grad if target.aux_levels else None,
               "kernel": target.aux_kernel.out.weight.grad if target.aux_kernel else None}[mode]
    assert reading.abs().sum() > 0


@pytest.mark.parametrize("mode", AUX_MODES)
def test_a_warm_start_with_noise_channels_keeps_them_in_place(mode: str) -> None:
    """The buffers sit between the gradients and the noise channels: the RGB net's noise weights
    must land on the noise channels of the wider input."""
    rgb = dataclasses.replace(TINY, noise_input=True, kernel=3)
    source = trained_like(rgb, seed=4)
    target = build_model(_arm(rgb, mode))
    grow_model(target, source)
    x = torch.rand(1, target.config.image_channels, 16, 20)
    with torch.no_grad():
        assert torch.equal(target.eval()(x), source(torch.cat([x[:, :3], x[:, 9:]], dim=1)))


def test_a_fresh_stem_arm_reads_the_buffers_and_add_aux_refuses_other_nets() -> None:
    """The test above can fail: without the warm start the buffers change the output."""
    config = _arm(dataclasses.replace(TINY, kernel=3), "stem")
    model = trained_like(config)
    x = torch.rand(1, 9, 16, 16)
    y = x.clone()
    y[:, 3:] = 1 - y[:, 3:]
    with torch.no_grad():
        assert not torch.equal(model(x), model(y))
    with pytest.raises(ConfigError, match="not the source with them"):
        add_aux(model, trained_like(dataclasses.replace(TINY, kernel=5)))


def test_the_kernel_arm_s_buffers_move_only_the_filter() -> None:
    """In ``kernel`` mode the buffers reach only the filter's weights, and a filter of a constant
    image is zero: for a constant RGB the output does not depend on them (within 1e-5: the filter
    sums its terms before it subtracts the centre's), where in ``levels`` mode it does."""
    outputs = {}
    for mode in ("kernel", "levels"):
        model = build_model(_arm(dataclasses.replace(TINY, kernel=3), mode))
        with torch.no_grad():
            for p in model.parameters():
                p.add_(0.1 * torch.randn_like(p))
        model.eval()
        x = torch.full((1, 9, 16, 16), 0.4)
        x[:, 3:] = torch.rand(1, 6, 16, 16)
        y = x.clone()
        y[:, 3:] = torch.rand(1, 6, 16, 16)
        with torch.no_grad():
            outputs[mode] = (model(x) - model(y)).abs().max().item()
    assert outputs["kernel"] < 1e-5 and outputs["levels"] > 1e-3


@pytest.mark.parametrize("mode", AUX_MODES)
def test_checkpoint_round_trip_rebuilds_each_arm_from_the_file(tmp_path: Path, mode: str) -> None:
    config = _arm(dataclasses.replace(TINY, kernel=3), mode, aux_normals="camera", aux_prefilter="bilateral")
    model = trained_like(config, seed=1)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01)
    save_checkpoint(tmp_path / "m.ckpt", model, step=3)
    loaded, loaded_config, _ = load_model(tmp_path / "m.ckpt")
    assert loaded_config == config
    x = torch.rand(1, 9, 21, 17)
    with torch.no_grad():
        assert torch.equal(loaded.eval()(x), model(x))


@pytest.mark.parametrize("change, message", [
    ({"aux_mode": "levels"}, "needs aux_inputs"),
    ({"aux_normals": "camera"}, "needs aux_inputs"),
    ({"aux_inputs": True, "aux_mode": "skip"}, "unknown model aux_mode 'skip'"),
    ({"aux_inputs": True, "aux_prefilter": "box"}, "unknown model aux_prefilter"),
    ({"aux_inputs": True, "aux_mode": "kernel"}, "needs a predicted filter"),
    ({"aux_inputs": True, "aux_mode": "levels", "head": 4}, "needs no head"),
    ({"aux_inputs": True, "arch": "densenet", "levels": 0, "aux_mode": "noskip"}, "needs a multi-scale arch"),
    ({"aux_inputs": True, "arch": "densenet", "levels": 0, "aux_prefilter": "bilateral"}, "multi-scale"),
])
def test_inconsistent_aux_options_are_refused(change: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        dataclasses.replace(TINY, **change)


@pytest.mark.parametrize("mode", ["levels", "kernel"])
def test_macs_count_the_branches(mode: str) -> None:
    config = _arm(dataclasses.replace(TINY, levels=3, kernel=3), mode)
    assert macs_per_pixel(config, pool_first=False) == pytest.approx(conv_macs_per_pixel(build_model(config)),
                                                                     rel=1e-9)
    assert macs_per_pixel(config) > macs_per_pixel(dataclasses.replace(config, aux_inputs=False, aux_mode="stem"))


@pytest.mark.parametrize("mode", AUX_MODES)
def test_tiles_reproduce_the_whole_image_with_the_prefilter(mode: str) -> None:
    """The prefilter widens the reach (receptive_radius): tiles cut with it stay exact."""
    config = _arm(dataclasses.replace(TINY, kernel=3), mode, aux_prefilter="bilateral")
    assert receptive_radius(config) == receptive_radius(dataclasses.replace(config, aux_prefilter="none")) \
        + PREFILTER_RADIUS
    model = trained_like(config, seed=2)
    rng = np.random.default_rng(5)
    color = rng.random((37, 45, 3), dtype=np.float32) * 2
    aux = np.concatenate([rng.random((37, 45, 3), dtype=np.float32),
                          rng.random((37, 45, 3), dtype=np.float32) * 2 - 1], axis=2)
    whole = denoise_image(model, color, aux, core=64)
    np.testing.assert_allclose(denoise_image(model, color, aux, core=16), whole, rtol=1e-5, atol=1e-5)


def test_prefilter_keeps_constant_buffers_exactly() -> None:
    aux = torch.tensor([0.3, 0.5, 0.7, 0.0, 0.6, -0.8]).view(1, 6, 1, 1).expand(2, 6, 9, 13).contiguous()
    assert torch.equal(prefilter(aux), aux)


def test_prefilter_keeps_an_edge_and_smooths_noise_beside_it(rng: np.random.Generator) -> None:
    """Two materials (albedo 0.2 | 0.8, normals facing +z | +x): a clean step comes back as it is
    (within 1e-6: a neighbour across it weighs e^-54); with noise of std 0.02 on both buffers the
    error drops by more than half and each side keeps its mean (within 0.01)."""
    h, w = 32, 32
    clean = np.zeros((1, 6, h, w), np.float32)
    clean[:, :3, :, :16], clean[:, :3, :, 16:] = 0.2, 0.8
    clean[:, 5, :, :16], clean[:, 3, :, 16:] = 1.0, 1.0
    np.testing.assert_allclose(prefilter(torch.from_numpy(clean)).numpy(), clean, rtol=0, atol=1e-6)
    noisy = clean + rng.normal(0, 0.02, clean.shape).astype(np.float32)
    out = prefilter(torch.from_numpy(noisy)).numpy()
    assert np.std(out - clean) < 0.5 * np.std(noisy - clean)
    for side in (slice(0, 16), slice(16, 32)):
        np.testing.assert_allclose(out[..., side].mean(axis=(0, 2, 3)), clean[..., side].mean(axis=(0, 2, 3)),
                                   atol=0.01)
