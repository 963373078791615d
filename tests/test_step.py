"""One optimisation step: the loss goes down, the LR schedule, and the NaN/Inf guard."""
from __future__ import annotations

import pytest
import torch

from imaging.errors import TrainingError
from model.architectures import build_model
from model.config import ModelConfig
from training.loss import denoising_loss
from training.step import NonFiniteGuard, learning_rate, train_step

TINY = ModelConfig(layers=2, growth=4, init_features=8)


def _batch() -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    ref = torch.rand(4, 3, 12, 12, generator=gen) * 0.5
    return ref + 0.1 * torch.randn(4, 3, 12, 12, generator=gen), ref


def test_steps_reduce_loss_on_fixed_batch() -> None:
    torch.manual_seed(0)
    model = build_model(TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    noisy, ref = _batch()
    guard = NonFiniteGuard(5)
    # residual model: starts as the identity (loss = the noise), measured 0.081 -> 0.064 in 12 steps
    losses = [train_step(model, opt, noisy, ref, step=s, lr=1e-3, guard=guard).loss for s in range(12)]
    assert losses[-1] < 0.85 * losses[0]
    assert guard.skipped_total == 0


def test_learning_rate_schedule() -> None:
    assert learning_rate(0.01, 0.9, 10_000, 0) == pytest.approx(0.01)
    assert learning_rate(0.01, 0.9, 10_000, 9_999) == pytest.approx(0.01)
    assert learning_rate(0.01, 0.9, 10_000, 10_000) == pytest.approx(0.009)
    assert learning_rate(0.01, 0.9, 10_000, 25_000) == pytest.approx(0.0081)
    assert learning_rate(0.01, 0.9, 10_000, 0, warmup=4) == pytest.approx(0.0025)
    assert learning_rate(0.01, 0.9, 10_000, 3, warmup=4) == pytest.approx(0.01)


def test_step_sets_lr() -> None:
    model = build_model(TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1.0)
    train_step(model, opt, *_batch(), step=0, lr=0.0042, guard=NonFiniteGuard(3))
    assert opt.param_groups[0]["lr"] == 0.0042


def test_nan_batch_is_skipped_and_weights_untouched() -> None:
    torch.manual_seed(0)
    model = build_model(TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    noisy, ref = _batch()
    guard = NonFiniteGuard(3)
    train_step(model, opt, noisy, ref, step=0, lr=1e-2, guard=guard)  # Adam state exists now
    before = {k: v.clone() for k, v in model.state_dict().items()}
    adam_before = {i: {k: v.clone() for k, v in s.items()} for i, s in opt.state_dict()["state"].items()}
    bad = noisy.clone()
    bad[0, 0, 3, 3] = float("nan")
    result = train_step(model, opt, bad, ref, step=1, lr=1e-2, guard=guard)
    assert result.skipped and guard.skipped_total == 1 and guard.consecutive == 1
    for key, value in model.state_dict().items():  # weights AND BatchNorm running stats
        torch.testing.assert_close(value, before[key], rtol=0, atol=0, equal_nan=False)
    for i, state in opt.state_dict()["state"].items():
        for key, value in state.items():
            torch.testing.assert_close(value, adam_before[i][key], rtol=0, atol=0)
    assert not train_step(model, opt, noisy, ref, step=2, lr=1e-2, guard=guard).skipped
    assert guard.consecutive == 0 and guard.skipped_total == 1


def test_inf_target_is_skipped() -> None:
    model = build_model(TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    noisy, ref = _batch()
    ref[0, 1, 0, 0] = float("inf")
    assert train_step(model, opt, noisy, ref, step=0, lr=1e-2, guard=NonFiniteGuard(3)).skipped


def test_guard_stops_after_limit() -> None:
    model = build_model(TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    noisy, ref = _batch()
    noisy[:] = float("nan")
    guard = NonFiniteGuard(3)
    train_step(model, opt, noisy, ref, step=0, lr=1e-2, guard=guard)
    train_step(model, opt, noisy, ref, step=1, lr=1e-2, guard=guard)
    with pytest.raises(TrainingError, match="step 2: the loss was NaN/Inf for 3 steps in a row"):
        train_step(model, opt, noisy, ref, step=2, lr=1e-2, guard=guard)
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())


def test_grad_clip_limits_update() -> None:
    torch.manual_seed(0)
    model = build_model(TINY)
    noisy, ref = _batch()
    opt = torch.optim.SGD(model.parameters(), lr=1.0)
    before = [p.detach().clone() for p in model.parameters()]
    result = train_step(model, opt, noisy, ref, step=0, lr=1.0, guard=NonFiniteGuard(3), grad_clip=1e-3)
    assert result.grad_norm > 1e-3
    moved = torch.sqrt(sum(((p.detach() - b) ** 2).sum() for p, b in zip(model.parameters(), before)))
    assert float(moved) == pytest.approx(1e-3, rel=1e-3)


def test_loss_is_computed_in_float32_under_bf16() -> None:
    torch.manual_seed(0)
    model = build_model(TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    noisy, ref = _batch()
    result = train_step(model, opt, noisy, ref, step=0, lr=1e-3, guard=NonFiniteGuard(3), bf16=True)
    assert not result.skipped
    with torch.no_grad():
        assert denoising_loss(model(noisy), ref).dtype == torch.float32


def test_bf16_autocasts_on_the_batchs_device(monkeypatch: pytest.MonkeyPatch) -> None:
    """The forward pass autocasts where the batch lives (a GPU batch: on the GPU, in bfloat16), and
    only when asked."""
    seen = []
    real = torch.autocast

    def recording(device_type: str, *args: object, **kwargs: object) -> torch.autocast:
        seen.append((device_type, kwargs.get("dtype"), kwargs.get("enabled")))
        return real(device_type, *args, **kwargs)

    monkeypatch.setattr(torch, "autocast", recording)
    model = build_model(TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    train_step(model, opt, *_batch(), step=0, lr=1e-3, guard=NonFiniteGuard(3), bf16=True)
    train_step(model, opt, *_batch(), step=1, lr=1e-3, guard=NonFiniteGuard(3))
    assert seen == [("cpu", torch.bfloat16, True), ("cpu", torch.bfloat16, False)]


def test_micro_batch_of_whole_batch_is_identical_and_chunks_accumulate() -> None:
    noisy, ref = _batch()
    weights = []
    for micro in (None, 4, 2):
        torch.manual_seed(0)
        model = build_model(TINY)
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        result = train_step(model, opt, noisy, ref, step=0, lr=1e-3, guard=NonFiniteGuard(3), micro_batch=micro)
        assert not result.skipped
        weights.append(torch.cat([p.detach().reshape(-1) for p in model.parameters()]))
    torch.testing.assert_close(weights[1], weights[0], rtol=0, atol=0)
    assert not torch.equal(weights[2], weights[0])  # BatchNorm statistics per chunk differ
