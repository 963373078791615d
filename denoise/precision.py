"""The float format the folded inference networks compute in.

``float32``: exact up to float32 rounding (the reference). ``bfloat16``: the convolutions and the
activations between them in bfloat16 (8-bit mantissa, float32 accumulation inside oneDNN); the
network's input (transfer-space RGB, gradients, noise channels) is built in float32 and its
output converted back to float32 before the residual is added, so the noisy image itself is not
rounded. On CPUs with native bfloat16 arithmetic (AMX or AVX512-BF16) this halves the network's
time; elsewhere oneDNN emulates it and it is slower than float32. ``auto`` picks bfloat16 only
where the CPU has it natively, for the multi-scale networks, and for a flat network only where it
runs on renders of at most :data:`FLAT_BF16_MAX_SPP` spp (a member limited so, ``NAME:-16``, or a
checkpoint trained on them): in bfloat16 a flat network loses about 0.1 dB on clean renders (flat-s-allspp
on the eval scenes at 128 spp: 40.99 dB against 41.12 in float32; none at 16 spp), far below a noisy
render's own noise (docs/experiments.md, "Inference speed and precision"). A registry entry may fix a
member's format (``NAME@bfloat16``). Its speed: ``benchmarks/inference.py``.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

PRECISIONS = ("auto", "float32", "bfloat16")
NATIVE_BF16_FLAGS = frozenset({"amx_bf16", "avx512_bf16"})
FLAT_BF16_MAX_SPP = 16  # auto: a flat net limited to renders of at most this many spp computes in bfloat16


def cpu_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> frozenset[str]:
    """The feature flags of the first CPU listed in ``cpuinfo`` (empty where it cannot be read)."""
    try:
        text = Path(cpuinfo).read_text(errors="replace")
    except OSError:
        return frozenset()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            return frozenset(value.split())
    return frozenset()


def native_bfloat16(cpuinfo: str | Path = "/proc/cpuinfo") -> bool:
    """True when the CPU computes bfloat16 natively (AMX-BF16 or AVX512-BF16)."""
    return bool(cpu_flags(cpuinfo) & NATIVE_BF16_FLAGS)


def check_precision(precision: str) -> str:
    """``precision`` if it is one of :data:`PRECISIONS`; raises ValueError otherwise."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    return precision


def compute_dtype(precision: str, multiscale: bool = True, cpuinfo: str | Path = "/proc/cpuinfo",
                  max_spp: int = 0) -> torch.dtype:
    """The torch dtype of ``precision`` (one of :data:`PRECISIONS`) for a network that is
    ``multiscale`` or flat and runs on renders of at most ``max_spp`` spp (0: any). ``auto`` keeps a
    flat network in float32 unless ``max_spp`` is within :data:`FLAT_BF16_MAX_SPP`; raises
    ValueError for an unknown precision. (torch is imported here: the CLIs read
    :data:`PRECISIONS` before they need torch.)"""
    import torch

    if check_precision(precision) == "auto":
        low_spp_only = 0 < max_spp <= FLAT_BF16_MAX_SPP
        return torch.bfloat16 if (multiscale or low_spp_only) and native_bfloat16(cpuinfo) else torch.float32
    return torch.bfloat16 if precision == "bfloat16" else torch.float32
