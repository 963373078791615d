"""Batches prepared ahead: the same batch for a step whoever prepares it (the step itself, a thread,
forked worker processes), delivered as NCHW tensors."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from training.batches import BatchSource, auto_workers, to_tensor
from training.patches import PatchConfig, TrainingPair
from training.train_config import TrainConfig


def _pairs(rng: np.random.Generator) -> list[TrainingPair]:
    return [TrainingPair(rng.random((40, 40, 3), dtype=np.float32), rng.random((40, 40, 3), dtype=np.float32), i, 4)
            for i in range(3)]


@pytest.mark.parametrize("prefetch, workers", [(True, 0), (False, 2)], ids=["thread", "processes"])
def test_every_way_gives_the_steps_own_batch(rng: np.random.Generator, prefetch: bool, workers: int) -> None:
    pairs = _pairs(rng)
    config = TrainConfig(data="d", out="o", batch=4, steps=10, patch=PatchConfig(size=16, min_unique=0),
                         prefetch=prefetch)
    plain = BatchSource(pairs, dataclasses.replace(config, prefetch=False))
    ahead = BatchSource(pairs, config, workers=workers)
    try:
        for step in (0, 1, 2, 5, 6, 9):  # in order, then a jump (a resumed run), then the last step
            for a, b in zip(ahead.get(step), plain.get(step)):
                assert a.shape == b.shape and torch.equal(a, b)
    finally:
        ahead.close()
    assert ahead._pending == {}


def test_tensors_are_nchw_in_the_asked_memory_order(rng: np.random.Generator) -> None:
    batch = rng.random((2, 8, 8, 3), dtype=np.float32)
    last, plain = to_tensor(batch, True), to_tensor(batch, False)
    assert last.shape == plain.shape == (2, 3, 8, 8)
    assert last.is_contiguous(memory_format=torch.channels_last) and plain.is_contiguous()
    assert torch.equal(last, plain)


def test_workers_only_where_a_gpu_waits() -> None:
    assert auto_workers(torch.device("cpu"), cores=16) == 0
    assert auto_workers(torch.device("cuda"), cores=16) == 8
    assert auto_workers(torch.device("cuda"), cores=4) == 3
    assert auto_workers(torch.device("cuda"), cores=1) == 1
