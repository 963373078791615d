"""What the noise guard (denoise/noise_guard.py) costs where renders are noisy and buys where they
have converged; the measurement behind its default window and strength.

Every render is the one ``render-and-denoise`` makes (:mod:`pipeline.evaluation`: two independent
halves, so each image comes with its variance estimate); the model denoises it once, and the guard
is applied with each (window radius, pivot spp) setting to the bare network's output. Columns:
``model`` (the bare network), ``default path`` (what ``render-and-denoise`` returns), each setting,
OIDN. Two regimes:

* ``noisy``: every scene of ../shared/eval-scenes at its reference resolution, spp 4, 16, 128
  (seed 7), against its stored 2048-spp reference.exr.
* ``converged``: the demo scene at 24 and 64 px and every eval scene at 48 px wide, spp 256, 1024
  and 4096, against a 16384-spp reference rendered here (another seed): the case where a denoiser must
  not make the image worse.

PSNR is tonemapped as in ../shared/eval-scenes/README.md. OIDN colour-only denoises the same
renders. Means are over the scenes whose reference ceiling is >= 40 dB (``noisy``) and over all
scenes (``converged``: the 16384-spp reference is far cleaner than any input here).

    python -m benchmarks.noise_guard [--settings 1:0,1:256,2:256] [--scenes a,b] [--model M] [--quick]

Writes benchmarks/results/noise_guard.json and noise_guard.md (``--report-only``: rewrites the
tables from the recorded JSON, e.g. after the default setting changed among the measured ones).
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from benchmarks.eval_scenes import (CEILING_DB, RESULTS, ROOT, SEED, EvalScene, eval_scenes, finish_record,
                                    run_record, save_result)
from imaging.metrics import psnr
from console.usage import COMMAND_ERRORS, OneLineParser, name_list
from denoise.denoiser import Denoiser
from pipeline.evaluation import BARE, OIDN, RenderSettings, denoise_outputs, render_input
from denoise.noise_guard import DEFAULT_PIVOT_SPP, DEFAULT_RADIUS, guard, strength_for

DEMO = ROOT / "scenes" / "examples" / "demo.xml"
REF_SEED = 1_000_003


Setting = tuple[int, float]  # (window radius, pivot spp: strength max(1, pivot/spp))


def label(setting: Setting) -> str:
    return f"guard r{setting[0]} p{setting[1]:g}"


def score_render(scene: Any, spp: int, case: RenderSettings, ref: np.ndarray, denoiser: Denoiser,
                 guards: list[Setting]) -> dict[str, float]:
    """PSNR of the noisy render, the bare network, the default path (guard at its default), the
    network with each guard setting, and OIDN: one render and one forward pass
    (:mod:`pipeline.evaluation`)."""
    noisy = render_input(scene, spp, case)
    outputs = denoise_outputs(noisy, {"model": denoiser}, oidn=True, bare=True)
    out = outputs["model" + BARE].image
    row = {"noisy": psnr(noisy.rgb, ref), "model": psnr(out, ref),
           "default path": psnr(outputs["model"].image, ref)}
    for setting in guards:
        guarded, weight = guard(noisy.rgb, out, noisy.variance, setting[0], strength_for(spp, setting[1]))
        row[label(setting)] = psnr(guarded, ref)
        row[f"weight {label(setting)}"] = weight
    row["oidn"] = psnr(outputs[OIDN].image, ref)
    return row


def noisy_regime(scenes: list[EvalScene], spps: list[int], denoiser: Denoiser,
                 guards: list[Setting]) -> dict[str, Any]:
    rows: dict[str, Any] = {}
    for scene in tqdm(scenes, desc="noisy regime", unit="scene"):
        ref = scene.reference()
        case = scene.settings(resolution=(ref.shape[1], ref.shape[0]))
        loaded = case.load()
        rows[scene.name] = {"ceiling_db": scene.ceiling_db,
                            **{str(s): score_render(loaded, s, case, ref, denoiser, guards) for s in spps}}
    return rows


def converged_regime(cases: list[tuple[str, Path, tuple[int, int]]], spps: list[int], ref_spp: int,
                     denoiser: Denoiser, guards: list[Setting]) -> dict[str, Any]:
    rows: dict[str, Any] = {}
    for name, xml, res in tqdm(cases, desc="converged regime", unit="scene"):
        case = RenderSettings(str(xml), res, SEED)
        scene = case.load()
        ref = render_input(scene, ref_spp, replace(case, seed=REF_SEED, noise_guard=False)).rgb  # one piece
        rows[name] = {str(s): score_render(scene, s, case, ref, denoiser, guards) for s in spps}
    return rows


def converged_cases(scenes: list[EvalScene], width: int) -> list[tuple[str, Path, tuple[int, int]]]:
    cases = [("demo@24", DEMO, (24, 24)), ("demo@64", DEMO, (64, 64))]
    for scene in scenes:
        w, h = scene.resolution
        size = (width, max(1, round(width * h / w)))
        cases.append((f"{scene.name}@{width}", scene.folder / "scene.xml", size))
    return cases


def summarize(rows: dict[str, Any], spps: list[int], names: list[str]) -> dict[str, Any]:
    """Per spp: mean PSNR of each method, and the worst (most negative) change against noisy."""
    out: dict[str, Any] = {"scenes": len(names)}
    for spp in spps:
        methods = [k for k in rows[names[0]][str(spp)] if not k.startswith("weight")]
        entry = {}
        for m in methods:
            values = [rows[n][str(spp)][m] for n in names]
            diffs = [rows[n][str(spp)][m] - rows[n][str(spp)]["noisy"] for n in names]
            entry[m] = {"mean_psnr": float(np.mean(values)), "worst_vs_noisy_db": float(min(diffs))}
        out[str(spp)] = entry
    return out


def markdown(summary: dict[str, Any], spps: list[int], title: str) -> list[str]:
    methods = list(summary[str(spps[0])])
    lines = [f"**{title}** ({summary['scenes']} scenes): mean PSNR dB (worst change vs noisy)", "",
             "| spp | " + " | ".join(methods) + " |", "|---:|" + "---:|" * len(methods)]
    for spp in spps:
        e = summary[str(spp)]
        lines.append(f"| {spp} | " + " | ".join(
            f"{e[m]['mean_psnr']:.2f} ({e[m]['worst_vs_noisy_db']:+.2f})" for m in methods) + " |")
    return lines + [""]


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.noise_guard", description=__doc__.split("\n\n")[0])
    p.add_argument("--settings", default="1:0,1:64,1:256,1:1024,2:0,2:256",
                   help="comma-separated RADIUS:PIVOT_SPP guard settings")
    p.add_argument("--scenes", type=name_list, help="comma-separated eval scene names (default: all)")
    p.add_argument("--model", default=None, help="checkpoint or preset (default: the shipped default)")
    p.add_argument("--width", type=int, default=48, help="eval scenes' width in the converged regime")
    p.add_argument("--quick", action="store_true", help="3 scenes, fewer spp (a smoke run)")
    p.add_argument("--report-only", action="store_true",
                   help="no measurement: rewrite the tables of results/noise_guard.json for the "
                   "current default setting")
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(argv)
    try:
        settings = [(int(r), float(st)) for r, st in (x.split(":") for x in args.settings.split(","))]
    except ValueError:
        p.error(f"--settings: expected RADIUS:PIVOT_SPP,..., got {args.settings!r}")
    default = label((DEFAULT_RADIUS, DEFAULT_PIVOT_SPP))
    names = args.scenes
    if args.quick and names is None:
        names = ["bitterli_cornell_box", "matpreview_plastic", "bitterli_veach_mis"]
    noisy_spps, conv_spps, ref_spp = (([4, 16], [1024], 4096) if args.quick
                                      else ([4, 16, 128], [256, 1024, 4096], 16384))
    try:
        if args.report_only:
            result = json.loads((RESULTS / "noise_guard.json").read_text())
            result["default"] = default
        else:
            result = measure(run_record("benchmarks.noise_guard", argv), eval_scenes(names), args.model,
                             settings, default, noisy_spps, conv_spps, ref_spp, args.width)
    except COMMAND_ERRORS as exc:
        return p.fail(exc)
    text = report(result)
    print(text)
    if not args.quick:
        save_result(RESULTS, "noise_guard", result, text)
    return 0


def measure(record: dict[str, Any], scenes: list[EvalScene], model: str | None, guards: list[Setting],
            default: str, noisy_spps: list[int], conv_spps: list[int], ref_spp: int,
            width: int) -> dict[str, Any]:
    """Both regimes with ``model``; the result file's dict."""
    denoiser = Denoiser(model)
    start = time.perf_counter()
    noisy_rows = noisy_regime(scenes, noisy_spps, denoiser, guards)
    conv_rows = converged_regime(converged_cases(scenes, width), conv_spps, ref_spp, denoiser, guards)
    scored = [n for n, r in noisy_rows.items() if r["ceiling_db"] >= CEILING_DB]
    summary = {"noisy": summarize(noisy_rows, noisy_spps, scored),
               "converged": summarize(conv_rows, conv_spps, list(conv_rows))}
    record = finish_record(record, start)
    return {**record, "seconds": record["wall_s"], "model": denoiser.name, "settings": guards,
            "default": default, "seed": SEED, "noisy_spp": noisy_spps, "converged_spp": conv_spps,
            "reference_spp_converged": ref_spp, "summary": summary, "noisy": noisy_rows, "converged": conv_rows}


def report(result: dict[str, Any]) -> str:
    """The markdown tables of a result: means per regime, then every converged case."""
    default, summary = result["default"], result["summary"]
    noisy_spps = result.get("noisy_spp", [4, 16, 128])
    conv_spps = result.get("converged_spp", [256, 1024, 4096])
    lines = [f"Noise guard, model `{result['model']}`; default setting: {default}.", ""]
    lines += markdown(summary["noisy"], noisy_spps, f"noisy regime: eval scenes, ceiling >= {CEILING_DB:g} dB")
    lines += markdown(summary["converged"], conv_spps,
                      f"converged regime: {result['reference_spp_converged']}-spp references")
    lines.append(f"| converged case | spp | noisy | model | {default} | oidn |")
    lines.append("|---|---:|---:|---:|---:|---:|")
    for name, row in result["converged"].items():
        for spp in conv_spps:
            e = row[str(spp)]
            lines.append(f"| {name} | {spp} | {e['noisy']:.2f} | {e['model']:.2f} | "
                         f"{e.get(default, math.nan):.2f} | {e['oidn']:.2f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
