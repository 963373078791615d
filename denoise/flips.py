"""Test-time flips: which mirrored copies of its input a network's output is averaged over.

``flips`` = 1 (the network as it is), 2 (and its left-right mirror) or 4 (and the up-down and the
doubly mirrored copies). Measured on the eval scenes (docs/experiments.md): 2 flips buy 0.10-0.14 dB, 4
flips 0.20-0.24 dB, for 2x and 4x the network's time. :func:`denoise.chain.flip_average` computes
it; this module only names the choices (the CLIs read them without importing torch).
"""
from __future__ import annotations

# flips -> the dims of an NxCxHxW tensor to mirror, one tuple per copy (() = as it is)
FLIPS: dict[int, tuple[tuple[int, ...], ...]] = {1: ((),), 2: ((), (-1,)), 4: ((), (-1,), (-2,), (-2, -1))}


def check_flips(flips: int) -> int:
    """``flips`` if it is a key of :data:`FLIPS`; raises ValueError otherwise."""
    if flips not in FLIPS:
        raise ValueError(f"flips must be one of {', '.join(map(str, FLIPS))}, got {flips!r}")
    return flips
