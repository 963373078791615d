"""ModelConfig and presets: validation, JSON round trip, parameter counts."""
from __future__ import annotations

import pytest

from imaging.errors import ConfigError
from model.architectures import build_model, count_parameters
from model.config import PRESETS, ModelConfig, preset
from model.network import densenet_params

# Documented in model/config.py; changing an architecture detail must update both.
EXPECTED_PARAMS = {"flat-s": 51_232, "flat-m": 122_112, "flat-l": 220_192, "paper": 261_888}


def test_presets_exist_and_grow() -> None:
    assert {"flat-s", "flat-m", "flat-l"} <= set(PRESETS)
    counts = [densenet_params(PRESETS[n]) for n in ("flat-s", "flat-m", "flat-l")]
    assert counts == sorted(counts)


@pytest.mark.parametrize("name", sorted(EXPECTED_PARAMS))
def test_preset_parameter_counts(name: str) -> None:
    model = build_model(PRESETS[name])
    assert count_parameters(model) == EXPECTED_PARAMS[name] == densenet_params(PRESETS[name])


@pytest.mark.parametrize("name", sorted(n for n in PRESETS if not PRESETS[n].multiscale))
@pytest.mark.parametrize("aux", [False, True])
def test_plaincnn_matches_densenet_within_5_percent(name: str, aux: bool) -> None:
    dense = count_parameters(build_model(preset(name, aux_inputs=aux)))
    plain = count_parameters(build_model(preset(name, arch="plaincnn", aux_inputs=aux)))
    assert abs(plain - dense) / dense <= 0.05


def test_round_trip_dict() -> None:
    config = preset("flat-s", arch="plaincnn", transfer="pu", output="direct", aux_inputs=True)
    assert ModelConfig.from_dict(config.to_dict()) == config


@pytest.mark.parametrize("changes, message", [
    ({"arch": "unet"}, "unknown arch 'unet'"),
    ({"noise_input": 1}, "noise_input must be true or false"),
    ({"output": "kernel"}, "unknown output mode 'kernel'"),
    ({"transfer": "srgb"}, "unknown transfer 'srgb'"),
    ({"layers": 0}, "model layers must be an integer in 1..4096"),
    ({"growth": 2.5}, "model growth must be an integer"),
    ({"aux_inputs": "yes"}, "aux_inputs must be true or false"),
])
def test_invalid_values(changes: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ModelConfig(**changes)


def test_unknown_key_and_preset() -> None:
    with pytest.raises(ConfigError, match="unknown model config key"):
        ModelConfig.from_dict({"layers": 3, "depth": 4})
    with pytest.raises(ConfigError, match="unknown model preset 'huge'"):
        preset("huge")


def test_input_channels() -> None:
    assert ModelConfig().in_channels == 9 and ModelConfig().image_channels == 3
    assert ModelConfig(aux_inputs=True).in_channels == 15 and ModelConfig(aux_inputs=True).image_channels == 9
