"""Command-line entry points ``render-and-denoise``, ``denoise`` and ``tradeoff``: parse, run, map errors."""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from console.progress import tqdm_bars
from rendering.render import DEFAULT_MAX_MEMORY_MB
from console.usage import OneLineParser, int_list, name_list, name_value, positive_float, positive_int
from denoise.flips import FLIPS
from denoise.precision import PRECISIONS
from denoise.denoiser import DEFAULT_MODEL
from denoise.ensemble import SEPARATOR
from pipeline.evaluation import RenderSettings


PRECISION_HELP = ("float format of the network: bfloat16 halves its time on CPUs with native bfloat16 "
                  "(AMX, AVX512-BF16) at a measured cost in quality (docs/speed.md); auto: bfloat16 "
                  "for the multi-scale nets where the CPU has it natively, else float32")
FLIPS_HELP = ("average the network over 1, 2 or 4 mirrored copies of the image: 2x or 4x the "
              "network's time for about 0.1 or 0.2 dB (docs/speed.md)")
ENERGY_HELP = ("leave the output's local means as the network made them (default: matched to the render's "
               "where they differ by more than its noise; docs/noise-guard.md)")
SKIP_HELP = ("leave the 64-px cells whose noise (transfer-space standard deviation from the halves) is "
             "below NOISE out of the network; they keep the render, as the noise guard would "
             "(benchmarks/skip.py measures time and change; default: the network everywhere)")


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


def render_settings(args: argparse.Namespace) -> RenderSettings:
    """The :class:`RenderSettings` of parsed :func:`add_render_arguments` flags."""
    return RenderSettings(scene=args.scene, resolution=tuple(args.res) if args.res else None, seed=args.seed,
                          params=dict(args.param), max_memory_mb=args.max_memory_mb,
                          noise_guard=not args.no_noise_guard, skip_below=args.skip_below,
                          precision=args.precision, flips=args.flips, energy=not args.no_energy,
                          reference=args.reference,
                          reference_spp=args.reference_spp)


def _run_and_summarise(parser: OneLineParser, action: Callable[[], Any],
                       summary: Callable[[Any], list[str]], outputs: str, quiet: bool) -> int:
    """Run a command's library call (:meth:`OneLineParser.attempt`); unless ``quiet``, print the
    summary of its result and where its outputs are. Returns the exit code."""
    result, code = parser.attempt(action)
    if code == 0 and not quiet:
        print("\n".join(summary(result)))
        print(f"outputs: {outputs}")
    return code


def render_parser() -> OneLineParser:
    p = OneLineParser(prog="render-and-denoise",
                      description="Render a Mitsuba scene, denoise it, report metrics.")
    add_render_arguments(p, reference_required=False, guard_help=(
        "render in one piece and keep the denoiser's output as it is (default: render in two halves "
        "and keep the render where its noise does not explain the change)"))
    p.add_argument("--spp", type=positive_int, help="samples per pixel (128)")
    p.add_argument("--model", help=f"checkpoint or preset name (default: {SEPARATOR.join(DEFAULT_MODEL)}); "
                   "A+B: an ensemble (e.g. fast+u-high); 'auto' with --time-budget")
    compare = p.add_mutually_exclusive_group()
    compare.add_argument("--compare", choices=["oidn"], action="append", default=[],
                         help="denoise with OIDN colour-only too, and fail without pyoidn (default: "
                         "compare whenever pyoidn is installed)")
    compare.add_argument("--no-compare", action="store_true", help="do not run OIDN")
    p.add_argument("--out", help="output folder (default: the scene's name)")
    p.add_argument("--time-budget", type=positive_float, metavar="SECONDS",
                   help="choose spp (and, with --model auto, the preset) to finish within SECONDS")
    p.add_argument("--curves", metavar="TRADEOFF_JSON",
                   help="trade curves (a tradeoff run's tradeoff.json) for --model auto")
    p.add_argument("--quiet", action="store_true", help="no summary on stdout")
    return p


def main(argv: list[str] | None = None) -> int:
    """``render-and-denoise scene.xml [...]``."""
    parser = render_parser()
    args = parser.parse_args(argv)
    if args.time_budget is None and (args.model == "auto" or args.curves):
        parser.error("--model auto and --curves need --time-budget")
    if args.time_budget is not None and args.spp is not None:
        parser.error("--spp and --time-budget exclude each other (the budget chooses the spp)")
    from pipeline.run import RunConfig, run, summary_lines

    cfg = RunConfig(render=render_settings(args), out=args.out or Path(args.scene).stem, spp=args.spp or 128,
                    model=args.model,
                    compare_oidn=False if args.no_compare else ("oidn" in args.compare or None),
                    time_budget=args.time_budget, curves=args.curves)
    log = (lambda s: None) if args.quiet else (lambda s: print(f"... {s}", file=sys.stderr))
    return _run_and_summarise(parser, lambda: run(cfg, log), summary_lines,
                              f"{cfg.out}/ (report.html, metrics.json, comparison.png)", args.quiet)


def denoise_parser() -> OneLineParser:
    p = OneLineParser(prog="denoise", description="Denoise an image rendered elsewhere (EXR with any "
                      "layers or parts, PFM, Radiance HDR); the output keeps the input's layout.")
    p.add_argument("files", nargs="+", metavar="IN OUT",
                   help="input and output image (with --halves: the output only); an output "
                   "ending in .pfm or .hdr is written in that format, anything else as EXR")
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
    p.add_argument("--model", help=f"checkpoint or preset name (default: {SEPARATOR.join(DEFAULT_MODEL)}); "
                   "A+B: an ensemble (e.g. fast+u-high)")
    p.add_argument("--reference", help="reference image: print metrics")
    p.add_argument("--max-memory-mb", type=float, default=DEFAULT_MAX_MEMORY_MB, help="tile memory bound")
    p.add_argument("--skip-below", type=positive_float, metavar="NOISE", help=SKIP_HELP)
    p.add_argument("--precision", choices=PRECISIONS, default="auto", help=PRECISION_HELP)
    p.add_argument("--flips", type=int, choices=tuple(FLIPS), default=1, help=FLIPS_HELP)
    p.add_argument("--no-energy", action="store_true", help=ENERGY_HELP)
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
                            energy=not args.no_energy)
    result, code = parser.attempt(lambda: denoise_file(cfg))
    if code:
        return code
    print(json.dumps(result, indent=1))
    return 0


def tradeoff_parser() -> OneLineParser:
    p = OneLineParser(prog="tradeoff", description="Measure error against time for each "
                                "spp and denoiser; plot, Pareto frontier, equal-quality savings.")
    add_render_arguments(p, reference_required=True, guard_help=(
        "as render-and-denoise --no-noise-guard: one-piece renders, unguarded models"))
    p.add_argument("--spp", type=int_list, default=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024),
                   help="comma-separated spp levels (1,2,4,...,1024)")
    p.add_argument("--models", type=name_list, default=None,
                   help="comma-separated presets (model/weights/<name>.ckpt), checkpoint paths or "
                        "ensembles A+B (fast,balanced,high,u-high,fast+u-high,fast+u-high-lowspp)")
    p.add_argument("--compare", choices=["oidn"], action="append", default=[],
                   help="also measure OIDN colour-only (needs pyoidn)")
    p.add_argument("--repeat", type=positive_int, default=3, help="timing repeats, median kept (3)")
    p.add_argument("--metric", choices=["relmse", "psnr", "flip"], default="relmse",
                   help="error of the plot, frontier and saving table (relmse)")
    p.add_argument("--out", help="output folder (default: <scene name>-tradeoff)")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no table")
    return p


def tradeoff_main(argv: list[str] | None = None) -> int:
    """``tradeoff scene.xml [--spp ...] [--models ...] [--compare oidn] (--reference F |
    --reference-spp N)``."""
    parser = tradeoff_parser()
    args = parser.parse_args(argv)
    from pipeline.tradeoff import DEFAULT_MODELS, TradeoffConfig, run_tradeoff
    from pipeline.tradeoff_report import saving_table

    models = args.models if args.models is not None else DEFAULT_MODELS
    cfg = TradeoffConfig(render=render_settings(args), out=args.out or f"{Path(args.scene).stem}-tradeoff",
                         spp=list(args.spp), models=list(models), compare_oidn="oidn" in args.compare,
                         repeat=args.repeat, metric=args.metric)
    return _run_and_summarise(parser, lambda: run_tradeoff(cfg, tqdm_bars("step", enabled=not args.quiet)),
                              saving_table, f"{cfg.out}/ (tradeoff.json, tradeoff.csv, tradeoff.png)", args.quiet)


if __name__ == "__main__":
    sys.exit(main())
