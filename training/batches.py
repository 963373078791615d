"""The batches of a run: one deterministic batch per step, prepared ahead, delivered on the run's device.

The batch of step ``s`` is drawn from ``numpy.random.default_rng([seed, s])`` (:meth:`BatchSource._make`),
so whichever worker prepares it, and whether the run was resumed, it is the same batch. Ahead of
the step that needs it, a batch is prepared by

* nothing (``prefetch`` off, no workers): in the step itself;
* one background thread (``prefetch``, no workers; the CPU default: sampling crops is cheap next to
  a CPU step);
* ``workers`` processes (forked, so they share the images in RAM; each returns a batch as numpy
  arrays), ``2 * workers`` steps ahead: what keeps a GPU busy, whose step is shorter than the
  crop sampling of one CPU core.

On a CUDA device a batch is copied from pinned memory without blocking the host.
"""
from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np
import torch

from model.noise_input import drop_noise
from training.patches import TrainingPair, sample_batch
from training.train_config import TrainConfig

MAX_AUTO_WORKERS = 8
_FORKED: BatchSource | None = None  # the source a forked worker prepares batches of (inherited at fork)


def available_cpus() -> int:
    """Cores this process may run on: its affinity mask where the OS has one, else all cores."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def auto_workers(device: torch.device, cores: int | None = None) -> int:
    """Batch worker processes for ``workers = 0``: none on the CPU (the step keeps the cores busy;
    one prefetch thread is enough), else every core but the one that drives the GPU, at most
    :data:`MAX_AUTO_WORKERS`."""
    if device.type == "cpu":
        return 0
    cores = available_cpus() if cores is None else cores
    return max(1, min(MAX_AUTO_WORKERS, cores - 1))


def to_tensor(batch: np.ndarray, channels_last: bool, device: torch.device | None = None) -> torch.Tensor:
    """NxHxWxC float32 array -> NxCxHxW tensor on ``device`` (channels-last memory order, or
    contiguous NCHW); to a CUDA device through pinned memory, asynchronously."""
    tensor = torch.from_numpy(batch)
    if device is not None and device.type == "cuda":
        tensor = tensor.pin_memory().to(device, non_blocking=True)
    tensor = tensor.permute(0, 3, 1, 2)
    return tensor if channels_last else tensor.contiguous()


def _forked_make(step: int) -> tuple[np.ndarray, np.ndarray]:
    assert _FORKED is not None
    return _FORKED._make(step)


class BatchSource:
    """Deterministic per-step batches on ``device``, prepared ahead (module docstring)."""

    def __init__(self, pairs: list[TrainingPair], config: TrainConfig, device: torch.device | None = None,
                 workers: int = 0) -> None:
        self.pairs, self.config = pairs, config
        self.device = device or torch.device("cpu")
        self.workers = workers
        self._threads = ThreadPoolExecutor(1, thread_name_prefix="patches") \
            if config.prefetch and not workers else None
        self._processes: Any = None
        self._pending: dict[int, Any] = {}  # step -> Future (thread) or AsyncResult (process)

    def _make(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng([self.config.seed, step])
        model = self.config.model
        noisy, ref = sample_batch(self.pairs, self.config.batch, self.config.patch, rng, model.color_groups,
                                  model.camera_normals)
        if model.noise_input:
            drop_noise(noisy, model.noise_start, self.config.noise_dropout, rng)
        return noisy, ref

    def _start_processes(self) -> None:
        global _FORKED
        _FORKED = self  # the children inherit it (and the images) at fork, without pickling
        try:
            self._processes = multiprocessing.get_context("fork").Pool(self.workers)
        finally:
            _FORKED = None

    def _submit(self, step: int) -> None:
        if self.workers:
            if self._processes is None:
                self._start_processes()
            self._pending[step] = self._processes.apply_async(_forked_make, (step,))
        elif self._threads is not None:
            self._pending[step] = self._threads.submit(self._make, step)

    def _ahead(self) -> int:
        return 2 * self.workers if self.workers else 1 if self._threads is not None else 0

    def batch(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(noisy NxPxPxC, ref NxPxPx3) transfer-space arrays of ``step``; queues the next steps."""
        pending = self._pending.pop(step, None)
        for stale in [s for s in self._pending if s < step]:  # a step was repeated or skipped
            del self._pending[stale]
        for ahead in range(step + 1, min(step + 1 + self._ahead(), self.config.steps)):
            if ahead not in self._pending:
                self._submit(ahead)
        if pending is None:
            return self._make(step)
        return pending.result() if isinstance(pending, Future) else pending.get()

    def get(self, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(noisy NxCxPxP, ref Nx3xPxP) transfer-space tensors of ``step`` on the device."""
        noisy, ref = self.batch(step)
        return (to_tensor(noisy, self.config.channels_last, self.device),
                to_tensor(ref, self.config.channels_last, self.device))

    def close(self) -> None:
        """Stop the background thread or processes."""
        self._pending.clear()
        if self._threads is not None:
            self._threads.shutdown(wait=True, cancel_futures=True)
        if self._processes is not None:
            self._processes.terminate()
            self._processes.join()
            self._processes = None
