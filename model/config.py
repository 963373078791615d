"""Typed model configuration and the named architecture presets.

A :class:`ModelConfig` fully describes a network: it is saved in every checkpoint and the model is
rebuilt from it alone. Presets name architectures (``train --preset``), never shipped models: the
models a user picks by name (``fast``, ``balanced``, ``high``) live in the registry, and a preset
name never means a checkpoint. Parameter counts for ``aux_inputs=False``, checked by
``tests/test_model_config.py``; all with the PU transfer and residual output that measured best
(docs/experiments.md):

* ``flat-s``  — flat densenet, k=8,  L=10, first conv 16 wide:  51,232 parameters (plaincnn: width 14, 52,328)
* ``flat-m``  — flat densenet, k=8,  L=20, first conv 16 wide: 122,112 parameters (plaincnn: width 17, 118,784)
* ``flat-l``  — flat densenet, k=8,  L=30, first conv 16 wide: 220,192 parameters (plaincnn: width 22, 224,824)
* ``paper``   — flat densenet, k=12, L=20, first conv 24 wide: 261,888 parameters (plaincnn: width 26, 264,832)
* ``unet-s``, ``unet-m``, ``unet-l`` — the multi-scale dense U-Net (:mod:`model.unet`), five
  resolutions, growing in width and depth (docs/design.md)

``flat-s``, ``flat-m`` and ``flat-l`` share growth rate and width, so each is a prefix of the next:
the deeper ones can be warm-started from the shallower (:mod:`model.grow`). ``paper`` is Kim &
Lee's network (one dense block of L=20 bottleneck layers; k=12 is our choice, the paper gives
none). With ``aux_inputs`` the first conv takes 15 instead of 9 channels (+4,704 parameters,
+7,056 for ``paper``). The network ``train`` builds when no preset is named is
``unet-m`` with the predicted 5x5 filter (:data:`DEFAULT_TRAIN_MODEL`), the registry's
``unet-m-k5-lowspp``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from imaging.errors import ConfigError

ARCHS = ("densenet", "plaincnn", "dense_unet", "plain_unet")
FLAT_ARCHS = ("densenet", "plaincnn")
UNET_ARCHS = ("dense_unet", "plain_unet")
MAX_LEVELS = 6
MAX_KERNEL = 15  # the predicted filter of the multi-scale archs (ModelConfig.kernel)
NOISE_CHANNELS = 4  # transfer-space noise std per RGB channel + "the noise is known" flag
AUX_CHANNELS = 6  # albedo RGB + normal XYZ, channels 3:9 of the image tensor
# where a multi-scale net's albedo/normal reach it (model.aux_input): the stem and the input skip
# ("stem"), the stem only ("noskip"), every encoder level's input ("levels"), or only the predicted
# filter's coefficients ("kernel")
AUX_MODES = ("stem", "noskip", "levels", "kernel")
AUX_NORMALS = ("world", "camera")  # the frame the normals are given in (model.aux_input)
AUX_PREFILTERS = ("none", "bilateral")  # what the network does to the buffers first (model.aux_input)
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
    ``noise_input``: also feed what a render made of two halves tells about its noise
    (:mod:`model.noise_input`: per RGB channel how far one standard deviation of the mean moves the
    pixel in transfer space, and a flag that is 1 where the variance is known) -> 4 more channels;
    ``noise_radius``: the variance is first averaged over a (2r+1)^2 window (a two-halves estimate
    has one degree of freedom per pixel; the window gives the network a local noise level).
    ``levels``: for the multi-scale archs (``dense_unet``, ``plain_unet``, :mod:`model.unet`) the
    number of resolutions below the half-resolution stem (the image is processed at 1/2 .. 1/2^(levels+1));
    0 for the flat archs. For the multi-scale archs ``layers`` counts the layers of each of the
    2*levels+1 blocks, ``init_features`` is the stem's width and ``growth`` the growth rate at
    half resolution (:mod:`model.unet` says how widths grow with depth). ``head``: multi-scale
    archs only, channels of a full-resolution refinement head after the encoder/decoder (two 3x3
    convs on its output and the network input, :mod:`model.unet`); 0 for none. ``kernel``: multi-scale
    archs with residual output only, the odd size k of a per-pixel filter the network predicts and
    applies to the input RGB at full resolution (:func:`model.unet.apply_kernel`); 0 for none.
    ``aux_mode``, ``aux_normals``, ``aux_prefilter`` (with ``aux_inputs`` only; :mod:`model.aux_input`):
    where a multi-scale net's albedo and normal reach it (``stem``: the stem and the input skip;
    ``noskip``: the stem only; ``levels``: every encoder level's input, not the stem; ``kernel``:
    only the predicted filter's coefficients), the frame of the normals it is given (``world`` as
    Mitsuba renders them, or ``camera``: the sensor's frame, :mod:`rendering.camera`) and a fixed
    filter it applies to both buffers first (``none`` or ``bilateral``). Defaults: the paper's
    sizes, log transfer, residual output (the network predicts only the correction, which starts
    near the identity).
    """

    arch: str = "densenet"
    layers: int = 20
    growth: int = 12
    init_features: int = 24
    bottleneck: int = 4
    transfer: str = "log"
    output: str = "residual"
    aux_inputs: bool = False
    levels: int = 0
    noise_input: bool = False
    noise_radius: int = 0
    head: int = 0
    kernel: int = 0
    aux_mode: str = "stem"
    aux_normals: str = "world"
    aux_prefilter: str = "none"

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
        for name in ("aux_inputs", "noise_input"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"model {name} must be true or false, got {getattr(self, name)!r}")
        if not isinstance(self.noise_radius, int) or isinstance(self.noise_radius, bool) \
                or not 0 <= self.noise_radius <= 8:
            raise ConfigError(f"model noise_radius must be an integer in 0..8, got {self.noise_radius!r}")
        if not isinstance(self.levels, int) or isinstance(self.levels, bool):
            raise ConfigError(f"model levels must be an integer, got {self.levels!r}")
        if self.arch in UNET_ARCHS and not 1 <= self.levels <= MAX_LEVELS:
            raise ConfigError(f"model levels must be in 1..{MAX_LEVELS} for {self.arch}, got {self.levels}")
        if self.arch in FLAT_ARCHS and self.levels != 0:
            raise ConfigError(f"model levels must be 0 for the flat {self.arch}, got {self.levels}")
        if not isinstance(self.head, int) or isinstance(self.head, bool) or not 0 <= self.head <= 256:
            raise ConfigError(f"model head must be an integer in 0..256, got {self.head!r}")
        if self.arch in FLAT_ARCHS and self.head:
            raise ConfigError(f"model head must be 0 for the flat {self.arch} (it already runs at full resolution)")
        if not isinstance(self.kernel, int) or isinstance(self.kernel, bool) \
                or not (self.kernel == 0 or (3 <= self.kernel <= MAX_KERNEL and self.kernel % 2)):
            raise ConfigError(f"model kernel must be 0 or an odd integer in 3..{MAX_KERNEL}, got {self.kernel!r}")
        if self.kernel and (not self.multiscale or self.output != "residual" or self.head):
            raise ConfigError("model kernel needs a multi-scale arch with residual output and no head")
        self._check_aux()

    def _check_aux(self) -> None:
        for name, known in (("aux_mode", AUX_MODES), ("aux_normals", AUX_NORMALS), ("aux_prefilter", AUX_PREFILTERS)):
            if getattr(self, name) not in known:
                raise ConfigError(f"unknown model {name} {getattr(self, name)!r} (known: {', '.join(known)})")
        changed = [f"{name} {getattr(self, name)!r}" for name, default in
                   (("aux_mode", "stem"), ("aux_normals", "world"), ("aux_prefilter", "none"))
                   if getattr(self, name) != default]
        if changed and not self.aux_inputs:
            raise ConfigError(f"model {', '.join(changed)} needs aux_inputs (albedo and normal)")
        multiscale_only = [f"{name} {getattr(self, name)!r}" for name, default in
                     (("aux_mode", "stem"), ("aux_prefilter", "none")) if getattr(self, name) != default]
        if multiscale_only and not self.multiscale:
            raise ConfigError(f"model {', '.join(multiscale_only)} needs a multi-scale arch (not {self.arch})")
        if self.aux_mode != "stem" and self.head:
            raise ConfigError(f"model aux_mode {self.aux_mode!r} needs no head (the head reads the buffers)")
        if self.aux_mode == "kernel" and not self.kernel:
            raise ConfigError("model aux_mode 'kernel' needs a predicted filter (kernel > 0)")

    @property
    def kernel_taps(self) -> int:
        """Coefficients per pixel of the predicted filter: its k*k - 1 neighbours (0 without one)."""
        return self.kernel ** 2 - 1 if self.kernel else 0

    @property
    def multiscale(self) -> bool:
        """True for the encoder/decoder archs of :mod:`model.unet`."""
        return self.arch in UNET_ARCHS

    @property
    def in_channels(self) -> int:
        """Network input channels: RGB + 6 gradient channels (+ albedo + normal) (+ noise)."""
        return self.image_channels + 6

    @property
    def stem_channels(self) -> int:
        """Channels of the network input the multi-scale stem reads: all of them, but the
        albedo and normal where ``aux_mode`` keeps them from the stem (``levels``, ``kernel``)."""
        return self.in_channels - AUX_CHANNELS * (self.aux_inputs and self.aux_mode in ("levels", "kernel"))

    @property
    def skip_channels(self) -> int:
        """Channels of the network input the multi-scale input skip reads: all of them, but the
        albedo and normal where ``aux_mode`` is not ``stem``."""
        return self.in_channels - AUX_CHANNELS * (self.aux_inputs and self.aux_mode != "stem")

    @property
    def image_channels(self) -> int:
        """Channels of the image tensor the model takes: RGB (+ albedo RGB + normal XYZ)
        (+ noise RGB + flag): 3, 7, 9 or 13, in that order."""
        return 3 + AUX_CHANNELS * self.aux_inputs + NOISE_CHANNELS * self.noise_input

    @property
    def color_groups(self) -> tuple[int, ...]:
        """First channels of the image tensor's colour triplets (RGB, albedo, noise RGB): the
        channels an RGB permutation (augmentation) must permute alike."""
        return (0,) + ((3,) if self.aux_inputs else ()) + ((self.noise_start,) if self.noise_input else ())

    @property
    def camera_normals(self) -> int | None:
        """Index of the image tensor's normal XYZ when they are in the camera's frame (training's
        flips and transposes turn them with the image), else None."""
        return 3 + 3 if self.aux_inputs and self.aux_normals == "camera" else None

    @property
    def noise_start(self) -> int:
        """Index of the first noise channel in the image tensor (the 4 noise channels come last)."""
        return self.image_channels - NOISE_CHANNELS

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
    "flat-s": ModelConfig(layers=10, growth=8, init_features=16, transfer="pu"),
    "flat-m": ModelConfig(layers=20, growth=8, init_features=16, transfer="pu"),
    "flat-l": ModelConfig(layers=30, growth=8, init_features=16, transfer="pu"),
    "paper": ModelConfig(layers=20, growth=12, init_features=24, transfer="pu"),
    # the multi-scale family (model.unet): 2-3 dense layers per block, 5 resolutions (1/2 .. 1/32); RGB
    # only: the noise input (--noise-input) cost 1.4 dB at equal CPU time (docs/experiments.md, science)
    "unet-s": ModelConfig(arch="dense_unet", levels=4, layers=2, growth=8, init_features=24, transfer="pu"),
    "unet-m": ModelConfig(arch="dense_unet", levels=4, layers=2, growth=12, init_features=32, transfer="pu"),
    "unet-l": ModelConfig(arch="dense_unet", levels=4, layers=3, growth=16, init_features=48, transfer="pu"),
}
# What ``train`` builds when no preset is named: unet-m with the predicted 5x5 filter, the network of
# the registry's unet-m-k5-lowspp (training/recipes/unet-m-k5-lowspp.toml).
DEFAULT_TRAIN_MODEL = dataclasses.replace(PRESETS["unet-m"], kernel=5)


def preset(name: str, **overrides: Any) -> ModelConfig:
    """The named preset, with optional field overrides (e.g. ``arch="plaincnn"``); raises
    :class:`ConfigError` listing the valid names for any other name, or for an unknown field."""
    if not isinstance(name, str) or name not in PRESETS:
        raise ConfigError(f"unknown model preset {name!r} (valid: {', '.join(PRESETS)})")
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(ModelConfig)})
    if unknown:
        raise ConfigError(f"unknown model config key(s): {', '.join(map(str, unknown))}")
    return dataclasses.replace(PRESETS[name], **overrides)
