"""Transfer functions: linear HDR radiance <-> the space the network sees.

Each curve has an exact inverse and is scaled so that ``HDR_MAX`` (65504, the float16 maximum)
maps to 1; radiance 0 maps to 0. Forward clamps negative radiance to 0. Computed in float64
internally and returned in the input's dtype (float32 round trip: rtol 1e-5 over 0..65504).

* ``log``: ``log1p(y) / log1p(65504)`` — radiance 1 maps to ~0.0625.
* ``pu``: the perceptually-uniform fit used by Intel Open Image Denoise (``training/color.py``):
  linear near 0, a power segment, then logarithmic; radiance 1 maps to ~0.319.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from imaging.errors import ConfigError

HDR_MAX = 65504.0
DISPLAY_GAMMA = 2.2  # imaging.metrics.tonemap's
DISPLAY_FLOOR = 1e-5  # TransferFunction.display's lower bound of y / (1 + y)

# OIDN's PU curve: y <= Y0 linear, y <= Y1 power, log above; X0/X1 are the curve at Y0/Y1.
_PU_A = 1.41283765e03
_PU_B = 1.64593172e00
_PU_C = 4.31384981e-01
_PU_D = -2.94139609e-03
_PU_E = 1.92653254e-01
_PU_F = 6.26026094e-03
_PU_G = 9.98620152e-01
_PU_Y0 = 1.57945760e-06
_PU_Y1 = 3.22087631e-02


def _pu_forward(y: torch.Tensor) -> torch.Tensor:
    """The PU curve of ``y >= 0`` (``y`` is overwritten). Each branch in place on one tensor,
    then selected: 4 whole-image temporaries instead of 12, 2.3x faster at 1080p with the
    Denoiser's allocator setting (every temporary is a fresh mapping, :mod:`denoise.allocator`)."""
    out = torch.add(y, _PU_F).log_().mul_(_PU_E).add_(_PU_G)
    power = torch.pow(y, _PU_C).mul_(_PU_B).add_(_PU_D)
    torch.where(y <= _PU_Y1, power, out, out=out)
    del power
    low = y <= _PU_Y0
    return torch.where(low, y.mul_(_PU_A), out, out=out)


# Branch points of the inverse, taken from the forward curve itself so that forward and inverse
# switch branch at exactly the same place (the published X0/X1 differ in the last digits).
_PU_X0 = _PU_A * _PU_Y0
_PU_X1 = _PU_B * _PU_Y1 ** _PU_C + _PU_D


def _pu_inverse(x: torch.Tensor) -> torch.Tensor:
    """The inverse PU curve (``x`` is overwritten), in place as :func:`_pu_forward`."""
    out = torch.sub(x, _PU_G).div_(_PU_E).exp_().sub_(_PU_F)
    power = torch.sub(x, _PU_D).div_(_PU_B).clamp_(min=0.0).pow_(1.0 / _PU_C)
    torch.where(x <= _PU_X1, power, out, out=out)
    del power
    low = x <= _PU_X0
    return torch.where(low, x.div_(_PU_A), out, out=out)


_PU_SCALE = 1.0 / (_PU_E * math.log(HDR_MAX + _PU_F) + _PU_G)
_LOG_SCALE = 1.0 / math.log1p(HDR_MAX)


def _compute_dtype(t: torch.Tensor) -> torch.dtype:
    """float64 for float64 tensors, float32 otherwise: a float32 image's round trip stays within
    1e-5 relative (tests/test_model_transfer.py) at half the time of float64 temporaries (the
    curve runs on every pixel of every denoise call, twice with the noise input)."""
    return torch.float64 if t.dtype == torch.float64 else torch.float32


@dataclass(frozen=True)
class TransferFunction:
    """A named, normalised transfer curve; ``forward``/``inverse`` work on any-shaped tensors."""

    name: str

    def forward(self, radiance: torch.Tensor) -> torch.Tensor:
        """Linear radiance (negatives clamped to 0) -> transfer space, HDR_MAX -> 1."""
        y = torch.clamp(radiance.to(_compute_dtype(radiance)), min=0.0)  # a new tensor
        x = torch.log1p(y).mul_(_LOG_SCALE) if self.name == "log" else _pu_forward(y).mul_(_PU_SCALE)
        return x.to(radiance.dtype)

    def inverse(self, encoded: torch.Tensor) -> torch.Tensor:
        """Transfer space -> linear radiance; exact inverse of :meth:`forward` on its range."""
        x = encoded.to(_compute_dtype(encoded))
        y = torch.expm1(x / _LOG_SCALE) if self.name == "log" else _pu_inverse(x / _PU_SCALE)  # x / s: new
        return y.clamp_(max=HDR_MAX).to(encoded.dtype)  # float32 rounding at 1.0 gives 65504.008

    def display(self, encoded: torch.Tensor) -> torch.Tensor:
        """Transfer space -> the metrics' display values ``(y / (1 + y)) ** (1 / 2.2)`` of the
        radiance ``y`` (:func:`imaging.metrics.tonemap`), differentiable: a loss in the space PSNR
        is measured in. ``encoded`` is clamped to [0, 1] first (the metric clamps negative
        radiance) and ``y / (1 + y)`` to at least ``DISPLAY_FLOOR`` (the gamma's slope is infinite
        at 0; the floor moves a display value by at most 0.006)."""
        x = torch.clamp(encoded, 0.0, 1.0)
        y = torch.expm1(x / _LOG_SCALE) if self.name == "log" else _pu_inverse_autograd(x / _PU_SCALE)
        return torch.clamp(y / (1.0 + y), min=DISPLAY_FLOOR) ** (1.0 / DISPLAY_GAMMA)


def _pu_inverse_autograd(x: torch.Tensor) -> torch.Tensor:
    """:func:`_pu_inverse` without in-place operations, for a loss to differentiate through."""
    log_branch = torch.exp((x - _PU_G) / _PU_E) - _PU_F
    power = torch.clamp((x - _PU_D) / _PU_B, min=0.0) ** (1.0 / _PU_C)
    return torch.where(x <= _PU_X0, x / _PU_A, torch.where(x <= _PU_X1, power, log_branch))


def get_transfer(name: str) -> TransferFunction:
    """The transfer function called ``name`` (``"log"`` or ``"pu"``)."""
    if name not in ("log", "pu"):
        raise ConfigError(f"unknown transfer function {name!r} (known: log, pu)")
    return TransferFunction(name)
