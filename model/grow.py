"""Deepen a trained DenseNet without changing what it computes (a Net2Net-style warm start).

A dense block of L layers is a prefix of one of L' > L layers with the same growth rate, first-conv
width and bottleneck: layer i sees ``c0 + i*k`` channels either way. :func:`grow_model` copies the
source's head, its L layers and its tail BatchNorm into the deeper model, and sets the tail conv's
weights on the ``(L'-L)*k`` new channels to zero. The new layers keep their He init, so they learn
from the first step (the tail weights on their outputs receive gradient), while the grown model in
eval mode computes exactly the source's output — training starts from the source's quality instead
of from the identity. The residual model's zero-initialised last conv works the same way.
A checkpoint of the very same model config (e.g. a multi-scale net) is copied as it is: a new run
(fresh optimiser, schedule and step count) that starts from trained weights. A multi-scale net
without the full-resolution head (:func:`model.unet.make_head`) is copied into the same net with
one, or with the predicted filter (``ModelConfig.kernel``): the head's last conv and the filter's
coefficients start at zero, so the grown net, too, starts by computing the source's output.
A multi-scale net without albedo and normal inputs is copied into the same net with them, in
any ``aux_mode`` (:mod:`model.aux_input`): the stem's and skip's weights on the buffers and the
buffers' branches' last convs are zero, so the grown net computes exactly (bit for bit, in eval
mode) the source's output whatever the buffers hold, and learns to use them from there.

The other way, a model with fewer layers takes the source's head, its first layers and the tail's
BatchNorm and conv weights on their channels (:func:`shrink_model`): a prefix of the trained block.
It computes what the source would with the dropped layers' tail weights set to zero, so it does not
start at the source's output, but from trained features that fine-tuning adapts the tail to (a
cheaper network warm-started from a trained one).
"""
from __future__ import annotations

import dataclasses

import torch

from imaging.errors import ConfigError
from model.aux_input import widen_weight
from model.config import ModelConfig

_SAME = ("arch", "growth", "init_features", "bottleneck", "transfer", "output", "aux_inputs")


def check_growable(source: ModelConfig, target: ModelConfig, shrink: bool = False) -> None:
    """Raise :class:`ConfigError` unless ``target`` is ``source`` with at least as many layers (with
    ``shrink``: at most as many, at least one)."""
    if source.arch != "densenet" or target.arch != "densenet":
        raise ConfigError("only densenet models can be grown (plaincnn has no dense block)")
    diff = [f"{k}: {getattr(source, k)!r} vs {getattr(target, k)!r}" for k in _SAME
            if getattr(source, k) != getattr(target, k)]
    if diff:
        raise ConfigError(f"cannot grow the model: it differs from the source in {'; '.join(diff)}")
    if shrink:
        if not 1 <= target.layers <= source.layers:
            raise ConfigError(f"cannot shrink {source.layers} layers into {target.layers}")
    elif target.layers < source.layers:
        raise ConfigError(f"cannot grow {source.layers} layers into {target.layers} (fewer)")


@torch.no_grad()
def grow_model(target: torch.nn.Module, source: torch.nn.Module) -> None:
    """Overwrite ``target``'s head, first layers and tail with ``source``'s (see module docstring).

    ``target``'s extra layers keep their current (He) init. Raises :class:`ConfigError` if the
    configs are not growable. Afterwards ``target.eval()(x) == source.eval()(x)`` up to rounding.
    A ``target`` with fewer layers is :func:`shrink_model`'s (its output is not the source's).
    A source with the very same config (any architecture; the noise input's averaging window may
    differ, the weights do not depend on it) is copied whole: a warm start.
    """
    same = dataclasses.replace(source.config, noise_radius=target.config.noise_radius)
    if same == target.config:
        target.load_state_dict(source.state_dict(), strict=True)
        return
    gains_output = not same.head and not same.kernel \
        and dataclasses.replace(same, head=target.config.head, kernel=target.config.kernel) == target.config
    if target.config.multiscale and gains_output:
        target.load_state_dict(source.state_dict(), strict=False)  # all but the new head or filter
        return
    if target.config.multiscale and not same.aux_inputs and _without_aux(target.config) == same:
        add_aux(target, source)
        return
    if target.config.arch == source.config.arch == "densenet" and target.config.layers < source.config.layers:
        shrink_model(target, source)
        return
    check_growable(source.config, target.config)
    target.tail[-1].weight.zero_()  # the new layers' outputs start unused
    _copy_prefix(target, source, len(source.body.layers))


def _without_aux(config: ModelConfig) -> ModelConfig:
    """``config`` without albedo and normal inputs (and the options that go with them)."""
    return dataclasses.replace(config, aux_inputs=False, aux_mode="stem", aux_normals="world", aux_prefilter="none")


@torch.no_grad()
def add_aux(target: torch.nn.Module, source: torch.nn.Module) -> None:
    """Copy the multi-scale RGB net ``source`` into ``target``, the same net with albedo and normal
    inputs: every weight of ``source`` in its place, the stem's and skip's columns on the buffers
    (``stem`` mode; ``noskip``: the stem's) zero, the branches of ``levels`` and ``kernel`` mode with
    their last conv zero (:mod:`model.aux_input`). Raises :class:`ConfigError` unless ``target``'s
    config is ``source``'s with the buffers."""
    source_config = dataclasses.replace(source.config, noise_radius=target.config.noise_radius)
    if not (target.config.multiscale and target.config.aux_inputs and not source.config.aux_inputs
            and _without_aux(target.config) == source_config):
        raise ConfigError("cannot add albedo/normal inputs: the model is not the source with them")
    state = target.state_dict()
    for key, value in source.state_dict().items():
        if state[key].shape != value.shape:  # the stem or skip reads the buffers too
            value = widen_weight(value, target.config)
        state[key].copy_(value)
    for branch in (target.aux_levels, target.aux_kernel):
        if branch is not None:
            branch.start_at_zero()


@torch.no_grad()
def shrink_model(target: torch.nn.Module, source: torch.nn.Module) -> None:
    """Overwrite ``target`` with ``source``'s head, its first ``target``'s-count layers and the tail's
    weights on their channels (see module docstring). Raises :class:`ConfigError` unless ``target``
    is ``source`` with fewer (at least one) layers."""
    check_growable(source.config, target.config, shrink=True)
    _copy_prefix(target, source, len(target.body.layers))


def _copy_prefix(target: torch.nn.Module, source: torch.nn.Module, layers: int) -> None:
    """Copy ``source``'s head, its first ``layers`` dense layers, and its tail's BatchNorm and conv
    weights on the channels those produce, into the same places of ``target``."""
    copied = ("head.", *(f"body.layers.{i}." for i in range(layers)))
    target_state = target.state_dict()
    for key, value in source.state_dict().items():
        if key.startswith(copied):
            target_state[key].copy_(value)
    c = min(source.body.out_channels, target.body.out_channels)
    src_bn, dst_bn = source.tail[0], target.tail[0]
    for name in ("weight", "bias", "running_mean", "running_var"):
        getattr(dst_bn, name)[:c] = getattr(src_bn, name)[:c]
    dst_bn.num_batches_tracked.copy_(src_bn.num_batches_tracked)
    target.tail[-1].weight[:, :c] = source.tail[-1].weight[:, :c]
