"""What the energy correction (:mod:`denoise.energy`) buys after the default path, and the
measurement behind its settings.

Each image is denoised once as ``render-and-denoise`` does it with the correction off (the
default model, noise input and guard from the render's halves where it has them); the output is
then corrected with every ``--settings`` (clamp, window radius in blocks, significance k; block
8 px and max ratio 1.5 as the defaults) and scored, beside OIDN colour-only on the same render.
Column ``halves``: the default settings with the variance of the render's two halves in place of
each block's sample variance (images that have halves). Two sets:

* ``validation`` (the tuning set): the held-out ``val`` scenes of ``--data`` folders at every spp
  (1-16 in the datasets of docs/training.md; a variance layer from 2 spp up), against their references.
* ``eval``: ../shared/eval-scenes rendered in two halves at seed 7 at ``--spp``, against their
  2048-spp references; the scenes whose reference ceiling is >= 40 dB.
* ``one-piece``: the same scenes rendered in one piece at ``--one-piece-spp`` (no halves, so no
  guard: a 1-spp render, ``--no-noise-guard``, a file from elsewhere).

Per spp: mean PSNR dB (tonemapped) of each column, how many images a setting made worse by more
than 0.05 dB and its worst change, and the mean radiance kept (image / reference) without the
correction, with the default settings and by OIDN. Then the default correction's time on a
1280x720 image (median of 5, on torch's threads, within the Denoiser's default memory bound).

    python -m benchmarks.energy --data data/train256 --data data/media256 [--spp 4,16,128]
        [--one-piece-spp 1,4,128,1024] [--settings 16:2:4,8:2:4,...] [--eval-dir DIR]

Writes benchmarks/results/energy.json and energy.md.
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
from console.usage import COMMAND_ERRORS, OneLineParser, int_list
from denoise.chain import image_exposure
from denoise.denoiser import Denoiser
from denoise.energy import EnergySettings, apply_ratio, block_statistics, block_sums, correct_in_place, ratio_map
from denoise.oidn import oidn_denoise

NONE = "none"
HALVES = "halves"
WORSE_DB = 0.05
UNBOUNDED = 2.0**40  # bytes: one row block per image (the results do not depend on it)


def label(s: EnergySettings) -> str:
    return f"T{s.clamp:g} r{s.radius} k{s.significance:g}"


def score_image(render: RenderResult, ref: np.ndarray, denoiser: Denoiser,
                settings: list[EnergySettings]) -> dict[str, float]:
    """PSNR of the render, the uncorrected output, each corrected one and OIDN; mean radiance kept."""
    assert denoiser.energy is None
    out = denoiser.denoise_render(render).image
    exposure = image_exposure(render.rgb)
    oidn = oidn_denoise(render.rgb)[0]
    row = {"noisy": psnr(render.rgb, ref), NONE: psnr(out, ref)}
    for s in settings:
        fixed = out.copy()
        correct_in_place(render.rgb, fixed, UNBOUNDED, exposure, s)
        row[label(s)] = psnr(fixed, ref)
        if s == EnergySettings():
            row["kept default"] = float(fixed.mean() / ref.mean())
    if render.variance is not None:
        row[HALVES] = psnr(halves_corrected(render, out, exposure), ref)
    row["oidn"] = psnr(oidn, ref)
    row["kept none"], row["kept oidn"] = float(out.mean() / ref.mean()), float(oidn.mean() / ref.mean())
    return row


def halves_corrected(render: RenderResult, out: np.ndarray, exposure: float) -> np.ndarray:
    """``out`` corrected with the default settings, the halves' variance (times exposure^2, clamped
    to clamp^2, non-finite as clamp^2) summed per block in place of each block's sample variance."""
    s = EnergySettings()
    noisy_sums, out_sums, _, counts = block_statistics(render.rgb, out, exposure, s.clamp, s.block, UNBOUNDED)
    var = np.asarray(render.variance, np.float64) * exposure * exposure
    var = np.clip(np.where(np.isfinite(var), var, s.clamp ** 2), 0.0, s.clamp ** 2)
    fixed = out.copy()
    apply_ratio(fixed, ratio_map(noisy_sums, out_sums, block_sums(var, s.block), counts, s), s.block, UNBOUNDED)
    return fixed


def validation_rows(folders: list[Path], denoiser: Denoiser,
                    settings: list[EnergySettings]) -> Iterator[tuple[int, dict[str, float]]]:
    images = val_images(folders, None, noise=True)
    for im in tqdm(images, desc="validation", unit="image"):
        render = RenderResult(rgb=im.noisy, spp=im.spp, variance=im.variance)
        yield im.spp, score_image(render, im.ref, denoiser, settings)


def eval_rows(spps: list[int], denoiser: Denoiser, settings: list[EnergySettings],
              eval_dir: Path = EVAL_DIR, halves: bool = True) -> Iterator[tuple[int, dict[str, float]]]:
    for spp, render, ref in scored_renders(None, spps, eval_dir, halves):
        yield spp, score_image(render, ref, denoiser, settings)


def summarize(rows: Iterator[tuple[int, dict[str, float]]], labels: list[str]) -> dict[str, Any]:
    """Per spp: images, each column's mean, and per setting the images worse than ``none`` by more
    than :data:`WORSE_DB` and the worst change."""
    by_spp: dict[int, list[dict[str, float]]] = {}
    for spp, row in rows:
        by_spp.setdefault(spp, []).append(row)
    table: dict[str, Any] = {}
    for spp, rs in sorted(by_spp.items()):
        entry: dict[str, Any] = {"images": len(rs), **{k: float(np.mean([r[k] for r in rs])) for k in rs[0]}}
        for name in labels:
            change = [r[name] - r[NONE] for r in rs]
            entry[f"worse {name}"] = int(sum(c < -WORSE_DB for c in change))
            entry[f"worst {name}"] = float(min(change))
        table[str(spp)] = entry
    return {"per_spp": table}


def markdown(summary: dict[str, Any], title: str, labels: list[str]) -> list[str]:
    columns = ["noisy", NONE, *labels, HALVES, "oidn"]
    lines = [f"**{title}**: mean PSNR dB; under each setting, images worse than `none` by > {WORSE_DB} dB "
             "/ the worst change", "",
             "| spp | images | " + " | ".join(columns) + " | kept: none / default / OIDN |",
             "|---:|---:|" + "---:|" * (len(columns) + 1)]
    for spp, row in summary["per_spp"].items():
        cells = [("-" if c not in row else f"{row[c]:.2f}")
                 + (f" ({row['worse ' + c]} / {row['worst ' + c]:+.2f})" if c in labels else "") for c in columns]
        kept = " / ".join(f"{row['kept ' + k]:.3f}" for k in ("none", "default", "oidn"))
        lines.append(f"| {spp} | {row['images']} | " + " | ".join(cells) + f" | {kept} |")
    return lines + [""]


def report(result: dict[str, Any], labels: list[str]) -> str:
    lines = [f"Source: `{result['command']}`; {result['date']}. Model {result['model']} with the noise guard; "
             f"`none`: no correction; T: clamp, r: window radius in 8-px blocks, k: significance; the default is "
             f"{label(EnergySettings())}; `halves`: the default with the halves' variance. kept: mean radiance / the "
             "reference's.", ""]
    for key, title in (("validation", "validation (held-out procedural scenes; the tuning set)"),
                       ("eval", f"eval scenes (ceiling >= {CEILING_DB:g} dB, seed {SEED})"),
                       ("one-piece", "eval scenes rendered in one piece (no halves, no guard)")):
        if key in result:
            lines += markdown(result[key], title, labels)
    if "seconds_720p" in result:
        lines.append(f"The default correction of a 1280x720 image: {result['seconds_720p'] * 1e3:.0f} ms.")
    return "\n".join(lines)


def seconds_720p(repeats: int = 5) -> float:
    """Median seconds of the default correction of a 1280x720 image (random radiance)."""
    import torch

    from imaging.blocks import pass_workers
    from denoise.denoiser import DEFAULT_MAX_MEMORY_MB

    rng = np.random.default_rng(0)
    noisy = rng.gamma(1.0, 0.5, (720, 1280, 3)).astype(np.float32)
    workers = pass_workers(720 * 1280, torch.get_num_threads())
    times = []
    for _ in range(repeats):
        out = noisy * np.float32(0.9)
        start = time.perf_counter()
        correct_in_place(noisy, out, DEFAULT_MAX_MEMORY_MB * 2**20, workers=workers)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def parse_settings(text: str) -> list[EnergySettings]:
    """``CLAMP:RADIUS:K,...`` -> settings (ValueError for a malformed or invalid one)."""
    out = []
    for item in text.split(","):
        clamp, radius, k = item.split(":")
        out.append(EnergySettings(clamp=float(clamp), radius=int(radius), significance=float(k)))
    return out


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.energy", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, action="append", default=[],
                   help="dataset folder (repeatable) whose 'val' scenes are the tuning set")
    p.add_argument("--settings", default="16:2:4,4:2:4,8:2:4,64:2:4,16:1:4,16:3:4,16:2:0,16:2:1,16:2:16",
                   help="comma-separated CLAMP:RADIUS:K combinations")
    p.add_argument("--spp", type=int_list, default=(4, 16, 128), help="eval scenes' spp")
    p.add_argument("--one-piece-spp", type=int_list, default=(1, 4, 128, 1024),
                   help="spp of the eval scenes rendered in one piece")
    p.add_argument("--eval-dir", type=Path, default=EVAL_DIR)
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(argv)
    try:
        settings = parse_settings(args.settings)
    except ValueError:
        p.error(f"--settings: expected CLAMP:RADIUS:K,... with valid values, got {args.settings!r}")
    if EnergySettings() not in settings:
        settings.insert(0, EnergySettings())
    labels = [label(s) for s in settings]
    try:
        denoiser = Denoiser(None, energy=None)
        record = run_record("benchmarks.energy", argv)
        start = time.perf_counter()
        result: dict[str, Any] = {"model": denoiser.name, "settings": [vars(s) for s in settings], "seed": SEED}
        if args.data:
            result["validation"] = summarize(validation_rows(args.data, denoiser, settings), labels)
        result["eval"] = summarize(eval_rows(list(args.spp), denoiser, settings, args.eval_dir), labels)
        result["one-piece"] = summarize(eval_rows(list(args.one_piece_spp), denoiser, settings, args.eval_dir,
                                                  halves=False), labels)
        result["seconds_720p"] = seconds_720p()
    except COMMAND_ERRORS as exc:
        return p.fail(exc)
    result = {**finish_record(record, start), **result}
    text = report(result, labels)
    print(text)
    save_result(RESULTS, "energy", result, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
