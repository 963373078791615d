"""What an ensemble of two denoisers (``--model A+B``, :mod:`denoise.ensemble`) buys over each, and
the measurement behind its window radius and ``lam``.

Each image is denoised once by every member (the bare network, as ``render-and-denoise`` runs it:
noise input from the halves); the outputs are then combined with every (radius, lam, power) setting and
with their plain mean, and every candidate goes through the noise guard at the render's strength,
as the default path does. Every member runs at every spp: this measures the combination itself, not
an ensemble's spp gate (a member trained for fewer spp sits out, ``Denoiser.active``; the scoreboard
runs that path). OIDN colour-only denoises the same images. Two sets:

* ``validation`` (the tuning set): the held-out ``val`` scenes of ``--data`` folders (renders with
  a variance layer at 4-256 spp; references at the dataset's reference spp).
* ``eval``: ../shared/eval-scenes rendered in two halves at seed 7 at ``--spp``, against their
  2048-spp references; means over the scenes whose reference ceiling is >= 40 dB.

PSNR is tonemapped (:mod:`imaging.metrics`).

    python -m benchmarks.ensemble --data data/train256 --data data/media256 [--members flat-s-allspp,unet-l-allspp]
        [--settings 3:0.3:1,3:0.3:2,...] [--spp 4,16,32,64,128,256] [--eval-dir DIR] [--quick]

Writes benchmarks/results/ensemble.json and ensemble.md.
"""
from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from benchmarks.eval_scenes import (CEILING_DB, EVAL_DIR, RESULTS, SEED, finish_record, run_record, save_result,
                                    scored_renders)
from benchmarks.validation import val_images
from imaging.metrics import psnr
from rendering.render import RenderResult
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, name_list, positive_int
from denoise.denoiser import Denoiser
from denoise.ensemble import DEFAULT_LAMBDA, DEFAULT_POWER, DEFAULT_RADIUS, combine
from denoise.noise_guard import guard, strength_for
from denoise.oidn import oidn_denoise

Setting = tuple[int, float, float]  # (window radius, lam, power)
MEAN = "mean"


def label(setting: Setting) -> str:
    return f"r{setting[0]} lam{setting[1]:g} p{setting[2]:g}"


def score_image(render: RenderResult, ref: np.ndarray, members: dict[str, Denoiser],
                settings: list[Setting]) -> dict[str, float]:
    """PSNR of the render, each member, their mean and each combination, all guarded, and OIDN."""
    assert render.variance is not None
    outs = {name: d.denoise_render(render, keep_network=True).network for name, d in members.items()}
    strength = strength_for(render.spp)

    def guarded(image: np.ndarray) -> float:
        return psnr(guard(render.rgb, image, render.variance, strength=strength)[0], ref)

    row = {"noisy": psnr(render.rgb, ref), **{name: guarded(out) for name, out in outs.items()},
           MEAN: guarded(combine(render.rgb, list(outs.values()), None))}
    for setting in settings:
        row[label(setting)] = guarded(combine(render.rgb, list(outs.values()), render.variance, *setting))
    row["oidn"] = psnr(oidn_denoise(render.rgb)[0], ref)
    return row


def validation_rows(folders: list[Path], members: dict[str, Denoiser], settings: list[Setting],
                    min_spp: int) -> Iterator[tuple[int, dict[str, float]]]:
    images = [im for im in val_images(folders, None, noise=True) if im.spp >= min_spp and im.variance is not None]
    for im in tqdm(images, desc="validation", unit="image"):
        render = RenderResult(rgb=im.noisy, spp=im.spp, variance=im.variance)
        yield im.spp, score_image(render, im.ref, members, settings)


def eval_rows(names: list[str] | None, spps: list[int], members: dict[str, Denoiser],
              settings: list[Setting], eval_dir: Path = EVAL_DIR) -> Iterator[tuple[int, dict[str, float]]]:
    for spp, render, ref in scored_renders(names, spps, eval_dir):
        yield spp, score_image(render, ref, members, settings)


def summarize(rows: Iterator[tuple[int, dict[str, float]]]) -> dict[str, Any]:
    """Per spp: the number of images and each column's mean PSNR; ``mean``: over the spp rows."""
    by_spp: dict[int, list[dict[str, float]]] = {}
    for spp, row in rows:
        by_spp.setdefault(spp, []).append(row)
    table = {str(spp): {"images": len(r), **{k: float(np.mean([x[k] for x in r])) for k in r[0]}}
             for spp, r in sorted(by_spp.items())}
    columns = [k for k in next(iter(table.values())) if k != "images"]
    return {"per_spp": table, "mean": {k: float(np.mean([t[k] for t in table.values()])) for k in columns}}


def markdown_table(summary: dict[str, Any], title: str) -> list[str]:
    columns = list(summary["mean"])
    lines = [f"**{title}**: mean PSNR dB (guarded as the default path; OIDN as it comes)", "",
             "| spp | images | " + " | ".join(columns) + " |", "|---:|---:|" + "---:|" * len(columns)]
    for spp, row in summary["per_spp"].items():
        lines.append(f"| {spp} | {row['images']} | " + " | ".join(f"{row[c]:.2f}" for c in columns) + " |")
    lines.append("| **mean** | | " + " | ".join(f"{summary['mean'][c]:.2f}" for c in columns) + " |")
    return lines + [""]


def report(result: dict[str, Any]) -> str:
    default = label((DEFAULT_RADIUS, DEFAULT_LAMBDA, DEFAULT_POWER))
    lines = [f"Source: `{result['command']}`; {result['date']}. Members {' + '.join(result['members'])}, "
             f"combined with each setting (r: window radius, lam: the regulariser, p: the power) or averaged ({MEAN}); "
             f"the default setting is {default}.", ""]
    for key, title in (("validation", "validation (held-out procedural scenes; the tuning set)"),
                       ("eval", f"eval scenes (ceiling >= {CEILING_DB:g} dB)")):
        if key in result:
            lines += markdown_table(result[key], title)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.ensemble", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, action="append", default=[],
                   help="dataset folder (repeatable) whose 'val' scenes are the tuning set")
    p.add_argument("--members", type=name_list, default=("flat-s-allspp", "unet-l-allspp"),
                   help="comma-separated checkpoints")
    p.add_argument("--settings", default="3:0.3:1,3:1:1,2:0.3:2,3:0:2,3:0.1:2,3:0.3:2,3:1:2,5:0.3:2",
                   help="comma-separated RADIUS:LAM:POWER combinations")
    p.add_argument("--spp", type=int_list, default=(4, 16, 32, 64, 128, 256), help="eval scenes' spp")
    p.add_argument("--min-spp", type=positive_int, default=4, help="validation images from this spp up")
    p.add_argument("--scenes", type=name_list, help="comma-separated eval scene names (default: all)")
    p.add_argument("--eval-dir", type=Path, default=EVAL_DIR)
    p.add_argument("--quick", action="store_true", help="3 eval scenes at 4 and 128 spp, no validation")
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(argv)
    try:
        settings = [(int(r), float(lam), float(power)) for r, lam, power in (x.split(":") for x in args.settings.split(","))]
    except ValueError:
        p.error(f"--settings: expected RADIUS:LAM:POWER,..., got {args.settings!r}")
    names, spps = args.scenes, list(args.spp)
    if args.quick:
        names, spps = names or ["bitterli_cornell_box", "matpreview_plastic", "bitterli_veach_mis"], [4, 128]
    try:
        members = {name: Denoiser(name) for name in args.members}
        record = run_record("benchmarks.ensemble", argv)
        start = time.perf_counter()
        result: dict[str, Any] = {"members": list(members), "settings": settings, "seed": SEED}
        if args.data and not args.quick:
            result["validation"] = summarize(validation_rows(args.data, members, settings, args.min_spp))
        result["eval"] = summarize(eval_rows(names, spps, members, settings, args.eval_dir))
    except COMMAND_ERRORS as exc:
        return p.fail(exc)
    result = {**finish_record(record, start), **result}
    text = report(result)
    print(text)
    if not args.quick:
        save_result(RESULTS, "ensemble", result, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
