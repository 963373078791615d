"""The tensors a :class:`ModelConfig`'s network holds, known without allocating them.

A checkpoint's header says which network to build; its tensors must be what that network holds.
:func:`expected_state` builds the network on torch's ``meta`` device (shapes and dtypes, no
memory) and lists its state dict and parameter order. Building is itself slow for absurd sizes
(thousands of layers), so two cheap lower bounds come first: :func:`min_state_entries` (every
bottleneck layer holds two BatchNorms of five entries and two conv weights) and
:func:`min_parameters` (every bottleneck layer's 3x3 conv holds ``9 * bottleneck * growth`` weights
per output channel: at least ``growth`` output channels in a dense block, at least one in a plain
one). A file with fewer tensors, or fewer bytes, than those bounds cannot hold the network.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from unittest import mock

import torch
from torch import nn

from imaging.errors import ConfigError
from imaging.memory_limit import fits_in_memory, megabytes
from model.architectures import build_model
from model.config import ModelConfig

TRAINING_BYTES_PER_PARAMETER = 16  # float32 weight, gradient and Adam's two moments
ENTRIES_PER_LAYER = 12  # BN (weight, bias, running mean and var, batches tracked) x 2 + 2 conv weights


@dataclass(frozen=True)
class ExpectedState:
    """``shapes``: state-dict name -> (shape, dtype); ``parameters``: the parameters' names in the
    order ``model.parameters()`` (and so the optimiser's state) takes them."""

    shapes: dict[str, tuple[tuple[int, ...], torch.dtype]]
    parameters: tuple[str, ...]


def bottleneck_layers(config: ModelConfig) -> int:
    """Bottleneck layers of the network: ``layers`` in each of its blocks (one flat block, or the
    2 * levels + 1 blocks of a multi-scale net)."""
    return config.layers * (2 * config.levels + 1 if config.multiscale else 1)


def min_state_entries(config: ModelConfig) -> int:
    """A lower bound on the network's state-dict entries."""
    return ENTRIES_PER_LAYER * bottleneck_layers(config)


def min_parameters(config: ModelConfig) -> int:
    """A lower bound on the network's parameters (module notes)."""
    dense = config.arch in ("densenet", "dense_unet")
    per_output = 9 * config.bottleneck * config.growth
    return bottleneck_layers(config) * per_output * (config.growth if dense else 1)


def check_fits_in_memory(config: ModelConfig, bytes_per_parameter: int = TRAINING_BYTES_PER_PARAMETER) -> None:
    """Raise :class:`ConfigError` naming both sizes when :func:`min_parameters` of ``config``, at
    ``bytes_per_parameter``, exceed the memory left (:mod:`imaging.memory_limit`): a config of
    absurd sizes is refused before anything is allocated."""
    need = min_parameters(config) * bytes_per_parameter
    fits, room = fits_in_memory(need)
    if not fits:
        raise ConfigError(f"the model config implies at least {min_parameters(config):,} parameters "
                          f"({megabytes(need)} to train), more than the {megabytes(room)} of memory available")


@contextlib.contextmanager
def _no_random_init() -> Iterator[None]:
    """He init draws from a normal distribution, which on the meta device imports torch's compiler
    (seconds); the shapes do not depend on it."""
    with mock.patch.object(nn.init, "kaiming_normal_", lambda tensor, *a, **k: tensor):
        yield


def expected_state(config: ModelConfig) -> ExpectedState:
    """The state dict and parameter order of ``config``'s network, built on the meta device."""
    with torch.device("meta"), _no_random_init():
        model = build_model(config)
    shapes = {name: (tuple(value.shape), value.dtype) for name, value in model.state_dict().items()}
    return ExpectedState(shapes, tuple(name for name, _ in model.named_parameters()))
