"""Record budget mode's model costs: ``pipeline/budget_costs.json`` (:mod:`pipeline.budget_costs`).

For each registry entry, in processes of their own (a run of ``render-and-denoise`` loads its
model once, in a fresh process): the two calibrations' times (:func:`pipeline.budget_costs.measure_speed`),
the seconds to load the entry with the CLI's default settings, its first call on a 128x128 image
(the extra over a warm call is ``first_s``), and its seconds per tile call and per window pixel,
warm, in its dearest spp range (:func:`pipeline.budget.tile_rates`), then the calibrations again.
Each figure is converted to the median calibration time of all processes (``figure * median /
its process's``; loading and the first call by the loading calibration, the tiles by the other),
so load on the machine while recording cancels to first order; the median over ``--processes``
runs is kept. Record on a quiet host: the calibrations and the models slow down alike only
roughly.

    python -m benchmarks.budget_costs [--processes 3] [--out pipeline/budget_costs.json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.eval_scenes import ROOT, finish_record, run_record
from console.usage import COMMAND_ERRORS, OneLineParser, positive_int
from imaging.atomic_io import write_json_atomic
from model.registry import registry
from pipeline.budget_costs import COSTS, SETTINGS, entry_signature, measure_speed

TIMES = {"load_s": "loading_calibration_s", "first_s": "loading_calibration_s",
         "per_call_s": "calibration_s", "per_px_s": "calibration_s"}  # figure -> the calibration it goes by
SIDE = 128


def measure(name: str) -> dict[str, Any]:
    """One entry's figures in this process (meant to be a fresh one), in seconds of this process."""
    import torch

    from model.architectures import alignment
    from pipeline.budget import probe_image, probe_spps, tile_rates, window_pixels
    from pipeline.evaluation import RenderSettings, make_denoiser

    before = measure_speed(None)
    t0 = time.perf_counter()
    den = make_denoiser(name, RenderSettings(scene="unused.xml"))  # the CLI's defaults
    load_s = time.perf_counter() - t0
    img = probe_image(SIDE)
    spps = probe_spps(den)
    cold = den.denoise_array(img, spp=spps[0]).seconds  # the first call in the process
    rates = {}
    for spp in spps:
        tile_rates(den, img, spp)  # every shape once: the second timing is warm
        rates[spp] = tile_rates(den, img, spp)
    px = window_pixels(SIDE, SIDE, den.cores(SIDE, SIDE), den.margin)
    warm = {spp: per_call + per_px * px for spp, (per_call, per_px) in rates.items()}
    dearest = max(warm, key=lambda spp: warm[spp])
    first, after = den.members[0], measure_speed(None)
    return {"calibration_s": (before.calibration_s + after.calibration_s) / 2,
            "loading_calibration_s": (before.loading_s + after.loading_s) / 2, "load_s": load_s,
            "first_s": max(0.0, cold - warm[spps[0]]), "per_call_s": rates[dearest][0],
            "per_px_s": rates[dearest][1], "dearest_spp": dearest, "bytes_per_pixel": den.bytes_per_pixel(),
            "core_margin": first.margin, "margin": den.margin, "alignment": alignment(first.config),
            "needs_aovs": den.needs_aovs, "signature": list(entry_signature(name)),
            "torch_threads": torch.get_num_threads()}


def in_fresh_process(name: str) -> dict[str, Any]:
    """:func:`measure` in a new interpreter."""
    done = subprocess.run([sys.executable, "-m", "benchmarks.budget_costs", "--one", name], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"measuring {name} failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def combine(runs: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """The recorded calibration times (medians of every process's) and each entry's figures at them."""
    calibrations = {c: statistics.median(r[c] for rows in runs.values() for r in rows) for c in set(TIMES.values())}
    entries = {}
    for name, rows in runs.items():
        entry = {k: v for k, v in rows[0].items() if k not in (*TIMES, *calibrations, "torch_threads")}
        entry.update({k: statistics.median(r[k] * calibrations[c] / r[c] for r in rows) for k, c in TIMES.items()})
        entries[name] = entry
    return {**calibrations, "entries": entries}


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.budget_costs", description=__doc__.split("\n")[0])
    p.add_argument("--processes", type=positive_int, default=3, help="fresh processes per entry (median kept)")
    p.add_argument("--out", type=Path, default=COSTS)
    p.add_argument("--one", metavar="ENTRY", help=argparse.SUPPRESS)  # the child: one entry, JSON on stdout
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(argv)
    if args.one:
        print(json.dumps(measure(args.one)))
        return 0
    try:
        from denoise.precision import native_bfloat16

        record, start = run_record("benchmarks.budget_costs", argv), time.perf_counter()
        runs: dict[str, list[dict[str, Any]]] = {name: [] for name in registry().entries}
        for i in range(args.processes):  # interleaved: a change of load meets every entry
            for name in runs:
                runs[name].append(in_fresh_process(name))
                r = runs[name][-1]
                print(f"{name} #{i + 1}: calibrations {r['calibration_s'] * 1e3:.1f} and "
                      f"{r['loading_calibration_s'] * 1e3:.1f} ms, load {r['load_s']:.2f} s, "
                      f"first call +{r['first_s']:.2f} s, {r['per_call_s'] * 1e3:.1f} ms a call + "
                      f"{r['per_px_s'] * 1e6:.2f} us a pixel", flush=True)
        result = finish_record(record, start)
        result["machine"].update(native_bfloat16=native_bfloat16(), torch_threads=runs[next(iter(runs))][0]["torch_threads"],
                                 cpus=os.cpu_count())
        result.update(settings=SETTINGS, side=SIDE, **combine(runs))
    except (*COMMAND_ERRORS, RuntimeError) as exc:
        return p.fail(exc)
    write_json_atomic(args.out, result)
    print(f"calibrations {result['calibration_s'] * 1e3:.1f} and {result['loading_calibration_s'] * 1e3:.1f} ms "
          f"a call; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
