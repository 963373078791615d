"""Where the networks run: the one place that turns ``--device auto|cpu|cuda`` into a torch device.

``auto`` is CUDA when torch sees a CUDA device, else the CPU. Everything else in the code asks a
module or a tensor where it lives (:func:`module_device`) instead of naming a device, so a run
chooses once and the rest follows.
"""
from __future__ import annotations

import torch
from torch import nn

from imaging.errors import ConfigError

DEVICES = ("auto", "cpu", "cuda")


def cuda_available() -> bool:
    """True when torch can use a CUDA device here (a CUDA build and a visible GPU)."""
    return bool(torch.cuda.is_available())


def check_device_name(name: object) -> str:
    """``name`` if it is a device this module knows (``auto``, ``cpu``, ``cuda``, ``cuda:N``), whether
    or not this machine has it; else :class:`ConfigError` listing them."""
    if isinstance(name, str):
        kind, _, index = name.partition(":")
        if name in DEVICES or (kind == "cuda" and index.isdigit()):
            return name
    raise ConfigError(f"device must be one of {', '.join(DEVICES)} (or cuda:N), got {name!r}")


def choose_device(name: str = "auto") -> torch.device:
    """The torch device for ``--device NAME``: ``auto`` (CUDA when present, else CPU), ``cpu`` or
    ``cuda`` (``cuda:N`` for the N-th GPU). Raises :class:`ConfigError` for another name or for
    ``cuda`` where torch sees no CUDA device."""
    _, _, index = check_device_name(name).partition(":")
    if name == "auto":
        return torch.device("cuda") if cuda_available() else torch.device("cpu")
    if name == "cpu":
        return torch.device("cpu")
    if not cuda_available():
        raise ConfigError(f"device {name!r}: torch sees no CUDA device here (torch {torch.__version__}; "
                          "use --device cpu or auto)")
    if index and int(index) >= torch.cuda.device_count():
        raise ConfigError(f"device {name!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    return torch.device(name)


def module_device(module: nn.Module) -> torch.device:
    """The device of ``module``'s first parameter or buffer (the CPU for a module with neither)."""
    for tensor in module.parameters():
        return tensor.device
    for tensor in module.buffers():
        return tensor.device
    return torch.device("cpu")


def device_name(device: torch.device) -> str:
    """What the hardware is called: the GPU's name for a CUDA device, "cpu" otherwise."""
    if device.type == "cuda":
        return str(torch.cuda.get_device_name(device))
    return "cpu"
