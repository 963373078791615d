"""Typed model configuration and the named presets.

A :class:`ModelConfig` fully describes a network: it is saved in every checkpoint and the model is
rebuilt from it alone. Presets (parameter counts for ``aux_inputs=False``, checked by
``tests/test_model_config.py``), all with the PU transfer and residual output that measured best
(README, "Choices, measured"):

* ``fast``     — k=8,  L=10, first conv 16 wide:  51,232 parameters (plaincnn: width 14, 52,328)
* ``balanced`` — k=8,  L=20, first conv 16 wide: 122,112 parameters (plaincnn: width 17, 118,784)
* ``high``     — k=8,  L=30, first conv 16 wide: 220,192 parameters (plaincnn: width 22, 224,824)
* ``paper``    — k=12, L=20, first conv 24 wide: 261,888 parameters (plaincnn: width 26, 264,832)

``fast``, ``balanced`` and ``high`` share growth rate and width, so each is a prefix of the next:
the deeper ones are trained warm-started from the shallower (:mod:`model.grow`), which is what
the 2-core CPU affords. ``paper`` is Kim & Lee's network (one dense block of L=20 bottleneck
layers; k=12 is our choice, the paper gives none) and the default of ``train``. With
``aux_inputs`` the first conv takes 15 instead of 9 channels (+4,704 parameters, +7,056 for
``paper``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from model.errors import ConfigError

ARCHS = ("densenet", "plaincnn")
OUTPUTS = ("residual", "direct")
TRANSFERS = ("log", "pu")


@dataclass(frozen=True)
class ModelConfig:
    """Architecture, transfer function and output mode of a denoiser.

    ``layers``: bottleneck layers L in the dense block; ``growth``: growth rate k (channels each
    layer adds); ``init_features``: width of the first 7x7 conv; ``bottleneck``: the 1x1 conv
    widens to ``bottleneck * growth`` channels (4 in the paper). ``transfer``: curve applied to
    linear radiance before the network (see :mod:`model.transfer`). ``output``: ``"residual"``
    predicts a correction added to the transfer-space input, ``"direct"`` the clean image itself.
    ``aux_inputs``: also feed albedo (RGB, [0,1]) and normal (XYZ, [-1,1]) -> 15 input channels.
    Defaults: the paper's sizes, log transfer, residual output (the network predicts only the
    correction, which starts near the identity).
    """

    arch: str = "densenet"
    layers: int = 20
    growth: int = 12
    init_features: int = 24
    bottleneck: int = 4
    transfer: str = "log"
    output: str = "residual"
    aux_inputs: bool = False

    def __post_init__(self) -> None:
        if self.arch not in ARCHS:
            raise ConfigError(f"unknown arch {self.arch!r} (known: {', '.join(ARCHS)})")
        if self.output not in OUTPUTS:
            raise ConfigError(f"unknown output mode {self.output!r} (known: {', '.join(OUTPUTS)})")
        if self.transfer not in TRANSFERS:
            raise ConfigError(f"unknown transfer {self.transfer!r} (known: {', '.join(TRANSFERS)})")
        for name in ("layers", "growth", "init_features", "bottleneck"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= 4096:
                raise ConfigError(f"model {name} must be an integer in 1..4096, got {value!r}")
        if not isinstance(self.aux_inputs, bool):
            raise ConfigError(f"model aux_inputs must be true or false, got {self.aux_inputs!r}")

    @property
    def in_channels(self) -> int:
        """Network input channels: RGB + 6 gradient channels (+ albedo + normal)."""
        return 15 if self.aux_inputs else 9

    @property
    def image_channels(self) -> int:
        """Channels of the image tensor the model takes: RGB (+ albedo + normal) = 3 or 9."""
        return 9 if self.aux_inputs else 3

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict of all fields."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ModelConfig:
        """Inverse of :meth:`to_dict`; raises :class:`ConfigError` on unknown or missing keys."""
        if not isinstance(data, dict):
            raise ConfigError(f"model config must be a JSON object, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"unknown model config key(s): {', '.join(unknown)}")
        return cls(**data)


PRESETS: dict[str, ModelConfig] = {
    "fast": ModelConfig(layers=10, growth=8, init_features=16, transfer="pu"),
    "balanced": ModelConfig(layers=20, growth=8, init_features=16, transfer="pu"),
    "high": ModelConfig(layers=30, growth=8, init_features=16, transfer="pu"),
    "paper": ModelConfig(layers=20, growth=12, init_features=24, transfer="pu"),
}


def preset(name: str, **overrides: Any) -> ModelConfig:
    """The named preset, with optional field overrides (e.g. ``arch="plaincnn"``)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown model preset {name!r} (known: {', '.join(PRESETS)})")
    return dataclasses.replace(PRESETS[name], **overrides)
