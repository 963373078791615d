"""Data-parallel training on several CPU processes with PyTorch DDP (gloo), launched by torchrun.

    torchrun --standalone --nproc-per-node 2 -m training.cli --data DIR --out RUN [...]
    train --nproc 2 --data DIR --out RUN [...]      (the same, through torchrun's own launcher)

What a run with N ranks computes — exactly what one process computes with ``micro_batch = B/N``:

- **Batches.** The global batch of step ``s`` is the single-process one (``rng([seed, s])``,
  ``batch`` = B patches); rank r keeps its shard, patches ``[r*B/N, (r+1)*B/N)``. DDP averages
  the gradients, so the update is the mean over all B patches.
- **BatchNorm.** Each rank normalises over its own B/N patches (SyncBatchNorm works only on GPUs
  in torch 2.13): "ghost batch norm" with chunks of B/N, which is what ``micro_batch`` does in one
  process. The run's config records it: ``micro_batch`` becomes B/N unless a smaller one was set,
  so the checkpoint says what was trained and resumes identically on 1 process or on any N with
  ``micro_batch`` dividing B/N. A run trained without ``micro_batch`` cannot be resumed on N > 1
  ranks (that would change what it learns). After each update the ranks' BatchNorm running
  statistics are merged into exactly the chunk-by-chunk updates of the single process.
- **Agreement.** Each chunk's loss is averaged over the ranks before the NaN/Inf check, so all
  ranks skip the same steps; after the all-reduce all ranks hold the same gradients and weights.

Rank 0 alone validates, logs, draws the progress bar and writes ``train_config.json``, the
checkpoints (atomically, as in one process) and ``curves.png``. Every rank holds the whole training
set in RAM and samples the whole global batch (cheap next to the network; on the prefetch thread).
If a rank dies, torchrun stops the others; the last complete ``last.ckpt`` stays, and the error
ends with the command that resumes it (``train --out RUN --resume --nproc N ...``: the original
command less what the checkpoint holds, see :func:`training.cli.resume_command`); it may also be
resumed with any other number of ranks, see above.

**Threads per rank** (:func:`choose_threads`): ``--threads`` if given; else ``OMP_NUM_THREADS``
if the environment sets it (torchrun sets 1 when it is unset and it starts several ranks); else
the cores this process may run on (its affinity mask: containers, ``taskset``) shared among the
ranks on this machine. ``train --nproc`` reports its choice and passes it to the ranks as
``OMP_NUM_THREADS``.
"""
from __future__ import annotations

import ctypes
import dataclasses
import datetime
import gc
import inspect
import logging
import os
import signal
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from imaging.errors import CheckpointError, ConfigError, TrainingError
from console.progress import ProgressFactory
from model.checkpoint import Checkpoint, read_checkpoint
from model.device import choose_device
from training.patches import TrainingPair
from training.run_log import RunLog
from training.batches import BatchSource, available_cpus
from training.train import TrainResult, _Run, run_training
from training.train_config import TrainConfig

BACKEND = "gloo"
TIMEOUT = datetime.timedelta(minutes=60)  # a collective waits this long (rank 0 validating...)


@dataclass(frozen=True)
class RankInfo:
    """This process's place in the job, from torchrun's environment variables."""

    rank: int
    world: int
    local_rank: int = 0
    local_world: int = 1

    @property
    def primary(self) -> bool:
        return self.rank == 0


def rank_from_env(env: dict[str, str] | None = None) -> RankInfo | None:
    """The :class:`RankInfo` torchrun set (RANK, WORLD_SIZE, LOCAL_RANK, LOCAL_WORLD_SIZE), or None."""
    env = dict(os.environ) if env is None else env
    if "RANK" not in env or "WORLD_SIZE" not in env:
        return None
    try:
        return RankInfo(int(env["RANK"]), int(env["WORLD_SIZE"]), int(env.get("LOCAL_RANK", 0)),
                        int(env.get("LOCAL_WORLD_SIZE", 1)))
    except ValueError:
        raise ConfigError(f"bad torchrun environment (RANK={env['RANK']!r}, "
                          f"WORLD_SIZE={env['WORLD_SIZE']!r})") from None


@dataclass(frozen=True)
class ThreadChoice:
    """Torch threads per rank and where the number came from (for the launcher's report)."""

    count: int
    source: str

    def __str__(self) -> str:
        return f"{self.count} torch thread{'s' if self.count != 1 else ''} each ({self.source})"


def choose_threads(threads: int | None, ranks_here: int, env: Mapping[str, str] | None = None) -> ThreadChoice:
    """Threads per rank for ``ranks_here`` ranks on this machine: ``threads`` (``--threads``), else
    an explicit ``OMP_NUM_THREADS`` in ``env`` (default ``os.environ``), else the available cores
    (:func:`available_cpus`) / ``ranks_here``. Raises :class:`ConfigError` for a bad OMP_NUM_THREADS."""
    env = os.environ if env is None else env
    if threads:
        return ThreadChoice(threads, "--threads or the config's threads")
    omp = env.get("OMP_NUM_THREADS")
    if omp is not None:
        if not omp.strip().isdigit() or int(omp) < 1:
            raise ConfigError(f"OMP_NUM_THREADS={omp!r} in the environment is not a positive integer")
        return ThreadChoice(int(omp), f"OMP_NUM_THREADS={int(omp)} in the environment")
    cpus = available_cpus()
    return ThreadChoice(max(1, cpus // ranks_here),
                        f"{cpus} core{'s' if cpus != 1 else ''} available to this process / {ranks_here} ranks")


def ddp_config(config: TrainConfig, world: int, resume: bool) -> TrainConfig:
    """``config`` as trained by ``world`` ranks: ``micro_batch`` set to the per-rank batch if unset.

    Raises :class:`ConfigError` if the batch does not split evenly, a run trained with whole-batch
    BatchNorm would be resumed on several ranks, or the run asks for a GPU (the ranks run on CPUs;
    ``auto`` means the CPU here).
    """
    if config.batch % world:
        raise ConfigError(f"batch {config.batch} does not split evenly over {world} ranks")
    if config.compile:
        raise ConfigError("--compile is not supported with DDP training (train without it)")
    if config.device.startswith("cuda"):
        raise ConfigError("DDP training runs on CPU processes (gloo); on a GPU train in one process "
                          "(--device cuda, no --nproc)")
    local = config.batch // world
    if config.micro_batch is None:
        if resume:
            raise ConfigError(f"this run normalises BatchNorm over the whole batch of {config.batch} "
                              f"(no micro_batch); {world} ranks would normalise over {local} patches "
                              f"each: resume it in one process")
        return dataclasses.replace(config, micro_batch=local)
    if local % config.micro_batch:
        raise ConfigError(f"micro_batch {config.micro_batch} does not divide the per-rank batch {local} "
                          f"(batch {config.batch} / {world} ranks)")
    return config


class ShardSource(BatchSource):
    """The single-process batch of each step, cut to this rank's shard of patches."""

    def __init__(self, pairs: list[TrainingPair], config: TrainConfig, shard: slice,
                 device: torch.device | None = None) -> None:
        super().__init__(pairs, config, device)
        self.shard = shard

    def _make(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        noisy, ref = super()._make(step)
        return noisy[self.shard], ref[self.shard]


class BatchNormMerge:
    """Optimiser post-step hook: give every rank the BatchNorm running statistics one process
    would have after running the global batch's chunks in order (rank 0's chunks first).

    Rank r ran ``chunks`` updates ``x <- (1-m) x + m c`` from the same start ``x0``, ending at
    ``x_r``; the sequential result is ``(1-m)^(N K) x0 + sum_r (1-m)^(K (N-1-r)) (x_r - (1-m)^K x0)``
    (one all-reduce, in float64). Skipped steps restore the statistics and make no optimiser step,
    so the hook never sees them.
    """

    def __init__(self, model: nn.Module, chunks: int, rank: RankInfo) -> None:
        self.layers = [m for m in model.modules()
                       if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.track_running_stats]
        if any(m.momentum is None for m in self.layers):
            raise ConfigError("DDP training needs BatchNorm with a momentum (not a cumulative average)")
        self.chunks, self.rank = chunks, rank
        self.start = self._snapshot()

    def _snapshot(self) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        return [(m.running_mean.clone(), m.running_var.clone(), m.num_batches_tracked.clone())
                for m in self.layers]

    @torch.no_grad()
    def __call__(self, optimizer: torch.optim.Optimizer, args: Any, kwargs: Any) -> None:
        world, k = self.rank.world, self.chunks
        parts = []
        for m, (mean0, var0, _) in zip(self.layers, self.start):
            keep = (1.0 - m.momentum) ** k
            weight = (1.0 - m.momentum) ** (k * (world - 1 - self.rank.rank))
            for now, before in ((m.running_mean, mean0), (m.running_var, var0)):
                parts.append(weight * (now.double() - keep * before.double()))
        flat = torch.cat(parts)
        dist.all_reduce(flat)
        offset = 0
        for m, (mean0, var0, count0) in zip(self.layers, self.start):
            keep_all = (1.0 - m.momentum) ** (k * world)
            for now, before in ((m.running_mean, mean0), (m.running_var, var0)):
                size = now.numel()
                now.copy_(keep_all * before.double() + flat[offset:offset + size].view_as(now))
                offset += size
            m.num_batches_tracked.copy_(count0 + world * (m.num_batches_tracked - count0))
        self.start = self._snapshot()


class _NoLog(RunLog):
    """The log of a rank other than 0: writes nothing."""

    def __init__(self) -> None:
        super().__init__(os.devnull)

    def append(self, record: dict[str, Any]) -> None:
        pass

    def read(self) -> list[dict[str, Any]]:
        return []

    def truncate_after(self, step: int) -> None:
        pass


class RankRun(_Run):
    """A training run seen from one DDP rank: rank 0 keeps every side effect, the others none."""

    def __init__(self, config: TrainConfig, resume: bool, rank: RankInfo) -> None:
        self.rank = rank
        self.primary = rank.primary
        super().__init__(config, resume)
        if not self.primary:
            self.validator = None
        local = config.batch // rank.world
        self.shard = slice(rank.rank * local, (rank.rank + 1) * local)
        self.optimizer.register_step_post_hook(BatchNormMerge(self.model, local // config.micro_batch, rank))
        self.reduce_loss = self._mean_over_ranks

    def choose_device(self) -> torch.device:
        """The ranks compute on CPU cores (gloo): ``auto`` means the CPU here (:func:`ddp_config`)."""
        return choose_device("cpu")

    def _open(self, resume: bool, replace_partial: bool = False) -> Checkpoint | None:
        if self.primary:
            return super()._open(resume, replace_partial)
        self.log = _NoLog()
        return read_checkpoint(self.last_path) if resume else None

    def _mean_over_ranks(self, loss: float) -> float:
        value = torch.tensor([loss], dtype=torch.float64)
        dist.all_reduce(value)
        return float(value) / self.rank.world

    def network(self) -> nn.Module:
        from torch.nn.parallel import DistributedDataParallel as DDP

        # Buffers (BatchNorm statistics) are merged after each step, not broadcast before each forward.
        no_sync = ({"forward_sync_buffers": False} if "forward_sync_buffers" in inspect.signature(DDP).parameters
                   else {"broadcast_buffers": False})
        return DDP(self.model, **no_sync)

    def batch_source(self) -> BatchSource:
        return ShardSource(self.pairs, self.config, self.shard, self.device)

    def save(self, path: Path) -> None:
        if self.primary:
            super().save(path)
        elif path == self.last_path:
            self.saved_step = self.step


def _agree_started(rank: RankInfo, error: BaseException | None) -> None:
    """All ranks learn whether every rank built its run; the ones that did stop with one line."""
    flag = torch.tensor([0 if error else 1], dtype=torch.int32)
    dist.all_reduce(flag, op=dist.ReduceOp.MIN)
    if error is not None:
        raise error
    if int(flag) == 0:
        raise TrainingError(f"rank {rank.rank}: stopping, another rank could not start the run (see its error)")


def _stop_with_launcher() -> None:
    """Linux: have the kernel send SIGTERM when the launching torchrun agent dies (a ``kill -9``
    of ``train --nproc`` would otherwise leave the ranks running on their own)."""
    parent = os.getppid()
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the ranks then stop at the next lost collective
        return
    if os.getppid() != parent:  # the agent died before the call
        os.kill(os.getpid(), signal.SIGTERM)


def train_distributed(config: TrainConfig, rank: RankInfo, resume: bool = False,
                      progress: ProgressFactory | None = None, resume_hint: str | None = None) -> TrainResult:
    """Train ``config`` as rank ``rank.rank`` of ``rank.world`` (under torchrun); see the module doc.

    ``config`` is the single-process config (``ddp_config`` is applied here); ``progress`` is used
    on rank 0 only. Raises what :func:`training.train.train` raises, and :class:`TrainingError` when
    another rank is lost (the error names the last complete checkpoint and ``resume_hint``, the
    command that resumes the run).
    """
    config = ddp_config(config, rank.world, resume)
    _stop_with_launcher()
    torch.set_num_threads(choose_threads(config.threads, rank.local_world).count)
    dist.init_process_group(BACKEND, timeout=TIMEOUT)
    run: RankRun | None = None
    try:
        try:
            run = RankRun(config, resume, rank)
            error = None
        except Exception as exc:  # every rank must reach the agreement below, whatever failed
            run, error = None, exc
        _agree_started(rank, error)
        try:
            result = run_training(run, progress if rank.primary else None)
            dist.barrier()  # no rank tears the group down while another still uses it
            return result
        except RuntimeError as exc:  # gloo: "Connection closed by peer" etc.
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise TrainingError(f"rank {rank.rank} lost contact with the other ranks at step {run.step} "
                                f"({first[:200]}); {last_checkpoint(Path(config.out), resume_hint)}") from None
    finally:
        # The DDP wrapper's reducer holds the process group and the run sits in reference cycles
        # (bound hooks), so without this the group would be torn down by the garbage collector,
        # possibly at interpreter exit: a rank once aborted there after a complete run ("terminate
        # called without an active exception", CI). Free both now, then leave the group.
        del run
        gc.collect()
        dist.destroy_process_group()


def last_checkpoint(out: Path, resume_hint: str | None = None) -> str:
    """One phrase naming the run's last complete checkpoint and the command that continues it."""
    try:
        step = read_checkpoint(out / "last.ckpt").header["step"]
    except CheckpointError:
        return f"no complete checkpoint in {out} yet"
    how = f"resume with: {resume_hint}" if resume_hint else "resume with --out and --resume"
    return f"the last complete checkpoint is {out / 'last.ckpt'} (step {step}); {how}"


def _without_nproc(argv: Sequence[str]) -> list[str]:
    """``argv`` without ``--nproc N`` / ``--nproc=N`` (the ranks learn their number from torchrun)."""
    out: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--nproc":
            skip = True
        elif not arg.startswith("--nproc="):
            out.append(arg)
    return out


@contextmanager
def _environment(name: str, value: str) -> Iterator[None]:
    """``os.environ[name] = value`` for the block (the ranks inherit it), restored afterwards."""
    before = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = before


def launch(nproc: int, argv: Sequence[str], out: Path, threads: int | None = None,
           resume_hint: str | None = None, log: Callable[[str], None] = lambda s: None) -> None:
    """Run ``python -m training.cli ARGV`` on ``nproc`` local ranks through torchrun's launcher.

    ``threads`` is ``--threads``; the ranks' thread count (:func:`choose_threads`) is reported
    through ``log`` and passed to them as ``OMP_NUM_THREADS`` (an explicit one is kept). Raises
    :class:`TrainingError` naming the first rank that failed (torchrun then stopped the others),
    the last complete checkpoint in ``out`` and ``resume_hint``, the command that resumes it.
    """
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import parse_args, run

    choice = choose_threads(threads, nproc)
    log(f"{nproc} ranks, {choice}")
    logging.getLogger("torch.distributed.elastic").setLevel(logging.CRITICAL)  # we report failures
    args = parse_args(["--standalone", f"--nproc-per-node={nproc}", "--max-restarts=0", "-m", "training.cli"])
    args.training_script_args = _without_nproc(argv)  # set here: torchrun's parser would read them
    try:
        # an OMP_NUM_THREADS already set is the user's (kept); torchrun would otherwise set 1 (with a banner)
        with _environment("OMP_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", str(choice.count))):
            run(args)
    except ChildFailedError as exc:
        rank, failure = exc.get_first_failure()
        how = (f"was killed by {failure.signal_name()}" if failure.exitcode < 0
               else f"exited with code {failure.exitcode}")
        raise TrainingError(f"rank {rank} (pid {failure.pid}) {how}; all {nproc} ranks were stopped; "
                            f"{last_checkpoint(out, resume_hint)}") from None
