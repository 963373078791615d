"""What a checkpoint's card says about how it was made: hardware, hours, recipe, pixel filter.

A run writes :func:`card_meta` into every checkpoint (``meta`` of :mod:`model.checkpoint`). Hours
add up along a chain of warm starts: a run that starts from another checkpoint's weights
(``init_from``) begins with that checkpoint's hours and hardware, so the last stage of a recipe
carries the whole recipe's cost.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import platform
from pathlib import Path
from typing import Any

import torch

from imaging.errors import ConfigError, DatasetError
from model.checkpoint import BOX_FILTER, checkpoint_meta
from model.config import ModelConfig
from model.device import device_name
from training.batches import available_cpus
from training.recipe import Recipe

# TrainConfig fields that say where and how a run ran, not what it computes
_RUN_FIELDS = {"data", "extra_data", "out", "cpu_budget_s", "threads", "workers", "device", "progress", "prefetch",
               "init_from"}


@functools.lru_cache(maxsize=1)
def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; the platform's processor string elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return " ".join(line.split(":", 1)[1].split())
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def hardware(device: torch.device) -> str:
    """One line naming what a run computes on: the GPU (for a CUDA device) and the CPU with the
    cores this process may use, e.g. ``NVIDIA H100 80GB HBM3 + AMD EPYC 9354 (16 cores)``."""
    host = f"{cpu_model()} ({available_cpus()} cores)"
    return f"{device_name(device)} + {host}" if device.type == "cuda" else host


def data_pixel_filter(data_config: dict[str, Any]) -> dict[str, Any]:
    """The pixel filter of a run's data (its ``data_config``: the primary dataset's ``dataset.json``
    with the extra datasets under ``extra_data``) as {"type": ...}; raises :class:`DatasetError`
    when the datasets were rendered with different filters (a model learns one filter's noise)."""
    filters = []
    for config in (data_config, *data_config.get("extra_data", [])):
        recorded = config.get("filter") or "box"
        filters.append({"type": recorded} if isinstance(recorded, str) else dict(recorded))
    if any(f != filters[0] for f in filters):
        raise DatasetError(f"the datasets were rendered with different pixel filters "
                           f"({', '.join(sorted({str(f) for f in filters}))}); train on one filter at a time")
    return filters[0] if filters else dict(BOX_FILTER)


def inherited(header: dict[str, Any] | None) -> dict[str, Any]:
    """The hours (CPU and GPU seconds) and hardware a run starts from: those recorded in the card
    of the checkpoint it was warm-started from (``header``; None: from scratch)."""
    meta = checkpoint_meta(header or {})
    hours = meta.get("hours") or {}
    return {"cpu_s": 3600.0 * float(hours.get("cpu") or 0.0), "gpu_s": 3600.0 * float(hours.get("gpu") or 0.0),
            "hardware": list(meta.get("hardware") or [])}


def card_meta(base: dict[str, Any], cpu_s: float, gpu_s: float, machine: str, pixel_filter: dict[str, Any],
              recipe: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``meta`` a run writes: hours of everything up to this file (``base``, from
    :func:`inherited`, plus this run's ``cpu_s`` and ``gpu_s``), the hardware of every stage, the
    data's ``pixel_filter`` and the ``recipe`` ({"name", "sha256", "stage"}) when a recipe ran it."""
    machines = list(base.get("hardware") or [])
    if machine not in machines:
        machines.append(machine)
    meta: dict[str, Any] = {
        "hours": {"cpu": round((base.get("cpu_s", 0.0) + cpu_s) / 3600.0, 6),
                  "gpu": round((base.get("gpu_s", 0.0) + gpu_s) / 3600.0, 6)},
        "hardware": machines, "pixel_filter": pixel_filter}
    if recipe:
        meta["recipe"] = dict(recipe)
    return meta


def recipe_meta(header: dict[str, Any], recipe: Recipe, hardware_name: str) -> dict[str, Any]:
    """The card's ``meta`` of a checkpoint that ``recipe``'s final stage made from scratch before
    runs wrote one (:func:`card_meta` from the file's own record of its run: ``extra.cpu_s`` and
    ``gpu_s``, its data's pixel filter; ``hardware_name`` from the recipe's ``[stages.measured]``).
    Raises :class:`ConfigError` unless the file's training config is that stage's (the settings
    that decide what it computes: not the run control or the data folders) and its run started
    from nothing: a warm start's hours would be unknown."""
    stage = recipe.final
    recorded = header.get("train_config") or {}
    if recorded.get("init_from") or stage.init_from:
        raise ConfigError(f"recipe {recipe.name}: only a run from scratch has its hours in its own file")
    expected = json.loads(json.dumps(dataclasses.asdict(stage.train_config("", [""], None)), default=list))
    if isinstance(recorded.get("model"), dict):  # network fields added since the file was written hold their defaults
        defaults = json.loads(json.dumps(dataclasses.asdict(ModelConfig()), default=list))
        recorded = {**recorded, "model": {**defaults, **recorded["model"]}}
    differ = sorted(k for k in expected if k not in _RUN_FIELDS and recorded.get(k) != expected[k])
    if differ:
        raise ConfigError(f"recipe {recipe.name}: the file was trained with other settings than stage "
                          f"{stage.name} ({', '.join(differ)})")
    extra = header.get("extra") or {}
    return card_meta({}, float(extra.get("cpu_s") or 0.0), float(extra.get("gpu_s") or 0.0), hardware_name,
                     data_pixel_filter(header.get("data_config") or {}), recipe.identity(stage.name))
