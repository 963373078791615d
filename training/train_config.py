"""The typed training configuration, filled by ``training.cli`` and saved as JSON beside each run.

The defaults are the training of the registry's unet-m-k5-lowspp (training/recipes/unet-m-k5-lowspp.toml):
``unet-m`` with the predicted 5x5 filter, 128x128 crops, batch 8, Adam at lr 1e-3 with 100 warm-up
steps and a cosine decay over the whole run to 2% of it, 60,000 steps. Kim & Lee's schedule (lr
0.01 times 0.9 every 10,000 steps, batch 64, 28x28 crops) measured worse: lr 0.01 throws the
residual model far from the identity in its first steps (docs/experiments.md); it is still
``lr_cosine_steps 0`` with ``lr_decay``. ``grad_clip`` (off by default) clips the total L2
gradient norm; set it (e.g. 1.0) if training on very bright HDR data diverges.

``device``: ``auto`` (CUDA when present), ``cpu`` or ``cuda`` (:func:`model.device.choose_device`);
on CUDA the batches are prepared ahead by ``workers`` processes (0: as many as the cores allow, up
to 8) and copied from pinned memory, and ``bf16`` autocasts on the GPU.

Speed options — only ``bf16`` and ``micro_batch`` change what is learned:
``channels_last`` (NHWC memory layout for oneDNN convolutions), ``fused_adam`` (one fused Adam
kernel), ``prefetch`` (sample the next batch on a background thread), ``threads`` (torch intra-op
threads; 0 keeps torch's default), ``compile`` (torch.compile; needs a C++ compiler),
``bf16`` (bfloat16 autocast of the forward pass — changes numerics; measure before use),
``micro_batch`` (compute the batch in chunks with gradient accumulation: faster on small caches,
but BatchNorm then uses per-chunk statistics — "ghost batch norm" — so it changes what is learned).
Measured on the 2-core AVX2 dev machine (benchmarks/train_throughput.py, the paper's k=12 L=20,
batch 64): naive NCHW 21-25 patches/s; channels_last + fused Adam (the defaults) x1.2-1.3;
+ compile x1.2-1.3 (float error like naive NCHW, ~10x below eager channels_last, whose BatchNorm
variance is computed less precisely: gradient error vs float64 1.3e-3 instead of 1.7e-4);
micro_batch 16/32 x1.9-2.2; bf16 x0.25 (AVX2 has no bf16 arithmetic); 1 thread x0.8.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from imaging.errors import ConfigError
from model.config import DEFAULT_TRAIN_MODEL, ModelConfig
from model.device import check_device_name
from training.loss import NORMS as LOSS_NORMS, SSIM_WINDOW
from training.patches import PatchConfig
from training.step import learning_rate

LOSS_SPACES = ("transfer", "display")  # TrainConfig.loss_space

# Fields that may differ on --resume without changing what is being trained.
RESUMABLE_OVERRIDES = frozenset({
    "data", "steps", "log_every", "val_every", "ckpt_every", "max_bad_steps", "threads",
    "channels_last", "fused_adam", "prefetch", "compile", "oidn", "val_tile", "progress", "cpu_budget_s",
    "device", "workers",  # where the same computation runs
    "max_scenes", "extra_data",  # more scenes (a dataset grew, another joined): resuming on them is intended
})


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs besides the data itself. Paths are strings (JSON-ready).

    ``steps``: total optimiser steps of the run (a resumed run continues up to it); intervals
    (``log_every``, ``val_every``, ``ckpt_every``) are in steps, 0 disables validation.
    ``lr_warmup``: steps over which the LR ramps up linearly from lr/lr_warmup (0: none).
    ``init_from``: checkpoint of the same model, or of a densenet with other depth (same growth,
    width, transfer, output; deepened, or its first layers taken), whose weights start a new run
    (:mod:`model.grow`); the optimiser and step start afresh.
    ``lr_cosine_steps`` > 0: cosine decay of the LR to ``lr_final * lr`` over that many steps
    instead of the step schedule (``lr_decay``/``lr_decay_every`` then unused); -1 (the default):
    over ``steps``, fixed when the config is made (a resumed run given more steps keeps its cosine);
    0: the step schedule.
    ``noise_dropout``: for a model with ``noise_input``, the share of patches whose noise
    channels are zeroed (marked unknown), so that it also works on images without a variance.
    ``gradient_weight``: share of the gradient L1 in the loss (the paper's 0.1; 0: plain L1).
    ``log_loss_eps`` > 0: minimise the mean over patches of log(patch loss + eps) instead of the
    mean loss (:mod:`training.loss`: every spp level counts per relative gain, as mean PSNR does).
    ``ms_ssim_weight`` > 0: share of 1 - MS-SSIM in the loss (:mod:`training.loss`; Zhao et al.'s and
    OIDN's mix: 0.84 with ``gradient_weight`` 0); needs patches of at least 11 px.
    ``loss_norm``: "l1" (the paper's) or "l2" (squared differences in both loss terms: each pixel's
    conditional mean, which PSNR rewards, instead of its median; :mod:`training.loss`).
    ``loss_space``: "transfer" (the network's own space, the paper's) or "display" (the metrics'
    tonemap, :meth:`model.transfer.TransferFunction.display`: the space PSNR is measured in).
    ``max_scenes`` > 0: train and validate on the scenes with index below it only (the dataset
    may hold more, e.g. while it is still being generated), so a run's data is fixed; it applies
    to every dataset of the run. ``extra_data``: further dataset folders trained and validated
    on beside ``data`` (e.g. a family rendered on its own); checked like ``data``.
    ``cpu_budget_s`` > 0: stop (validate and save) once the optimisation has used this many
    process CPU seconds over all sittings — runs of different cost compared at equal CPU time.
    ``converged_pairs``: besides each scene's noisy renders, train on (reference, reference) — a
    converged input must come out unchanged (off in the paper; see docs/training.md).
    ``max_spp`` > 0: train and validate on the renders of at most that many spp only (a specialist
    for noisy input, e.g. an ensemble member; the best checkpoint is chosen on those levels too).
    ``min_spp`` > 0: likewise, the renders of at least that many spp only (a specialist for clean
    input; converged pairs, when on, are kept).
    """

    data: str
    out: str
    model: ModelConfig = field(default_factory=lambda: DEFAULT_TRAIN_MODEL)
    patch: PatchConfig = field(default_factory=lambda: PatchConfig(size=128))
    steps: int = 60_000
    batch: int = 8
    lr: float = 1e-3
    lr_decay: float = 0.9
    lr_decay_every: int = 10_000
    lr_warmup: int = 100
    lr_cosine_steps: int = -1
    lr_final: float = 0.02
    noise_dropout: float = 0.25
    gradient_weight: float = 0.1
    log_loss_eps: float = 0.0
    ms_ssim_weight: float = 0.0
    loss_norm: str = "l1"
    loss_space: str = "transfer"
    max_scenes: int = 0
    max_spp: int = 0
    min_spp: int = 0
    extra_data: tuple[str, ...] = ()
    cpu_budget_s: float = 0.0
    grad_clip: float | None = None
    init_from: str | None = None
    converged_pairs: bool = False
    micro_batch: int | None = None
    seed: int = 0
    log_every: int = 100
    val_every: int = 2_000
    ckpt_every: int = 1_000
    max_bad_steps: int = 20
    threads: int = 0
    channels_last: bool = True
    fused_adam: bool = True
    prefetch: bool = True
    compile: bool = False
    bf16: bool = False
    oidn: bool = True
    val_tile: int = 256
    progress: bool = True
    device: str = "auto"
    workers: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.extra_data, (list, tuple)) and all(isinstance(d, str) and d for d in self.extra_data):
            object.__setattr__(self, "extra_data", tuple(self.extra_data))
        else:
            raise ConfigError(f"extra_data must be a list of dataset folders, got {self.extra_data!r}")
        for name in ("steps", "batch", "lr_decay_every", "log_every", "ckpt_every", "max_bad_steps", "val_tile"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"{name} must be a positive integer, got {value!r}")
        if self.lr_cosine_steps == -1 and isinstance(self.steps, int) and self.steps >= 1:
            object.__setattr__(self, "lr_cosine_steps", self.steps)
        check_device_name(self.device)
        for name in ("val_every", "threads", "seed", "lr_warmup", "lr_cosine_steps", "max_scenes",
                     "max_spp", "min_spp", "workers"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ConfigError(f"{name} must be an integer >= 0, got {value!r}")
        if self.max_spp and self.min_spp > self.max_spp:
            raise ConfigError(f"min_spp ({self.min_spp}) must not exceed max_spp ({self.max_spp})")
        if not (isinstance(self.lr, (int, float)) and self.lr > 0):
            raise ConfigError(f"lr must be > 0, got {self.lr!r}")
        if not (isinstance(self.lr_decay, (int, float)) and 0 < self.lr_decay <= 1):
            raise ConfigError(f"lr_decay must be in (0, 1], got {self.lr_decay!r}")
        if not (isinstance(self.lr_final, (int, float)) and 0 <= self.lr_final <= 1):
            raise ConfigError(f"lr_final must be in [0, 1], got {self.lr_final!r}")
        if not (isinstance(self.cpu_budget_s, (int, float)) and self.cpu_budget_s >= 0):
            raise ConfigError(f"cpu_budget_s must be >= 0, got {self.cpu_budget_s!r}")
        if not (isinstance(self.gradient_weight, (int, float)) and 0 <= self.gradient_weight <= 1):
            raise ConfigError(f"gradient_weight must be in [0, 1], got {self.gradient_weight!r}")
        if not (isinstance(self.log_loss_eps, (int, float)) and 0 <= self.log_loss_eps <= 1):
            raise ConfigError(f"log_loss_eps must be in [0, 1], got {self.log_loss_eps!r}")
        if not (isinstance(self.ms_ssim_weight, (int, float)) and 0 <= self.ms_ssim_weight <= 1):
            raise ConfigError(f"ms_ssim_weight must be in [0, 1], got {self.ms_ssim_weight!r}")
        if self.loss_norm not in LOSS_NORMS:
            raise ConfigError(f"loss_norm must be one of {', '.join(LOSS_NORMS)}, got {self.loss_norm!r}")
        if self.loss_space not in LOSS_SPACES:
            raise ConfigError(f"loss_space must be one of {', '.join(LOSS_SPACES)}, got {self.loss_space!r}")
        if self.ms_ssim_weight > 0 and self.patch.size < SSIM_WINDOW:
            raise ConfigError(f"ms_ssim_weight needs patches of at least {SSIM_WINDOW} px (the SSIM window), "
                              f"got {self.patch.size}")
        if not (isinstance(self.noise_dropout, (int, float)) and 0 <= self.noise_dropout <= 1):
            raise ConfigError(f"noise_dropout must be in [0, 1], got {self.noise_dropout!r}")
        if self.micro_batch is not None and not (
                isinstance(self.micro_batch, int) and 1 <= self.micro_batch <= self.batch
                and self.batch % self.micro_batch == 0):
            raise ConfigError(f"micro_batch must divide batch ({self.batch}), got {self.micro_batch!r}")
        if not isinstance(self.converged_pairs, bool):
            raise ConfigError(f"converged_pairs must be true or false, got {self.converged_pairs!r}")
        if self.init_from is not None and not (isinstance(self.init_from, str) and self.init_from):
            raise ConfigError(f"init_from must be a checkpoint path or null, got {self.init_from!r}")
        if self.grad_clip is not None and not (isinstance(self.grad_clip, (int, float)) and self.grad_clip > 0):
            raise ConfigError(f"grad_clip must be > 0 or null, got {self.grad_clip!r}")

    def lr_at(self, step: int) -> float:
        """Learning rate of optimiser step ``step`` (from 0): decay schedule and warm-up."""
        return learning_rate(self.lr, self.lr_decay, self.lr_decay_every, step, self.lr_warmup,
                             self.lr_cosine_steps, self.lr_final)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (nested configs as dicts)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`ConfigError`."""
        if not isinstance(data, dict):
            raise ConfigError(f"train config must be a JSON object, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"unknown train config key(s): {', '.join(unknown)}")
        values = dict(data)
        for key, kind in (("model", ModelConfig), ("patch", PatchConfig)):
            if key in values and not isinstance(values[key], (dict, kind)):
                raise ConfigError(f"train config {key} must be a JSON object, got {type(values[key]).__name__}")
        if isinstance(values.get("model"), dict):
            values["model"] = ModelConfig.from_dict(values["model"])
        if isinstance(values.get("patch"), dict):
            patch_known = {f.name for f in dataclasses.fields(PatchConfig)}
            bad = sorted(set(values["patch"]) - patch_known)
            if bad:
                raise ConfigError(f"unknown patch config key(s): {', '.join(bad)}")
            values["patch"] = PatchConfig(**values["patch"])
        try:
            return cls(**values)
        except TypeError as exc:
            raise ConfigError(f"bad train config ({exc})") from None
