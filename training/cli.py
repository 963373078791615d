"""Command-line entry point ``train``: parse flags, build a :class:`TrainConfig`, call the library.

    train --recipe NAME --out DIR                  a shipped model from nothing (training/recipes/NAME.toml)
    train --recipe NAME --out DIR --data MINE --init-from MODEL --minutes M     fine-tune MODEL on your data
    train --data DIR --out RUN_DIR [--config FILE.json] [--preset flat-s|...|unet-m|unet-l] [--steps N] ...
    train --out RUN_DIR --resume [--steps N]
    train --nproc N ...     (DDP on N local processes via torchrun; or: torchrun ... -m training.cli ...)

Precedence for a new run: defaults (unet-m-k5-lowspp's training, :mod:`training.train_config`) <
``--config`` JSON (any TrainConfig fields; ``"model"`` may be a full ModelConfig object or
``{"preset": "flat-s", ...overrides}``) < flags. On ``--resume`` the config comes from
RUN_DIR/last.ckpt and only run-control flags (steps, intervals, speed options, device, data path)
may be given. ``--recipe`` runs :mod:`training.recipe_run` and takes only run control. Errors: one
line on stderr, exit 1 (2 for bad usage, 130 on Ctrl-C).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
from pathlib import Path
from typing import Any

from imaging.errors import ConfigError, DenoiserError
from imaging.json_read import parse_json
from imaging.output_paths import check_not_inputs
from console.progress import console_lines, tqdm_bars
from console.usage import OneLineParser
from model.config import ARCHS, AUX_MODES, AUX_NORMALS, AUX_PREFILTERS, PRESETS, UNET_ARCHS, ModelConfig, preset
from model.device import DEVICES
from training.distributed import RankInfo, ddp_config, launch, rank_from_env, train_distributed
from training.recipe import load_recipe, recipe_names
from training.recipe_run import RecipeRun, plan, run_recipe
from training.start_checks import RUN_FILES
from training.train import resume_config, train
from training.train_config import LOSS_NORMS, LOSS_SPACES, RESUMABLE_OVERRIDES, TrainConfig

_FLAGS = {  # argparse dest -> TrainConfig field
    "data": "data", "steps": "steps", "batch": "batch", "lr": "lr", "grad_clip": "grad_clip", "seed": "seed",
    "log_every": "log_every", "val_every": "val_every", "ckpt_every": "ckpt_every", "threads": "threads",
    "channels_last": "channels_last", "bf16": "bf16", "compile": "compile", "oidn": "oidn",
    "prefetch": "prefetch", "progress": "progress", "max_bad_steps": "max_bad_steps",
    "micro_batch": "micro_batch", "init_from": "init_from", "lr_decay": "lr_decay",
    "lr_decay_every": "lr_decay_every", "converged_pairs": "converged_pairs",
    "lr_warmup": "lr_warmup", "lr_cosine_steps": "lr_cosine_steps", "lr_final": "lr_final",
    "noise_dropout": "noise_dropout", "gradient_weight": "gradient_weight", "max_scenes": "max_scenes",
    "max_spp": "max_spp", "min_spp": "min_spp",
    "log_loss_eps": "log_loss_eps", "ms_ssim_weight": "ms_ssim_weight",
    "loss_norm": "loss_norm", "loss_space": "loss_space", "device": "device", "workers": "workers",
}
# flags a --recipe run takes (run control); the recipe sets everything else
_RECIPE_FLAGS = {"recipe", "out", "data", "extra_data", "init_from", "minutes", "cpu_minutes", "device", "threads",
                 "workers", "progress", "data_root", "dry_run"}
_DEFAULTS = TrainConfig(data="-", out="-")


def _preset_name(text: str) -> str:
    try:
        preset(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text
_MODEL_FLAGS = ("arch", "transfer", "output", "aux_inputs", "noise_input", "noise_radius", "levels", "layers",
                "growth", "init_features", "head", "kernel", "aux_mode", "aux_normals", "aux_prefilter")


def build_parser() -> argparse.ArgumentParser:
    """The ``train`` argument parser (every option defaults to None = not given)."""
    d = _DEFAULTS
    p = OneLineParser(prog="train",
                      description="Train a denoiser: a shipped model from its recipe (--recipe), a fine-tune of one "
                                  "on your data, or any network on a dataset. Without --recipe the defaults are "
                                  "the training of the U-Net every registry entry runs up to 16 spp (recipe "
                                  "unet-m-k5-lowspp: "
                                  f"unet-m with a 5x5 filter, {d.patch.size}px crops, batch {d.batch}, lr {d.lr:g} "
                                  f"with {d.lr_warmup} warm-up steps and a cosine to {d.lr_final:g} of it over the "
                                  f"run, {d.steps} steps).",
                      argument_default=None)
    p.add_argument("--recipe", metavar="NAME",
                   help=f"run a recipe from nothing (render its data, train its stages, resume after a kill): "
                        f"{', '.join(recipe_names())}, or a .toml file")
    p.add_argument("--data-root", metavar="DIR",
                   help="--recipe: where its datasets are rendered, one folder each (default data)")
    p.add_argument("--dry-run", action="store_true", default=False,
                   help="--recipe: run the start's checks and print the commands it amounts to, with what each "
                        "start will say (crops, validation); render and train nothing")
    p.add_argument("--data", help="dataset folder (dataset.json, manifest.jsonl, images/); with --recipe: train "
                                  "on it instead of the recipe's data")
    p.add_argument("--out", required=True, help="run folder (created with its parents: checkpoints, log.jsonl, "
                                                "curves.png); a new run replaces nothing there")
    p.add_argument("--config", help="JSON file with TrainConfig fields")
    p.add_argument("--resume", action="store_true", default=False, help="continue the run in --out")
    p.add_argument("--steps", type=int, help=f"total optimiser steps (default {d.steps})")
    p.add_argument("--minutes", type=float,
                   help="stop after this many minutes of wall time, saved and resumable (--resume, or the same "
                        "--recipe command)")
    p.add_argument("--device", choices=DEVICES, help="where to train: auto (default: cuda when present), cpu, cuda")
    p.add_argument("--workers", type=int,
                   help="processes preparing batches ahead (default 0: a thread on the CPU, up to 8 processes "
                        "on a GPU)")
    p.add_argument("--preset", type=_preset_name, metavar="NAME",
                   help=f"network preset: {', '.join(PRESETS)} (default: unet-m with --kernel 5)")
    p.add_argument("--arch", choices=list(ARCHS),
                   help="network family (without --preset, a flat arch starts from the paper preset's sizes)")
    p.add_argument("--levels", type=int, help="multi-scale archs: resolutions below the half-resolution stem")
    p.add_argument("--head", type=int,
                   help="multi-scale archs: channels of a full-resolution refinement head (0: none)")
    p.add_argument("--kernel", type=int,
                   help="multi-scale archs: size k (odd) of a predicted per-pixel k x k filter of the input (0: none)")
    p.add_argument("--layers", type=int, help="dense layers (flat: in the block; multi-scale: per block)")
    p.add_argument("--growth", type=int, help="growth rate k")
    p.add_argument("--width", dest="init_features", type=int, help="channels of the first conv / stem")
    p.add_argument("--noise-input", dest="noise_input", action="store_const", const=True,
                   help="also feed the render's noise (needs a dataset made with --variance)")
    p.add_argument("--no-noise-input", dest="noise_input", action="store_const", const=False,
                   help="do not feed the render's noise (overrides the preset)")
    p.add_argument("--noise-radius", type=int,
                   help="average the variance over a (2r+1)^2 window before the network (default 0: per pixel)")
    p.add_argument("--noise-dropout", type=float,
                   help="share of patches whose noise channels are hidden (default 0.25)")
    p.add_argument("--transfer", choices=["log", "pu"])
    p.add_argument("--output", choices=["residual", "direct"])
    p.add_argument("--aux", dest="aux_inputs", action="store_const", const=True, help="also feed albedo+normal")
    p.add_argument("--aux-mode", choices=AUX_MODES,
                   help="with --aux, multi-scale archs: where albedo and normal enter: stem (default: the stem and "
                        "the input skip), noskip (the stem only), levels (every encoder level's input, not the "
                        "stem), kernel (only the predicted filter's weights; needs --kernel)")
    p.add_argument("--aux-normals", choices=AUX_NORMALS,
                   help="with --aux: normals as rendered (world, default) or in the camera's frame (camera; read "
                        "from each scene's file)")
    p.add_argument("--aux-prefilter", choices=AUX_PREFILTERS,
                   help="with --aux, multi-scale archs: filter albedo and normal first (bilateral: a 5x5 joint "
                        "bilateral filter inside the network; default none)")
    p.add_argument("--batch", type=int, help=f"patches per step (default {d.batch})")
    p.add_argument("--patch", type=int, help=f"patch side in pixels (default {d.patch.size})")
    p.add_argument("--detail-crops", type=float, metavar="D",
                   help="choose crops by the reference's variation: share D of the probability goes by each "
                        "crop's standard deviation, among 4x the batch of candidates (default 0: uniform)")
    p.add_argument("--lr", type=float, help=f"Adam base learning rate (default {d.lr:g})")
    p.add_argument("--grad-clip", type=float, help="clip the gradient L2 norm to this (default off)")
    p.add_argument("--init-from", metavar="CKPT",
                   help="start from this checkpoint's weights (a file, or a registry checkpoint's name such as "
                        "unet-m-k5-lowspp; not an entry like high): the same model "
                        "(a warm start), or a densenet of other depth (deepened to the model's layers, or its "
                        "first layers); with --recipe and --data: fine-tune it on that data")
    p.add_argument("--converged-pairs", action="store_const", const=True,
                   help="also train on (reference, reference) pairs: converged input stays unchanged")
    p.add_argument("--lr-decay", type=float, help="LR factor per --lr-decay-every steps (default 0.9)")
    p.add_argument("--lr-warmup", type=int, help=f"steps of linear LR warm-up (default {d.lr_warmup})")
    p.add_argument("--lr-decay-every", type=int, help="steps per LR decay (default 10000)")
    p.add_argument("--lr-cosine-steps", type=int,
                   help="cosine LR decay over this many steps (default: over --steps; 0: the step schedule of "
                        "--lr-decay)")
    p.add_argument("--lr-final", type=float, help=f"LR at the end of the cosine, as a share of --lr ({d.lr_final:g})")
    p.add_argument("--gradient-weight", type=float,
                   help="share of the gradient L1 in the loss (default 0.1, the paper's; 0 = plain L1)")
    p.add_argument("--log-loss-eps", type=float,
                   help="minimise the mean over patches of log(patch loss + EPS) instead of the mean loss, "
                        "so clean high-spp patches count per relative gain (default 0 = off, the paper's)")
    p.add_argument("--ms-ssim-weight", type=float,
                   help="share of 1 - MS-SSIM in the loss (0.84 with --gradient-weight 0: the L1 + MS-SSIM mix "
                        "of Zhao et al. and OIDN; default 0 = off, the paper's loss)")
    p.add_argument("--loss-norm", choices=tuple(LOSS_NORMS),
                   help="per-value error of both loss terms: l1 (default, the paper's: each pixel's median) "
                        "or l2 (squared: its mean, which PSNR rewards)")
    p.add_argument("--loss-space", choices=LOSS_SPACES,
                   help="where the loss compares images: transfer (default, the network's space) or display "
                        "(the metrics' tonemap, where PSNR is measured)")
    p.add_argument("--max-scenes", type=int, help="use only the datasets' scenes with index below this")
    p.add_argument("--max-spp", type=int,
                   help="train and validate on the renders of at most this many spp only (default: all)")
    p.add_argument("--min-spp", type=int,
                   help="train and validate on the renders of at least this many spp only (default: all)")
    p.add_argument("--extra-data", action="append", metavar="DIR",
                   help="another dataset folder to train and validate on (repeatable)")
    p.add_argument("--cpu-minutes", type=float,
                   help="stop once the optimisation used this many process CPU minutes (all sittings; with "
                        "--recipe: each stage's)")
    p.add_argument("--micro-batch", type=int,
                   help="accumulate gradients over chunks of this size (faster; BatchNorm per chunk)")
    p.add_argument("--seed", type=int)
    p.add_argument("--log-every", type=int, help="steps per train-loss log line (default 100)")
    p.add_argument("--val-every", type=int, help="steps between validations, 0 = never (default 2000); data "
                                                 "without a held-out scene validates on its training scenes")
    p.add_argument("--ckpt-every", type=int, help="steps between last.ckpt saves (default 1000)")
    p.add_argument("--max-bad-steps", type=int, help="stop after this many NaN/Inf steps in a row (20)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--no-channels-last", dest="channels_last", action="store_const", const=False)
    p.add_argument("--no-prefetch", dest="prefetch", action="store_const", const=False)
    p.add_argument("--bf16", action="store_const", const=True, help="bfloat16 autocast (changes numerics)")
    p.add_argument("--compile", action="store_const", const=True, help="torch.compile the model")
    p.add_argument("--no-oidn", dest="oidn", action="store_const", const=False, help="skip the OIDN baseline")
    p.add_argument("--no-progress", dest="progress", action="store_const", const=False)
    p.add_argument("--nproc", type=int, help="train with DDP on this many local processes (launches torchrun; "
                                             "BatchNorm then works per process: see docs/cluster.md)")
    return p


def _read_json(path: str) -> dict[str, Any]:
    try:
        data = parse_json(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read config ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: config must be a JSON object")
    return data


def _model_config(base: Any, args: argparse.Namespace) -> ModelConfig:
    if isinstance(base, dict) and "preset" in base:
        base = dataclasses.asdict(preset(base["preset"], **{k: v for k, v in base.items() if k != "preset"}))
    model = ModelConfig.from_dict(base) if isinstance(base, dict) else _DEFAULTS.model
    if args.preset:
        model = PRESETS[args.preset]
    changes = {k: getattr(args, k) for k in _MODEL_FLAGS if getattr(args, k) is not None}
    if model is _DEFAULTS.model and "arch" in changes and changes["arch"] not in UNET_ARCHS:
        model = PRESETS["paper"]  # a flat network asked of the default U-Net: the paper's sizes
    if model.kernel and "kernel" not in changes and (changes.get("arch", model.arch) not in UNET_ARCHS
                                                      or changes.get("head") or changes.get("output") == "direct"):
        changes["kernel"] = 0  # the default network's filter, where the flags ask for a network without one
    return dataclasses.replace(model, **changes)


def shipped_checkpoint(name: str) -> str:
    """The checkpoint file of ``--init-from NAME``: NAME itself when it is a file, else the registry
    checkpoint of that name (``unet-m-k5-lowspp``; a retired name maps to its successor). Raises
    :class:`ConfigError` listing the registry's checkpoints (an entry such as ``fast`` is an
    ensemble: no one network to start from)."""
    from model.registry import registry

    if Path(name).is_file():
        return name
    shipped = registry()
    path = None if name in shipped.names else shipped.path_of(name)  # an entry's name means the entry
    if path is not None:
        return str(path)
    kind = "a registry entry (an ensemble), not one network" if name in shipped.names else \
        "no such checkpoint file or registry checkpoint"
    raise ConfigError(f"--init-from {name}: {kind}; the registry's checkpoints: {', '.join(shipped.checkpoints)}")


def config_from_args(args: argparse.Namespace) -> tuple[TrainConfig, bool]:
    """(TrainConfig, resume?) from parsed flags; raises :class:`ConfigError` on conflicts."""
    flags = {field: getattr(args, dest) for dest, field in _FLAGS.items() if getattr(args, dest) is not None}
    if args.init_from is not None:
        flags["init_from"] = shipped_checkpoint(args.init_from)
    if args.extra_data is not None:
        flags["extra_data"] = tuple(args.extra_data)
    if args.cpu_minutes is not None:
        flags["cpu_budget_s"] = 60.0 * args.cpu_minutes
    if args.resume:
        names = {"aux_inputs": "aux", "init_features": "width"}
        given = [f"--{names.get(k, k).replace('_', '-')}"
                 for k in ("config", "preset", "patch", "detail_crops", *_MODEL_FLAGS)
                 if getattr(args, k) is not None]
        if given:
            raise ConfigError(f"{', '.join(given)} cannot be combined with --resume "
                              f"(the run's config is in its checkpoint)")
        return resume_config(args.out, flags), True
    data = _read_json(args.config) if args.config else {}
    data.update(flags, out=args.out)
    data["model"] = _model_config(data.get("model"), args)
    if args.patch is not None:
        data["patch"] = dict(data.get("patch") or dataclasses.asdict(_DEFAULTS.patch), size=args.patch)
    if args.detail_crops is not None:
        data["patch"] = dict(data.get("patch") or dataclasses.asdict(_DEFAULTS.patch), detail=args.detail_crops)
    if "data" not in data:
        raise ConfigError("--data is required for a new run")
    return TrainConfig.from_dict(data), False


def resume_command(parser: argparse.ArgumentParser, args: argparse.Namespace, nproc: int | None = None,
                   launcher: str = "train") -> str:
    """The command that resumes the run ``args`` started: ``train --out RUN --resume`` with the
    run-control flags that were given (``--nproc``, ``--data``, ``--steps``, ``--threads``...,
    as given). What the checkpoint holds (``--config``, ``--preset``, the model, batch, LR...)
    is left out: ``--resume`` refuses or ignores it. ``nproc`` (ranks) replaces ``args.nproc``.
    """
    keep = {dest for dest, field in _FLAGS.items() if field in RESUMABLE_OVERRIDES}
    words = [*shlex.split(launcher), "--out", args.out, "--resume"]
    nproc = args.nproc if nproc is None else nproc
    if nproc is not None and nproc > 1:
        words += ["--nproc", str(nproc)]
    for action in parser._actions:  # in the parser's order, each flag as the user spells it
        value = getattr(args, action.dest, None)
        if action.dest not in keep or value is None:
            continue
        words += [action.option_strings[0]] if action.nargs == 0 else [action.option_strings[0], str(value)]
    return shlex.join(words)


def _resume_hint(parser: argparse.ArgumentParser, args: argparse.Namespace, rank: RankInfo | None) -> str:
    """:func:`resume_command` as seen by this process: the launcher, or a rank under torchrun."""
    if rank is None or rank.world == rank.local_world:  # one machine: train --nproc N does it
        return resume_command(parser, args, rank.world if rank is not None else None)
    return resume_command(parser, args, launcher="torchrun <the same torchrun options> -m training.cli")


def recipe_run_from_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> RecipeRun:
    """The :class:`RecipeRun` of a ``--recipe`` command parsed by ``parser``; raises
    :class:`ConfigError` for a flag the recipe sets (any value other than the parser's default:
    ``--seed 0`` and ``--no-oidn`` count)."""
    flag = {a.dest: a.option_strings[0] for a in parser._actions if a.option_strings}
    given = sorted(flag.get(dest, f"--{dest.replace('_', '-')}") for dest, value in vars(args).items()
                   if dest not in _RECIPE_FLAGS and value != parser.get_default(dest))
    if given:
        raise ConfigError(f"{', '.join(given)} cannot be combined with --recipe (the recipe sets it; run control "
                          "only: --data, --init-from, --minutes, --cpu-minutes, --device, --threads, --workers, "
                          "--data-root)")
    if args.extra_data and not args.data:
        raise ConfigError("--extra-data with --recipe needs --data (the recipe's own datasets are named in it)")
    control = {field: getattr(args, dest) for dest, field in _FLAGS.items()
               if dest in _RECIPE_FLAGS and dest not in ("data", "init_from") and getattr(args, dest) is not None}
    if args.cpu_minutes is not None:  # each stage's own budget (a fine-tune has one stage)
        control["cpu_budget_s"] = 60.0 * args.cpu_minutes
    return RecipeRun(out=Path(args.out), data_root=Path(args.data_root or "data"),
                     data=tuple([args.data, *(args.extra_data or [])]) if args.data else (),
                     init_from=shipped_checkpoint(args.init_from) if args.init_from else None,
                     minutes=args.minutes, control=control)


def recipe_main(parser: OneLineParser, args: argparse.Namespace) -> int:
    """``train --recipe``: run it (or print its plan with ``--dry-run``)."""
    try:
        recipe = load_recipe(args.recipe)
        run = recipe_run_from_args(parser, args)
        if args.dry_run:
            print("\n".join(plan(recipe, run)))
            return 0
        enabled = run.control.get("progress", True)
        result = run_recipe(recipe, run, tqdm_bars("step", enabled=enabled), tqdm_bars("scene", enabled=enabled),
                            log=console_lines("train: "))
    except (DenoiserError, OSError, MemoryError) as exc:
        return parser.fail(exc)
    except KeyboardInterrupt:
        return parser.interrupted("; run the same command again to resume")
    if result.stopped_in is not None:
        so_far = f"; the model so far: {result.model}" if result.model else ""
        print(f"stopped in stage {result.stopped_in} by the command's limit{so_far}; run it again (with a larger "
              "budget) to continue")
    else:
        print(f"recipe {recipe.name} done: {result.model}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point: returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.recipe is not None:
        return recipe_main(parser, args)
    if args.dry_run or args.data_root is not None:
        parser.error("--dry-run and --data-root go with --recipe")
    rank: RankInfo | None = None
    try:
        rank = rank_from_env()
        hint = _resume_hint(parser, args, rank)
        check_not_inputs([Path(args.out) / name for name in RUN_FILES], [args.config, args.init_from],
                         hint="choose another --out")
        config, resume = config_from_args(args)
        if args.nproc is not None and args.nproc < 1:
            raise ConfigError(f"--nproc must be >= 1, got {args.nproc}")
        ddp = (args.nproc or 1) > 1 or (rank is not None and rank.world > 1)
        if ddp and (config.cpu_budget_s or args.minutes is not None):
            raise ConfigError("--cpu-minutes and --minutes apply to one process only (DDP ranks would stop at "
                              "different steps)")
        if rank is None and args.nproc is not None and args.nproc > 1:
            ddp_config(config, args.nproc, resume)  # refuse before starting any process
            launch(args.nproc, sys.argv[1:] if argv is None else argv, Path(args.out), threads=config.threads,
                   resume_hint=hint, log=lambda line: print(f"train: {line}", flush=True))
            return 0
        progress = tqdm_bars("step", enabled=config.progress)
        if rank is not None and rank.world > 1:
            result = train_distributed(config, rank, resume=resume, progress=progress, resume_hint=hint)
        else:
            result = train(config, resume=resume, progress=progress, minutes=args.minutes,
                           log=console_lines("train: "))
    except (DenoiserError, OSError, MemoryError) as exc:
        tag = f"rank {rank.rank}: " if rank is not None and rank.world > 1 and "rank " not in str(exc) else ""
        return parser.fail(exc, tag)
    except KeyboardInterrupt:
        last = Path(args.out) / "last.ckpt"
        return parser.interrupted(f"; resume with: {_resume_hint(parser, args, rank)}" if last.exists() else "")
    if rank is not None and not rank.primary:
        return 0
    best = f"{result.best_psnr:.2f} dB" if result.best_psnr is not None else "n/a"
    stopped = f", stopped by the {result.stopped} (resume with: {hint})" if result.stopped else ""
    print(f"trained to step {result.step} (best val PSNR {best}, {result.skipped_steps} skipped steps{stopped}); "
          f"run in {result.run_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
