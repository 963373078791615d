"""The one place a device is chosen: --device auto|cpu|cuda, on a machine with or without CUDA."""
from __future__ import annotations

import pytest
import torch

import model.device
from imaging.errors import ConfigError
from model.device import check_device_name, choose_device, module_device


def test_auto_is_cuda_only_where_there_is_one(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(model.device, "cuda_available", lambda: False)
    assert choose_device("auto") == torch.device("cpu") == choose_device("cpu")
    monkeypatch.setattr(model.device, "cuda_available", lambda: True)
    assert choose_device("auto").type == "cuda"
    assert choose_device("cpu") == torch.device("cpu")


def test_cuda_without_one_is_a_one_line_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(model.device, "cuda_available", lambda: False)
    with pytest.raises(ConfigError, match="device 'cuda': torch sees no CUDA device here"):
        choose_device("cuda")


@pytest.mark.parametrize("name", ["tpu", "cuda:x", "", 3, "CPU"])
def test_unknown_device_lists_the_valid_ones(name: object) -> None:
    with pytest.raises(ConfigError, match=r"device must be one of auto, cpu, cuda \(or cuda:N\)"):
        check_device_name(name)


def test_a_module_is_where_its_weights_are() -> None:
    assert module_device(torch.nn.Conv2d(1, 1, 1)) == torch.device("cpu")
    assert module_device(torch.nn.ReLU()) == torch.device("cpu")  # nothing to ask: the CPU
