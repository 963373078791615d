"""Random networks for the tests: BatchNorm statistics (and affine parameters) that a trained
network has, so that folding, precision and checkpoint tests see more than the identity."""
from __future__ import annotations

import torch


def randomize_batchnorm(model: torch.nn.Module, mean: float, var: tuple[float, float],
                        bias: float | None = None, positive: bool = False) -> None:
    """Draw every BatchNorm2d's running mean in [-mean, mean] and variance in ``var``; with ``bias``,
    also its weight in [-1.5, 1.5] ([0.1, 1.5] if ``positive``, as trained ones are) with channel 0
    dead (relu(0*x + t) is a constant) and its bias in [-bias, bias]. Draws in that order from
    torch's global generator."""
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-mean, mean)
                m.running_var.uniform_(*var)
                if bias is not None:
                    m.weight.uniform_(0.1 if positive else -1.5, 1.5)
                    m.weight[0] = 0.0
                    m.bias.uniform_(-bias, bias)
