"""Command-line entry points ``render-and-denoise``, ``denoise`` and ``tradeoff``: parse, run, map errors."""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from console.clock import process_started
from console.progress import tqdm_bars
from rendering.render import DEFAULT_MAX_MEMORY_MB
from console.usage import OneLineParser, int_list, name_list, name_value, positive_float, positive_int
from denoise.flips import FLIPS
from denoise.precision import PRECISIONS
from model.device import DEVICES
from model.registry import AUTO, AUTO_TOLERANCE_DB, registry
from pipeline.evaluation import RenderSettings


DEVICE_HELP = ("where the networks run: cpu (default; the measured path), cuda (a GPU: the unfolded "
               "network in float32), auto (cuda when present)")
PRECISION_HELP = ("float format of the network: bfloat16 halves its time on CPUs with native bfloat16 "
                  "(AMX, AVX512-BF16) at a measured cost in quality (docs/experiments.md); auto: bfloat16 "
                  "for the multi-scale nets where the CPU has it natively, else float32")
FLIPS_HELP = ("average the network over 1, 2 or 4 mirrored copies of the image: 2x or 4x the "
              "network's time for about 0.1 or 0.2 dB (docs/experiments.md)")
ENERGY_HELP = ("leave the output's local means as the network made them (default: matched to the render's "
               "where they differ by more than its noise; docs/design.md)")
OVERWRITE_HELP = ("replace OUT if it exists, even when it is an input (the same file, a hard link or a symbolic "
                  "link to it; default: refused)")
OVERWRITE_FOLDER_HELP = ("write into an --out folder that holds an earlier run's files, replacing them (default: "
                         "refused before anything runs), even where one is the scene or the reference (the same "
                         "file or a link to it)")
SKIP_HELP = ("leave the 64-px cells whose noise (transfer-space standard deviation from the halves) is "
             "below NOISE out of the network; they keep the render, as the noise guard would "
             "(benchmarks/skip.py measures time and change; default: the network everywhere)")


def models_epilog() -> str:
    """The registry's names, one line each, for the end of ``--help``."""
    reg = registry()
    lines = ["models (--model NAME; --list-models prints their cards):"]
    lines += [f"  {reg.entries[n].help_line()}{' (default)' if n == reg.default else ''}" for n in reg.entries]
    lines.append(f"  {AUTO}: per render the cheapest of these within {AUTO_TOLERANCE_DB:g} dB of the best at "
                 "its spp (measured); with --time-budget the one that fits")
    lines.append("  or a checkpoint file written by `train`, or an expert spec A+B[:LO-HI] (docs/denoise.md)")
    return "\n".join(lines)


class ListModels(argparse.Action):
    """``--list-models``: print every registry entry's card and exit (no other argument needed)."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print the shipped models' cards (what runs, figures, training) and exit")

    def __call__(self, parser: argparse.ArgumentParser, *args: Any) -> None:
        reg = registry()
        print("\n\n".join(reg.card(name) for name in reg.entries))
        parser.exit()


def add_model_argument(p: argparse.ArgumentParser) -> None:
    """``--model`` and ``--list-models``, with the registry's names in the help's epilog."""
    p.add_argument("--model", metavar="NAME", help=f"a registry name ({', '.join(registry().names)}; "
                   f"default {registry().default}), a checkpoint file or an expert spec: see the list below")
    p.add_argument("--list-models", action=ListModels)
    p.epilog = models_epilog()
    p.formatter_class = argparse.RawDescriptionHelpFormatter


def print_record(parser: argparse.ArgumentParser, record: dict[str, Any], args: argparse.Namespace,
                 table: Callable[[dict[str, Any]], list[str]]) -> None:
    """A run's notes on stderr (``PROG: note: ...``, one line each), then its record as JSON
    (``--json``) or its ``table`` (unless ``--quiet``) on stdout."""
    for note in record.get("notes", []):
        print(f"{parser.prog}: note: {note}", file=sys.stderr)
    if args.json:
        print(json.dumps(record, indent=1))
    elif not args.quiet:
        print("\n".join(table(record)))


def add_render_arguments(p: argparse.ArgumentParser, reference_required: bool, guard_help: str) -> None:
    """The flags of :class:`RenderSettings` (``render-and-denoise`` and ``tradeoff``)."""
    p.add_argument("scene", help="Mitsuba 3 scene XML file")
    p.add_argument("--res", type=positive_int, nargs=2, metavar=("W", "H"), help="resolution")
    p.add_argument("--seed", type=int, default=0, help="render seed")
    p.add_argument("--param", type=name_value, action="append", default=[], metavar="NAME=VALUE",
                   help="scene $parameter")
    ref = p.add_mutually_exclusive_group(required=reference_required)
    ref.add_argument("--reference", help="reference EXR of the same size")
    ref.add_argument("--reference-spp", type=positive_int, help="render a reference at N spp")
    p.add_argument("--max-memory-mb", type=float, default=DEFAULT_MAX_MEMORY_MB,
                   help="memory bound of the render's films and of one denoiser tile")
    p.add_argument("--no-noise-guard", action="store_true", help=guard_help)
    p.add_argument("--skip-below", type=positive_float, metavar="NOISE", help=SKIP_HELP)
    p.add_argument("--precision", choices=PRECISIONS, default="auto", help=PRECISION_HELP)
    p.add_argument("--flips", type=int, choices=tuple(FLIPS), default=1, help=FLIPS_HELP)
    p.add_argument("--no-energy", action="store_true", help=ENERGY_HELP)
    p.add_argument("--device", choices=DEVICES, default="cpu", help=DEVICE_HELP)
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_FOLDER_HELP)


def render_settings(args: argparse.Namespace) -> RenderSettings:
    """The :class:`RenderSettings` of parsed :func:`add_render_arguments` flags."""
    return RenderSettings(scene=args.scene, resolution=tuple(args.res) if args.res else None, seed=args.seed,
                          params=dict(args.param), max_memory_mb=args.max_memory_mb,
                          noise_guard=not args.no_noise_guard, skip_below=args.skip_below,
                          precision=args.precision, flips=args.flips, energy=not args.no_energy,
                          device=args.device, reference=args.reference,
                          reference_spp=args.reference_spp, overwrite=args.overwrite)


def render_parser() -> OneLineParser:
    p = OneLineParser(prog="render-and-denoise",
                      description="Render a Mitsuba scene, denoise it, report metrics.")
    add_render_arguments(p, reference_required=False, guard_help=(
        "render in one piece and keep the denoiser's output as it is (default: render in two halves "
        "and keep the render where its noise does not explain the change)"))
    p.add_argument("--spp", type=positive_int, help="samples per pixel (128)")
    add_model_argument(p)
    compare = p.add_mutually_exclusive_group()
    compare.add_argument("--compare", choices=["oidn"], action="append", default=[],
                         help="denoise with OIDN too, colour-only and with albedo and normals (rendered "
                         "for it), and fail without pyoidn (default: compare whenever pyoidn is installed)")
    compare.add_argument("--no-compare", action="store_true", help="do not run OIDN")
    p.add_argument("--out", help="output folder (default: the scene's name): created, or an existing folder "
                   "holding none of this command's files (else --overwrite)")
    p.add_argument("--time-budget", type=positive_float, metavar="SECONDS",
                   help="choose spp (and, with --model auto, the model) so that the denoised image exists "
                   "within SECONDS of wall time from the command's start, on the host as it runs now: its "
                   "speed is measured first; writing the outputs comes after")
    p.add_argument("--curves", metavar="TRADEOFF_JSON",
                   help="trade curves (a tradeoff run's tradeoff.json) for --model auto")
    p.add_argument("--json", action="store_true", help="print the run's record (metrics.json) instead of the "
                   "table, and no progress")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr and no summary on stdout")
    return p


def main(argv: list[str] | None = None) -> int:
    """``render-and-denoise scene.xml [...]``."""
    parser = render_parser()
    args = parser.parse_args(argv)
    if args.time_budget is None and args.curves:
        parser.error("--curves needs --time-budget")
    if args.time_budget is not None and args.spp is not None:
        parser.error("--spp and --time-budget exclude each other (the budget chooses the spp)")
    from pipeline.run import RunConfig, run, summary_lines

    cfg = RunConfig(render=render_settings(args), out=args.out or Path(args.scene).stem, spp=args.spp or 128,
                    model=args.model,
                    compare_oidn=False if args.no_compare else ("oidn" in args.compare or None),
                    time_budget=args.time_budget, curves=args.curves)
    quiet = args.quiet or args.json
    log = (lambda s: None) if quiet else (lambda s: print(f"... {s}", file=sys.stderr))
    started = process_started() if argv is None else None  # the command's own start: the budget counts from it
    metrics, code = parser.attempt(lambda: run(cfg, log, started, None if quiet else tqdm_bars("sample", scale=True)))
    if code == 0:
        print_record(parser, metrics, args, lambda m: [
            *summary_lines(m), f"report: {Path(cfg.out) / 'report.html'} (metrics.json, comparison.png beside it)"])
    return code


def denoise_parser() -> OneLineParser:
    p = OneLineParser(prog="denoise", description="Denoise an image rendered elsewhere (EXR with any "
                      "layers or parts, PFM, Radiance HDR); the output keeps the input's layout.")
    p.add_argument("files", nargs="+", metavar="IN OUT",
                   help="input and output image (with --halves: the output only); the output's "
                   "extension picks its format: .exr (the input's layers and parts), .pfm, .hdr, or .png "
                   "(tonemapped 8-bit); any other is refused; an output that exists or is an input is refused "
                   "unless --overwrite")
    p.add_argument("--halves", nargs=2, metavar=("A", "B"),
                   help="two independent halves of one render: denoise their mean, with the noise "
                   "guard fed by their difference")
    p.add_argument("--layer", metavar="NAME", help="colour layer of a multi-layer EXR "
                   "(default: the bare R,G,B, else the one colour layer)")
    p.add_argument("--variance-layer", metavar="NAME",
                   help="layer holding the variance of the colour's estimate (default: 'variance')")
    p.add_argument("--rgb-only", action="store_true",
                   help="write a plain RGB EXR instead of the input's layers and parts")
    p.add_argument("--spp", type=positive_int,
                   help="samples per pixel of the input, for the noise guard and an ensemble's low-spp members "
                        "(default: the file's spp)")
    p.add_argument("--no-noise-guard", action="store_true",
                   help="ignore the variance: keep the denoiser's output as it is")
    add_model_argument(p)
    p.add_argument("--reference", help="reference image: print metrics, OIDN's too when pyoidn is installed "
                   "(colour-only, and with albedo and normals where the EXR has those layers)")
    p.add_argument("--max-memory-mb", type=float, default=DEFAULT_MAX_MEMORY_MB,
                   help="scratch memory bound in MB beyond the input and output images, as OIDN's "
                   "maxMemoryMB (default %(default)g)")
    p.add_argument("--skip-below", type=positive_float, metavar="NOISE", help=SKIP_HELP)
    p.add_argument("--precision", choices=PRECISIONS, default="auto", help=PRECISION_HELP)
    p.add_argument("--flips", type=int, choices=tuple(FLIPS), default=1, help=FLIPS_HELP)
    p.add_argument("--no-energy", action="store_true", help=ENERGY_HELP)
    p.add_argument("--device", choices=DEVICES, default="cpu", help=DEVICE_HELP)
    p.add_argument("--json", action="store_true", help="print what was done as JSON instead of the table")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    return p


def denoise_main(argv: list[str] | None = None) -> int:
    """``denoise IN OUT [--layer NAME] [...]`` or ``denoise --halves A B OUT``."""
    parser = denoise_parser()
    args = parser.parse_args(argv)
    if args.halves and len(args.files) != 1:
        parser.error(f"with --halves give only the output file, got {len(args.files)} paths")
    if not args.halves and len(args.files) != 2:
        parser.error(f"expected an input and an output file, got {len(args.files)} path(s)")
    if args.halves and args.variance_layer:
        parser.error("--halves and --variance-layer exclude each other (the halves give the variance)")
    from pipeline.denoise_file import DenoiseFileConfig, denoise_file

    cfg = DenoiseFileConfig(inputs=list(args.halves or args.files[:1]), output=args.files[-1],
                            model=args.model, reference=args.reference, layer=args.layer,
                            variance_layer=args.variance_layer, rgb_only=args.rgb_only, spp=args.spp,
                            noise_guard=not args.no_noise_guard, max_memory_mb=args.max_memory_mb,
                            skip_below=args.skip_below, precision=args.precision, flips=args.flips,
                            energy=not args.no_energy, device=args.device, overwrite=args.overwrite)
    from pipeline.denoise_file import denoise_summary

    result, code = parser.attempt(lambda: denoise_file(cfg))
    if code == 0:
        print_record(parser, result, args, denoise_summary)
    return code


def tradeoff_parser() -> OneLineParser:
    p = OneLineParser(prog="tradeoff", description="Measure error against time for each "
                                "spp and denoiser; plot, Pareto frontier, equal-quality savings.")
    add_render_arguments(p, reference_required=True, guard_help=(
        "as render-and-denoise --no-noise-guard: one-piece renders, unguarded models"))
    p.add_argument("--spp", type=int_list, default=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024),
                   help="comma-separated spp levels (1,2,4,...,1024)")
    p.add_argument("--models", "--model", type=name_list, default=None, metavar="NAMES",
                   help="comma-separated registry names, checkpoint files or expert specs (default: "
                        "the registry's entries, listed below)")
    p.add_argument("--list-models", action=ListModels)
    p.epilog = models_epilog()
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    compare = p.add_mutually_exclusive_group()
    compare.add_argument("--compare", choices=["oidn"], action="append", default=[],
                         help="measure OIDN colour-only and OIDN + albedo + normal too, and fail without "
                         "pyoidn (default: whenever pyoidn is installed)")
    compare.add_argument("--no-compare", action="store_true", help="do not run OIDN")
    p.add_argument("--repeat", type=positive_int, default=3, help="timing repeats, median kept (3)")
    p.add_argument("--metric", choices=["relmse", "psnr", "flip"], default="relmse",
                   help="error of the plot, frontier and saving table (relmse)")
    p.add_argument("--out", help="output folder (default: <scene name>-tradeoff): created, or an existing folder "
                   "holding none of this command's files (else --overwrite)")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no table")
    return p


def tradeoff_main(argv: list[str] | None = None) -> int:
    """``tradeoff scene.xml [--spp ...] [--models ...] [--compare oidn] (--reference F |
    --reference-spp N)``."""
    parser = tradeoff_parser()
    args = parser.parse_args(argv)
    from pipeline.tradeoff import DEFAULT_MODELS, TradeoffConfig, run_tradeoff
    from pipeline.tradeoff_report import recommendation_line, saving_table

    models = args.models if args.models is not None else DEFAULT_MODELS
    cfg = TradeoffConfig(render=render_settings(args), out=args.out or f"{Path(args.scene).stem}-tradeoff",
                         spp=list(args.spp), models=list(models),
                         compare_oidn=False if args.no_compare else ("oidn" in args.compare or None),
                         repeat=args.repeat, metric=args.metric)
    result, code = parser.attempt(lambda: run_tradeoff(cfg, tqdm_bars("step", enabled=not args.quiet)))
    if code == 0 and not args.quiet:
        print("\n".join(saving_table(result)))
        print(recommendation_line(result))
        print(f"report: {Path(cfg.out) / 'report.html'} (tradeoff.json, tradeoff.csv, tradeoff.png beside it)")
    return code


if __name__ == "__main__":
    sys.exit(main())
