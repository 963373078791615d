"""What rendering the albedo and normals for OIDN + albedo + normal adds to the render time.

Each eval scene is loaded as ``render-and-denoise`` loads it (``--res``, seed 7) and rendered at
each spp in two halves, three ways, every kernel compiled before anything is timed and the three
taken in turn ``--repeat`` times (medians kept):

* ``plain``: the render our models are given (:func:`pipeline.evaluation.render_input`);
* ``pass``: the AOV pass the commands add for OIDN (:func:`pipeline.evaluation.with_aovs`:
  Mitsuba's aov integrator alone on the same loaded scene, the render's camera rays);
* ``wrapped``: the one render that gives radiance and AOVs together (the scene's integrator
  inside Mitsuba's aov integrator, as a model that takes AOVs is rendered for).

It records the time ratios (plain + pass) / plain and wrapped / plain, whether the wrapped
render's radiance is the plain render's bit for bit, and the largest difference between the
pass's AOVs and the wrapped render's.

    python -m benchmarks.aov_cost [--scenes a,b] [--spp 4,16,128] [--res 256] [--repeat 3]

Prints a table and writes benchmarks/results/aov_cost.json and aov_cost.md.
"""
from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.eval_scenes import (EVAL_DIR, RESULTS, SEED, EvalScene, eval_scenes, finish_record, run_record,
                                   save_result)
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, name_list, positive_int
from pipeline.evaluation import AOVS, RenderSettings, render_input, with_aovs

DEFAULT_SCENES = ("bitterli_cornell_box", "bunny_sss_volpath", "matpreview_plastic", "tut_cbox_mirror_glass",
                  "tut_teapot_pointlights")
WAYS = ("plain", "pass", "wrapped")


def _timed(settings: RenderSettings, plain: Any, wrapped: Any, spp: int) -> dict[str, Any]:
    """One round: the three renders of ``spp``, their seconds and the wrapped render's agreement."""
    start = time.perf_counter()
    render = render_input(plain, spp, settings)
    plain_s = time.perf_counter() - start
    start = time.perf_counter()
    with_pass, _ = with_aovs(render, plain, settings)
    pass_s = time.perf_counter() - start
    start = time.perf_counter()
    both = render_input(wrapped, spp, settings, AOVS)
    wrapped_s = time.perf_counter() - start
    return {"plain": plain_s, "pass": pass_s, "wrapped": wrapped_s,
            "rgb_identical": bool(np.array_equal(render.rgb, both.rgb)),
            "rgb_max_diff": float(np.abs(render.rgb - both.rgb).max()),
            "aov_max_diff": max(float(np.abs(with_pass.aovs[a] - both.aovs[a]).max()) for a in AOVS)}


def measure_scene(scene: EvalScene, spps: list[int], resolution: tuple[int, int], repeat: int) -> dict[str, Any]:
    """Every spp of ``scene``: median seconds of each way, the ratios and the agreement."""
    settings = scene.settings(resolution=resolution)
    plain, wrapped = settings.load(), settings.load(AOVS)
    row: dict[str, Any] = {}
    for spp in spps:
        _timed(settings, plain, wrapped, spp)  # compiles the three kernels of this spp
        rounds = [_timed(settings, plain, wrapped, spp) for _ in range(repeat)]
        seconds = {way: statistics.median(r[way] for r in rounds) for way in WAYS}
        row[str(spp)] = {"seconds": seconds, "times": {way: [r[way] for r in rounds] for way in WAYS},
                         "pass_ratio": (seconds["plain"] + seconds["pass"]) / seconds["plain"],
                         "wrapped_ratio": seconds["wrapped"] / seconds["plain"],
                         "rgb_identical": all(r["rgb_identical"] for r in rounds),
                         "rgb_max_diff": max(r["rgb_max_diff"] for r in rounds),
                         "aov_max_diff": max(r["aov_max_diff"] for r in rounds)}
    return row


def summarize(rows: dict[str, Any], spps: list[int]) -> dict[str, Any]:
    """Per spp, the geometric mean and the range of each ratio over the scenes."""
    out = {}
    for spp in spps:
        entry = {}
        for key in ("pass_ratio", "wrapped_ratio"):
            values = [row[str(spp)][key] for row in rows.values()]
            entry[key] = {"geomean": float(np.exp(np.mean(np.log(values)))), "min": min(values), "max": max(values)}
        out[str(spp)] = entry
    return out


def markdown(result: dict[str, Any]) -> str:
    """Per scene and spp: median seconds, the two ratios and whether the wrapped RGB is the plain's."""
    lines = ["| scene | spp | plain s | pass s | wrapped s | (plain + pass) / plain | wrapped / plain | "
             "wrapped RGB = plain |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    for name, row in result["scenes"].items():
        for spp in result["spp"]:
            e = row[str(spp)]
            s = e["seconds"]
            same = "yes" if e["rgb_identical"] else f"no (max diff {e['rgb_max_diff']:.1e})"
            lines.append(f"| {name} | {spp} | {s['plain']:.3f} | {s['pass']:.3f} | {s['wrapped']:.3f} | "
                         f"{e['pass_ratio']:.2f} | {e['wrapped_ratio']:.2f} | {same} |")
    for spp in result["spp"]:
        m = result["summary"][str(spp)]
        lines.append(f"| **geometric mean** | {spp} | | | | {m['pass_ratio']['geomean']:.2f} | "
                     f"{m['wrapped_ratio']['geomean']:.2f} | |")
    return "\n".join(lines) + "\n"


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="python -m benchmarks.aov_cost", description=__doc__.split("\n")[0])
    p.add_argument("--scenes", type=name_list, default=DEFAULT_SCENES, help="comma-separated scene folder names")
    p.add_argument("--spp", type=int_list, default=(4, 16, 128), help="comma-separated spp (4,16,128)")
    p.add_argument("--res", type=positive_int, default=256, help="square film size in pixels (256)")
    p.add_argument("--repeat", type=positive_int, default=3, help="timed rounds, medians kept (3)")
    p.add_argument("--eval-dir", type=Path, default=EVAL_DIR)
    p.add_argument("--out", type=Path, default=RESULTS)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    record = run_record("benchmarks.aov_cost", argv)
    start = time.perf_counter()
    try:
        scenes = eval_scenes(args.scenes, args.eval_dir)
        rows = {scene.name: measure_scene(scene, list(args.spp), (args.res, args.res), args.repeat)
                for scene in scenes}
    except COMMAND_ERRORS as exc:
        return parser.fail(exc)
    result = {**finish_record(record, start), "resolution": [args.res, args.res], "seed": SEED,
              "spp": list(args.spp), "repeat": args.repeat, "scenes": rows, "summary": summarize(rows, list(args.spp))}
    table = markdown(result)
    save_result(args.out, "aov_cost", result, table)
    print(table)
    print(f"wrote {args.out / 'aov_cost.json'} and {args.out / 'aov_cost.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
