"""The training loop: data in RAM, guarded Adam steps, validation, logs, atomic checkpoints.

A run lives in one folder (``TrainConfig.out``, created with its parents): ``train_config.json``,
``log.jsonl``, ``last.ckpt`` (every ``ckpt_every`` steps and at the end), ``best.ckpt`` (best
validation PSNR) and ``curves.png``. The batch of step ``s`` is drawn from
``numpy.random.default_rng([seed, s])`` (:mod:`training.batches`), so a resumed run sees exactly the
batches an uninterrupted one would; model, BatchNorm statistics, Adam state, LR schedule (a function
of the step) and the torch RNG come from ``last.ckpt``. The run computes on the device its config
names (:func:`model.device.choose_device`); every checkpoint carries the card's ``meta``
(:mod:`training.provenance`: hours, hardware, the data's pixel filter, the recipe).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from imaging.atomic_io import TMP_PREFIX, write_text_atomic
from imaging.errors import CheckpointError, ConfigError, DenoiserError, TrainingError
from imaging.hashing import file_sha256
from console.progress import ProgressBar, ProgressFactory
from model.architectures import build_model
from model.checkpoint import (Checkpoint, model_from_checkpoint, read_checkpoint, restore_optimizer,
                              restore_rng, save_checkpoint)
from model.device import choose_device
from training.batches import BatchSource, auto_workers
from training.dataset import ValImage, load_training_pairs, load_val_images
from model.grow import grow_model
from model.shapes import check_fits_in_memory
from training.patches import TrainingPair
from training.provenance import card_meta, data_pixel_filter, hardware, inherited
from training.run_log import RunLog, plot_curves
from training.start_checks import (RUN_FILES, DataPlan, check_patch, check_run_folder, plan_data,
                                   validation_note)
from training.step import NonFiniteGuard, train_step
from training.train_config import RESUMABLE_OVERRIDES, TrainConfig
from model.transfer import get_transfer
from training.validate import Validator

DATASET_ID_STRIDE = 1_000_000  # scene ids of the k-th dataset of a run are its indices + k * this

# TrainConfig fields that the configs of the first runs lack, with the values those runs trained with
# (the defaults differ)
_UNRECORDED = {"lr_warmup": 0, "lr_cosine_steps": 0, "lr_final": 0.01}


@dataclass
class TrainResult:
    """Outcome of :func:`train`: final step, best validation PSNR (dB), skipped steps, and why it
    stopped before ``steps`` (``"cpu budget"``, ``"time"``; None: it reached them)."""

    run_dir: Path
    step: int
    best_psnr: float | None
    skipped_steps: int
    stopped: str | None = None


@dataclass
class _LossMeter:
    """Losses since the last train log line (kept in checkpoints so the curve continues)."""

    total: float = 0.0
    count: int = 0
    skipped: int = 0
    started: float = field(default_factory=time.perf_counter)
    paused: float = 0.0  # seconds spent validating/checkpointing, left out of patches/s
    started_cpu: float = field(default_factory=time.process_time)
    paused_cpu: float = 0.0  # process CPU seconds spent validating/checkpointing


def build_optimizer(model: torch.nn.Module, config: TrainConfig) -> torch.optim.Adam:
    """Adam at the configured base LR (the schedule sets the LR of each step)."""
    return torch.optim.Adam(model.parameters(), lr=config.lr, fused=True if config.fused_adam else None)


def resume_config(out: str | Path, overrides: dict[str, Any]) -> TrainConfig:
    """The config of the run in ``out`` (from its last.ckpt) with the allowed ``overrides``."""
    ckpt = read_checkpoint(Path(out) / "last.ckpt")
    saved = ckpt.header.get("train_config")
    if not isinstance(saved, dict):
        raise ConfigError(f"{ckpt.path}: holds no training config to resume from")
    # a saved config without these fields trained with these values
    base = TrainConfig.from_dict({**_UNRECORDED, **saved})
    changed = sorted(k for k, v in overrides.items() if k not in RESUMABLE_OVERRIDES and getattr(base, k, v) != v)
    if changed:
        raise ConfigError(f"cannot change {', '.join(changed)} on --resume (start a new run instead)")
    return dataclasses.replace(base, out=str(out), **overrides)


def _remove_temporaries(folder: Path) -> None:
    """Delete half-written files (``.tmp-*``) that a killed run left; never a finished file."""
    for leftover in folder.glob(f"{TMP_PREFIX}*"):
        leftover.unlink(missing_ok=True)


class _Run:
    """State of one training run; :func:`train` drives it."""

    primary = True  # writes the run's files (under DDP only rank 0 does: training.distributed)
    reduce_loss: Callable[[float], float] | None = None  # chunk loss -> the value all DDP ranks agree on

    def __init__(self, config: TrainConfig, resume: bool, recipe: dict[str, Any] | None = None,
                 log: Callable[[str], None] | None = None, replace_partial: bool = False) -> None:
        self.config = config
        self.device = self.choose_device()
        self.recipe = recipe  # {"name", "sha256", "stage"} of the recipe that runs this, for the card
        self.say = log or (lambda line: None)  # one line for the console (validation scores)
        self.dir = Path(config.out)
        self.log = RunLog(self.dir / "log.jsonl")
        self.last_path, self.best_path = self.dir / "last.ckpt", self.dir / "best.ckpt"
        ckpt = self._open(resume, replace_partial)
        plan = plan_data(config, ckpt)
        check_patch(config, plan)
        self.val_label = "the training scenes" if plan.val_on_train else "the held-out scenes"
        self.data_config, self.pairs, val_images = self._load_data(plan)
        self.validator = Validator(val_images, config.oidn) if val_images and config.val_every else None
        self.model, self.optimizer = self._build(ckpt)
        # the loss's map of output and reference (None: compare in the network's transfer space)
        self.loss_space = get_transfer(config.model.transfer).display if config.loss_space == "display" else None
        extra = ckpt.header.get("extra", {}) if ckpt else {}
        self.step = int(ckpt.header["step"]) if ckpt else 0
        try:
            self.best_psnr: float | None = None if extra.get("best_psnr") is None else float(extra["best_psnr"])
            self.guard = NonFiniteGuard(config.max_bad_steps, int(extra.get("skipped_total", 0)))
            meter = extra.get("meter", {})
            self.meter = _LossMeter(float(meter.get("total", 0.0)), int(meter.get("count", 0)),
                                    int(meter.get("skipped", 0)))
            self.train_s = float(extra.get("train_s", 0.0))  # optimisation seconds so far, all sittings
            self.cpu_s = float(extra.get("cpu_s", 0.0))  # process CPU seconds of optimisation, all sittings
            self.gpu_s = float(extra.get("gpu_s", 0.0))  # optimisation seconds on a GPU, all sittings
        except (TypeError, ValueError, AttributeError, OverflowError) as exc:
            raise CheckpointError(f"{ckpt.path}: corrupt training state in checkpoint ({exc})") from None
        self.pixel_filter = data_pixel_filter(self.data_config)
        self.machine = hardware(self.device)
        # identity of the --init-from weights (the file at that path may be replaced later)
        self.init_from: dict[str, Any] | None = extra.get("init_from") if ckpt else (
            {"path": config.init_from, "sha256": file_sha256(Path(config.init_from))} if config.init_from else None)
        # hours and hardware of the chain of warm starts before this run (its card adds them up)
        self.inherited: dict[str, Any] = extra.get("inherited") if ckpt and "inherited" in extra else \
            inherited(self.source_header)
        self.saved_step: int | None = self.step if ckpt else None
        if ckpt:
            self.log.truncate_after(self.step)
        self.created: list[Path] = [] if resume or not self.primary else self._create()
        note = validation_note(config, plan)
        if note:
            self.say(note)

    def choose_device(self) -> torch.device:
        """Where this run computes: the config's ``device`` (:func:`model.device.choose_device`)."""
        return choose_device(self.config.device)

    def _load_data(self, plan: DataPlan) -> tuple[dict[str, Any], list[TrainingPair], list[ValImage]]:
        """The primary dataset's config (the extra datasets' configs under ``extra_data``), the
        training pairs and validation images of every dataset of ``plan`` (scene ids of the k-th
        dataset offset by k * :data:`DATASET_ID_STRIDE`, so they stay distinct)."""
        config, model = self.config, self.config.model
        pairs: list[TrainingPair] = []
        val_images: list[ValImage] = []
        for k, (root, train, val) in enumerate(plan.datasets):
            pairs += load_training_pairs(root, train, get_transfer(model.transfer), model.aux_inputs,
                                         converged=config.converged_pairs, noise=model.noise_input,
                                         index_offset=k * DATASET_ID_STRIDE, noise_radius=model.noise_radius,
                                         normals=model.aux_normals)
            if config.val_every:
                val_images += load_val_images(root, val, model.aux_inputs, model.noise_input,
                                              index_offset=k * DATASET_ID_STRIDE, normals=model.aux_normals)
        return plan.data_config, pairs, val_images

    def _open(self, resume: bool, replace_partial: bool = False) -> Checkpoint | None:
        """The checkpoint a resume continues (None for a new run, whose folder is only checked:
        :func:`training.start_checks.check_run_folder`; :meth:`_create` makes it)."""
        if resume:
            ckpt = read_checkpoint(self.last_path)
            _remove_temporaries(self.dir)
            return ckpt
        check_run_folder(self.dir, resume, replace_partial)
        return None

    def _create(self) -> list[Path]:
        """Make a new run's folder, once everything it needs has been read and built; returns the
        folders this made (the folder and any missing parents, deepest first) and deletes the files
        of an earlier start that left no checkpoint (``replace_partial``: the run folder check let
        them through)."""
        created = [p for p in (self.dir, *self.dir.parents) if not p.exists()]
        self.dir.mkdir(parents=True, exist_ok=True)
        for name in RUN_FILES:
            (self.dir / name).unlink(missing_ok=True)
        _remove_temporaries(self.dir)
        return created

    def undo_start(self) -> None:
        """Remove what a new run that never saved a checkpoint wrote: its files, and the folders it
        made where they are empty now (a failed start leaves nothing behind; a run with a
        checkpoint, or one resumed, is kept)."""
        if self.saved_step is not None or not self.primary:
            return
        for name in RUN_FILES:
            (self.dir / name).unlink(missing_ok=True)
        _remove_temporaries(self.dir)
        for folder in self.created:
            with contextlib.suppress(OSError):  # not empty: something else is in it now
                folder.rmdir()

    def _build(self, ckpt: Checkpoint | None) -> tuple[torch.nn.Module, torch.optim.Adam]:
        self.source_header: dict[str, Any] | None = None  # the warm start's header (its card's hours)
        if ckpt is None:
            check_fits_in_memory(self.config.model)
            torch.manual_seed(self.config.seed)
            model = build_model(self.config.model)
            if self.config.init_from:
                source_ckpt = read_checkpoint(self.config.init_from)
                self.source_header = source_ckpt.header
                source = model_from_checkpoint(source_ckpt)
                try:
                    grow_model(model, source)
                except ConfigError as exc:
                    raise ConfigError(f"{self.config.init_from}: {exc}") from None
        else:
            model = model_from_checkpoint(ckpt)
            if model.config != self.config.model:
                raise ConfigError(f"{ckpt.path}: model config differs from the run's train config")
        model = model.to(self.device, memory_format=torch.channels_last if self.config.channels_last
                         else torch.preserve_format)
        model.train()
        optimizer = build_optimizer(model, self.config)
        if ckpt is not None:
            restore_optimizer(ckpt, optimizer)
            restore_rng(ckpt)
        return model, optimizer

    def network(self) -> torch.nn.Module:
        """The module the steps run: the model (compiled with ``compile``)."""
        return _compiled(self)

    def batch_source(self) -> BatchSource:
        """Where the batch of each step comes from (prepared ahead, on the run's device)."""
        workers = self.config.workers or auto_workers(self.device)
        return BatchSource(self.pairs, self.config, self.device, workers)

    def meta(self) -> dict[str, Any]:
        """The card's ``meta`` of a checkpoint written now (:func:`training.provenance.card_meta`)."""
        return card_meta(self.inherited, self.cpu_s, self.gpu_s, self.machine, self.pixel_filter, self.recipe)

    def save(self, path: Path) -> None:
        """Checkpoint the current state to ``path`` atomically."""
        meter = {"total": self.meter.total, "count": self.meter.count, "skipped": self.meter.skipped}
        save_checkpoint(path, self.model, step=self.step, optimizer=self.optimizer,
                        train_config=self.config.to_dict(), data_config=self.data_config,
                        extra={"best_psnr": self.best_psnr, "skipped_total": self.guard.skipped_total,
                               "meter": meter, "train_s": self.train_s, "cpu_s": self.cpu_s, "gpu_s": self.gpu_s,
                               "init_from": self.init_from, "inherited": self.inherited},
                        meta=self.meta())
        if path == self.last_path:
            self.saved_step = self.step

    def cpu_used(self) -> float:
        """Process CPU seconds of optimisation so far, all sittings (what ``cpu_budget_s`` limits)."""
        m = self.meter
        return self.cpu_s + time.process_time() - m.started_cpu - m.paused_cpu

    def out_of_cpu(self) -> bool:
        """True once the run's optimisation CPU seconds reached ``cpu_budget_s`` (if set)."""
        budget = self.config.cpu_budget_s
        return bool(budget) and self.cpu_used() >= budget

    def log_train(self) -> None:
        """Write the mean loss since the last train line and reset the meter."""
        m = self.meter
        elapsed = time.perf_counter() - m.started - m.paused
        self.train_s += max(elapsed, 0.0)
        if self.device.type == "cuda":
            self.gpu_s += max(elapsed, 0.0)
        self.cpu_s += max(time.process_time() - m.started_cpu - m.paused_cpu, 0.0)
        self.log.append({"type": "train", "step": self.step, "loss": m.total / m.count if m.count else None,
                         "lr": self.config.lr_at(self.step - 1),
                         "skipped": m.skipped, "skipped_total": self.guard.skipped_total,
                         "train_s": self.train_s, "cpu_s": self.cpu_s,
                         "patches_per_s": (m.count + m.skipped) * self.config.batch / elapsed
                         if elapsed > 0 else None})
        self.meter = _LossMeter()

    def validate(self) -> dict[str, Any] | None:
        """Validate, log, and write best.ckpt on a new best PSNR."""
        if self.validator is None:
            return None
        result = self.validator.run(self.model, self.config.val_tile)
        self.log.append({"type": "val", "step": self.step, **result})
        better = result["psnr"] is not None and (self.best_psnr is None or result["psnr"] > self.best_psnr)
        if better:
            self.best_psnr = result["psnr"]
            self.save(self.best_path)
        score = "n/a" if result["psnr"] is None else f"{result['psnr']:.2f} dB"
        best = "the best so far" if better else \
            ("best n/a" if self.best_psnr is None else f"best {self.best_psnr:.2f} dB")
        yardsticks = [f"{name} {result[key]:.2f}" for name, key in (("noisy", "noisy_psnr"), ("OIDN", "oidn_psnr"))
                      if result.get(key) is not None]
        self.say(f"step {self.step}: validation PSNR {score} on {self.val_label} ({result['images']} images; "
                 f"{', '.join([*yardsticks, best])})")
        return result


def _one_step(run: _Run, net: torch.nn.Module, source: BatchSource, bar: ProgressBar | None) -> None:
    config = run.config
    noisy, ref = source.get(run.step)
    lr = config.lr_at(run.step)
    result = train_step(net, run.optimizer, noisy, ref, step=run.step, lr=lr, guard=run.guard,
                        grad_clip=config.grad_clip, bf16=config.bf16, micro_batch=config.micro_batch,
                        reduce_loss=run.reduce_loss, gradient_weight=config.gradient_weight,
                        log_eps=config.log_loss_eps, ms_ssim_weight=config.ms_ssim_weight,
                        loss_norm=config.loss_norm, loss_space=run.loss_space)
    run.step += 1
    if result.skipped:
        run.meter.skipped += 1
    else:
        run.meter.total += result.loss
        run.meter.count += 1
    if run.step % config.log_every == 0 or run.step == config.steps:
        run.log_train()
    paused, paused_cpu = time.perf_counter(), time.process_time()
    if config.val_every and (run.step % config.val_every == 0 or run.step == config.steps):
        run.validate()
    if run.step % config.ckpt_every == 0 or run.step == config.steps:
        run.save(run.last_path)
    run.meter.paused += time.perf_counter() - paused
    run.meter.paused_cpu += time.process_time() - paused_cpu
    if bar is not None:
        bar.update(1)
        bar.set_postfix_str(f"loss={result.loss:.4g}, lr={lr:.3g}", refresh=False)


def _compiled(run: _Run) -> torch.nn.Module:
    if not run.config.compile:
        return run.model
    return torch.compile(run.model)


def train(config: TrainConfig, resume: bool = False, progress: ProgressFactory | None = None,
          minutes: float | None = None, recipe: dict[str, Any] | None = None,
          log: Callable[[str], None] | None = None, replace_partial: bool = False) -> TrainResult:
    """Train (or, with ``resume``, continue) the run described by ``config`` up to ``config.steps``.

    ``minutes``: stop this sitting after that many minutes of wall time (validated and saved, so
    ``--resume`` continues it); ``recipe``: {"name", "sha256", "stage"} written into every
    checkpoint's card; ``log``: gets the start's line about its validation
    (:func:`training.start_checks.validation_note`) and each validation's score, one line each;
    ``replace_partial``: the folder's files of a start that left no checkpoint may be replaced
    (:func:`training.start_checks.check_run_folder`). Every check runs before the run's folder is
    made, and a new run that stops before its first checkpoint (an error, or Ctrl-C) removes what
    it wrote. Raises :class:`DatasetError`, :class:`ConfigError` (also for a folder holding
    something else), :class:`CheckpointError` or :class:`TrainingError` (NaN/Inf for
    ``max_bad_steps`` steps in a row). A KeyboardInterrupt propagates without saving (a step cut
    in half is no state to resume from): ``--resume`` continues from the last periodic
    last.ckpt. With ``val_every=0`` there is no validation and no best.ckpt.
    """
    if config.threads:
        torch.set_num_threads(config.threads)
    deadline = None if minutes is None else time.monotonic() + 60.0 * minutes
    run = _Run(config, resume, recipe, log, replace_partial)
    try:
        return run_training(run, progress, deadline)
    except BaseException:
        run.undo_start()
        raise


class _Forecast:
    """Where this sitting is expected to stop: ``steps``, or sooner where the wall-clock deadline or
    the CPU budget comes first at the pace of its steps so far. It sets the progress bar's total
    (at most once a second), so that the bar's estimate of the time left follows the limit that
    will stop the run, and names that limit in the bar's description."""

    def __init__(self, run: _Run, deadline: float | None) -> None:
        self.run, self.deadline = run, deadline
        self.step0, self.wall0, self.cpu0 = run.step, time.monotonic(), run.cpu_used()
        self.shown = self.wall0
        self.reason: str | None = None

    def stop_step(self) -> tuple[int, str | None]:
        """(the step expected to be the last, the limit that stops there: None for ``steps``)."""
        run, now = self.run, time.monotonic()
        done = run.step - self.step0
        last, reason = run.config.steps, None
        if done <= 0:
            return last, reason
        if self.deadline is not None:
            at = run.step + math.ceil(max(self.deadline - now, 0.0) / ((now - self.wall0) / done))
            if at < last:
                last, reason = at, "time limit"
        budget, used = run.config.cpu_budget_s, run.cpu_used()
        if budget and used > self.cpu0:
            at = run.step + math.ceil(max(budget - used, 0.0) / ((used - self.cpu0) / done))
            if at < last:
                last, reason = at, "cpu budget"
        return last, reason

    def show(self, bar: ProgressBar) -> None:
        """Revise ``bar``'s total (and description) to :meth:`stop_step`, while the run goes on (at
        once where the run has reached the total)."""
        now = time.monotonic()
        if now - self.shown < 1.0 and self.run.step < bar.total:
            return
        self.shown = now
        last, reason = self.stop_step()
        if reason != self.reason:
            self.reason = reason
            bar.set_description(reason or "", refresh=False)
        if last != bar.total:
            bar.total = last
            bar.refresh()

    def finish(self, bar: ProgressBar) -> None:
        """The run stopped at its limit: the bar's total is the step it reached."""
        if self.reason is not None and bar.total != self.run.step:
            bar.total = self.run.step
            bar.refresh()


def _stop_reason(run: _Run, deadline: float | None) -> str | None:
    if run.out_of_cpu():
        return "cpu budget"
    if deadline is not None and time.monotonic() >= deadline:
        return "time"
    return None


def run_training(run: _Run, progress: ProgressFactory | None = None, deadline: float | None = None) -> TrainResult:
    """Step ``run`` up to its config's ``steps`` (or its CPU budget, or the monotonic-clock
    ``deadline``): the loop of :func:`train`, shared with DDP."""
    config = run.config
    if run.primary:
        write_text_atomic(run.dir / "train_config.json", json.dumps(config.to_dict(), indent=2) + "\n")
    net = run.network()
    source = run.batch_source()
    bar = progress(config.steps, run.step) if progress is not None else None
    try:
        if run.step < config.steps and config.compile:
            try:
                _one_step(run, net, source, bar)
            except DenoiserError:  # ours (bad data, config...), not the compiler's
                raise
            except Exception as exc:  # torch.compile reports missing compilers etc. in many types
                first_line = str(exc).splitlines()[0] if str(exc) else ""
                raise TrainingError(f"torch.compile failed ({type(exc).__name__}: {first_line}); "
                                    f"train without --compile") from None
        stopped = _stop_reason(run, deadline)
        forecast = _Forecast(run, deadline) if deadline is not None or config.cpu_budget_s else None
        while run.step < config.steps and stopped is None:
            _one_step(run, net, source, bar)
            stopped = _stop_reason(run, deadline)
            if forecast is not None and bar is not None and stopped is None and run.step < config.steps:
                forecast.show(bar)
        if forecast is not None and bar is not None and stopped is not None:
            forecast.finish(bar)
        if stopped and run.meter.count + run.meter.skipped:  # stopped between log lines
            run.log_train()
            if config.val_every and run.step % config.val_every:
                run.validate()
    finally:
        source.close()
        if bar is not None:
            bar.close()
        if run.primary:
            with contextlib.suppress(OSError):  # a full disk here must not hide why the run stopped
                plot_curves(run.log.read(), run.dir / "curves.png")
    if run.saved_step != run.step:
        run.save(run.last_path)
    return TrainResult(run.dir, run.step, run.best_psnr, run.guard.skipped_total,
                       stopped if run.step < config.steps else None)
