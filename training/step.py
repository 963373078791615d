"""One optimisation step: LR schedule, loss, NaN/Inf guard, optional gradient clipping.

A step whose loss or gradient norm is NaN/Inf is skipped: no optimiser update, and the BatchNorm
running statistics are restored to their values before the step, so a bad batch never reaches the
weights. :class:`NonFiniteGuard` counts such steps and raises :class:`TrainingError` after
``limit`` in a row.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from imaging.errors import TrainingError
from training.loss import GRADIENT_WEIGHT, denoising_loss


def learning_rate(base_lr: float, decay: float, decay_every: int, step: int, warmup: int = 0,
                  cosine_steps: int = 0, final: float = 0.01) -> float:
    """LR of step ``step`` (counting from 0), ramped up linearly over the first ``warmup`` steps
    (``(step + 1) / warmup`` of it).

    ``cosine_steps == 0``: the paper's step schedule ``base_lr * decay ** (step // decay_every)``.
    ``cosine_steps > 0``: cosine decay from ``base_lr`` to ``final * base_lr`` over that many steps
    (then constant), as OIDN's one-cycle schedule after its warm-up.
    """
    ramp = min(1.0, (step + 1) / warmup) if warmup > 0 else 1.0
    if cosine_steps > 0:
        t = min(step, cosine_steps) / cosine_steps
        return base_lr * (final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * t))) * ramp
    return base_lr * decay ** (step // decay_every) * ramp


class NonFiniteGuard:
    """Counts skipped steps; raises :class:`TrainingError` after ``limit`` consecutive ones."""

    def __init__(self, limit: int, skipped_total: int = 0) -> None:
        self.limit = limit
        self.consecutive = 0
        self.skipped_total = skipped_total

    def bad(self, step: int, what: str) -> None:
        """Record a skipped step; raise once ``limit`` were skipped in a row."""
        self.consecutive += 1
        self.skipped_total += 1
        if self.consecutive >= self.limit:
            raise TrainingError(f"step {step}: {what} was NaN/Inf for {self.consecutive} steps in a row; "
                                f"stopping (try a lower --lr or --grad-clip)")

    def good(self) -> None:
        """Record a successful step."""
        self.consecutive = 0


@dataclass(frozen=True)
class StepResult:
    """``loss``: the batch loss (NaN/Inf when skipped); ``grad_norm``: total L2 gradient norm
    before clipping (NaN when the loss was already bad); ``skipped``: no update was made."""

    loss: float
    grad_norm: float
    skipped: bool


def train_step(model: torch.nn.Module, optimizer: torch.optim.Optimizer, noisy: torch.Tensor,
               ref: torch.Tensor, *, step: int, lr: float, guard: NonFiniteGuard,
               grad_clip: float | None = None, bf16: bool = False,
               micro_batch: int | None = None,
               reduce_loss: Callable[[float], float] | None = None,
               gradient_weight: float = GRADIENT_WEIGHT, log_eps: float = 0.0,
               ms_ssim_weight: float = 0.0, loss_norm: str = "l1",
               loss_space: Callable[[torch.Tensor], torch.Tensor] | None = None) -> StepResult:
    """Forward, loss, backward and (unless NaN/Inf) an optimiser update on one batch.

    ``noisy``: NxCxHxW transfer-space input, ``ref``: Nx3xHxW transfer-space target.
    ``bf16`` runs the forward pass under bfloat16 autocast on the batch's device (loss in float32).
    ``micro_batch`` splits the batch into chunks of that size whose gradients are accumulated
    (the update still averages over all N patches, but BatchNorm normalises each chunk with its
    own statistics and updates its running statistics once per chunk).
    ``gradient_weight``: share of the gradient-L1 term in the loss, ``log_eps`` > 0: the mean of
    the patches' log losses, ``ms_ssim_weight``: share of 1 - MS-SSIM, ``loss_norm`` and ``loss_space``
    (its ``norm`` and ``to_space``; all :func:`training.loss.denoising_loss`).
    ``reduce_loss`` maps each chunk's loss to the value all data-parallel processes agree on (the
    mean over DDP ranks, NaN if any rank's is NaN), so that every rank skips the same steps;
    None keeps this process's own value.
    """
    for group in optimizer.param_groups:
        group["lr"] = lr
    buffers = [b.detach().clone() for b in model.buffers()]
    optimizer.zero_grad(set_to_none=True)
    size = micro_batch or len(noisy)
    loss_value = 0.0
    for start in range(0, len(noisy), size):
        with torch.autocast(noisy.device.type, dtype=torch.bfloat16, enabled=bf16):
            out = model(noisy[start:start + size])
        loss = denoising_loss(out, ref[start:start + size], gradient_weight, log_eps,
                              ms_ssim_weight, loss_norm, loss_space) * (len(out) / len(noisy))
        chunk_loss = float(loss.detach())
        if reduce_loss is not None:
            chunk_loss = reduce_loss(chunk_loss)
        loss_value += chunk_loss
        if not math.isfinite(chunk_loss):
            optimizer.zero_grad(set_to_none=True)
            _restore(model, buffers)
            guard.bad(step, "the loss")
            return StepResult(chunk_loss, float("nan"), True)
        loss.backward()
    params = [p for p in model.parameters() if p.grad is not None]
    norm = float(torch.nn.utils.clip_grad_norm_(params, grad_clip if grad_clip else math.inf, foreach=True))
    if not math.isfinite(norm):
        optimizer.zero_grad(set_to_none=True)
        _restore(model, buffers)
        guard.bad(step, "the gradient")
        return StepResult(loss_value, norm, True)
    optimizer.step()
    guard.good()
    return StepResult(loss_value, norm, False)


def _restore(model: torch.nn.Module, buffers: list[torch.Tensor]) -> None:
    with torch.no_grad():
        for buf, saved in zip(model.buffers(), buffers):
            buf.copy_(saved)
