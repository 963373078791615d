"""What a checkpoint's card says about how it was made: hardware, hours, recipe, pixel filter.

A run writes :func:`card_meta` into every checkpoint (``meta`` of :mod:`model.checkpoint`). Hours
add up along a chain of warm starts: a run that starts from another checkpoint's weights
(``init_from``) begins with that checkpoint's hours and hardware, so the last stage of a recipe
carries the whole recipe's cost.
"""
from __future__ import annotations

import functools
import platform
from pathlib import Path
from typing import Any

import torch

from imaging.errors import DatasetError
from model.checkpoint import BOX_FILTER, checkpoint_meta
from model.device import device_name
from training.batches import available_cpus


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
