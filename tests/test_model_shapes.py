"""What a model config implies, without building it: the state dict on the meta device equals the
built network's, and the cheap lower bounds are lower bounds."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from imaging import memory_limit
from imaging.errors import ConfigError
from model.architectures import build_model, count_parameters
from model.config import PRESETS, ModelConfig
from model.shapes import check_fits_in_memory, expected_state, min_parameters, min_state_entries

CONFIGS = [*PRESETS.values(),
           ModelConfig(arch="plaincnn", layers=4, growth=6, init_features=8),
           ModelConfig(arch="plain_unet", levels=2, layers=2, growth=4, init_features=8, head=8),
           ModelConfig(arch="dense_unet", levels=3, layers=1, growth=5, init_features=7, kernel=5, noise_input=True),
           ModelConfig(layers=3, growth=4, init_features=8, aux_inputs=True, bottleneck=2)]


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: f"{c.arch}-{c.layers}-{c.growth}-{c.levels}")
def test_meta_state_is_the_built_state_and_bounds_hold(config: ModelConfig) -> None:
    rng = torch.get_rng_state()
    expected = expected_state(config)
    assert torch.equal(rng, torch.get_rng_state())  # building on the meta device draws nothing
    model = build_model(config)
    assert expected.shapes == {k: (tuple(v.shape), v.dtype) for k, v in model.state_dict().items()}
    assert expected.parameters == tuple(name for name, _ in model.named_parameters())
    assert min_state_entries(config) <= len(expected.shapes)
    assert min_parameters(config) <= count_parameters(model)


def test_absurd_sizes_are_bounded_before_anything_is_built() -> None:
    """growth 4096 on the flat-s preset: the bound alone says 6e9 parameters (counted, not built)."""
    huge = dataclasses.replace(PRESETS["flat-s"], growth=4096)
    assert min_parameters(huge) == 10 * 9 * 4 * 4096 * 4096
    deep = ModelConfig(arch="dense_unet", levels=6, layers=4096, growth=8, init_features=8)
    assert min_state_entries(deep) == 12 * 4096 * 13


def test_training_refuses_what_cannot_fit(monkeypatch: pytest.MonkeyPatch) -> None:
    check_fits_in_memory(PRESETS["flat-s"])
    monkeypatch.setattr(memory_limit, "available_bytes", lambda: 10 * 2**30)
    with pytest.raises(ConfigError, match=r"the model config implies at least 6,039,797,760 parameters "
                                          r"\(92,160 MB to train\), more than the 10,240 MB of memory available"):
        check_fits_in_memory(dataclasses.replace(PRESETS["flat-s"], growth=4096))
