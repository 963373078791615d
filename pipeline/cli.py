"""Command-line entry points ``render-and-denoise`` and ``denoise``: parse, run, map errors."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.errors import DenoiserError


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _param(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected name=value, got {text!r}")
    return name, value


def _fail(prog: str, exc: BaseException) -> int:
    message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    print(f"{prog}: {message}", file=sys.stderr)
    return 1


def render_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="render-and-denoise",
                                description="Render a Mitsuba scene, denoise it, report metrics.")
    p.add_argument("scene", help="Mitsuba 3 scene XML file")
    p.add_argument("--spp", type=_positive_int, default=128, help="samples per pixel (128)")
    p.add_argument("--res", type=_positive_int, nargs=2, metavar=("W", "H"), help="resolution")
    p.add_argument("--seed", type=int, default=0, help="render seed")
    p.add_argument("--model", help="checkpoint (default: the shipped weights)")
    ref = p.add_mutually_exclusive_group()
    ref.add_argument("--reference", help="reference EXR of the same size")
    ref.add_argument("--reference-spp", type=_positive_int, help="render a reference at N spp")
    p.add_argument("--compare", choices=["oidn"], action="append", default=[],
                   help="also denoise with OIDN colour-only (needs pyoidn)")
    p.add_argument("--param", type=_param, action="append", default=[], metavar="NAME=VALUE",
                   help="scene $parameter")
    p.add_argument("--out", help="output folder (default: the scene's name)")
    p.add_argument("--max-memory-mb", type=float, default=1024.0, help="tile memory bound")
    p.add_argument("--quiet", action="store_true", help="no summary on stdout")
    return p


def main(argv: list[str] | None = None) -> int:
    """``render-and-denoise scene.xml [...]``."""
    args = render_parser().parse_args(argv)
    from pipeline.run import RunConfig, run, summary_lines

    cfg = RunConfig(scene=args.scene, out=args.out or Path(args.scene).stem, spp=args.spp,
                    resolution=tuple(args.res) if args.res else None, seed=args.seed,
                    model=args.model, reference=args.reference, reference_spp=args.reference_spp,
                    compare_oidn="oidn" in args.compare, params=dict(args.param),
                    max_memory_mb=args.max_memory_mb)
    log = (lambda s: None) if args.quiet else (lambda s: print(f"... {s}", file=sys.stderr))
    try:
        metrics = run(cfg, log)
    except (DenoiserError, OSError, ValueError) as exc:
        return _fail("render-and-denoise", exc)
    except KeyboardInterrupt:
        print("render-and-denoise: interrupted", file=sys.stderr)
        return 130
    if not args.quiet:
        print("\n".join(summary_lines(metrics)))
        print(f"outputs: {cfg.out}/ (report.html, metrics.json, comparison.png)")
    return 0


def denoise_main(argv: list[str] | None = None) -> int:
    """``denoise IN.exr OUT.exr [--model PATH] [--reference REF.exr]``."""
    p = argparse.ArgumentParser(prog="denoise", description="Denoise an EXR rendered elsewhere.")
    p.add_argument("input")
    p.add_argument("output")
    p.add_argument("--model", help="checkpoint (default: the shipped weights)")
    p.add_argument("--reference", help="reference EXR: print metrics")
    p.add_argument("--max-memory-mb", type=float, default=1024.0)
    args = p.parse_args(argv)
    from pipeline.run import denoise_file

    try:
        result = denoise_file(args.input, args.output, args.model, args.reference, args.max_memory_mb)
    except (DenoiserError, OSError, ValueError) as exc:
        return _fail("denoise", exc)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
