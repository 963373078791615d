"""Skipping the network where a render has already converged: time saved, output unchanged.

``Denoiser(skip_below=t)`` leaves the 64-px cells whose transfer-space noise (from the render's
two halves) is below ``t`` out of the network: they come back as the render, and the network runs
on the smallest aligned rectangle holding every noisy cell (:func:`denoise.chain.denoise_image`).
The noise guard would keep the render there anyway; this measures what skipping changes on the
user's path (render in halves -> :meth:`denoise.denoiser.Denoiser.denoise_render`: noise input,
network, guard), for three renders of the demo scene:

* ``converged`` — 4096 spp;
* ``mixed``     — the left half of the image from the 4096-spp render, the right half from a
  16-spp one (image and variance both), as a render whose background converged first would be;
* ``noisy``     — 16 spp (nothing to skip: the cost of the test itself).

For each threshold: the median seconds of the call with and without skipping, the share of pixels
left out, and how much the output moved (largest absolute and relative radiance change, PSNR of
each against a 16384-spp reference).

    python -m benchmarks.skip [--model CKPT] [--size 256] [--thresholds 0.001,0.003,0.01] [--repeat 3]

Writes benchmarks/results/skip.json.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import write_json_atomic
from imaging.metrics import psnr
from rendering.render import load_scene, prepare, render_loaded
from model.architectures import alignment
from denoise.chain import noisy_region
from model.transfer import get_transfer
from denoise.denoiser import Denoiser
from denoise.noise_guard import strength_for

RESULTS = Path(__file__).resolve().parent / "results" / "skip.json"
DEMO = Path(__file__).resolve().parents[1] / "scenes" / "examples" / "demo.xml"


def renders(size: int) -> dict[str, Any]:
    """The three renders (rgb, variance, spp) and a 16384-spp reference of the demo scene."""
    scene = load_scene(prepare(DEMO, (size, size)))
    converged = render_loaded(scene, 4096, seed=1, halves=True)
    noisy = render_loaded(scene, 16, seed=2, halves=True)
    reference = render_loaded(scene, 16384, seed=3).rgb
    half = size // 2
    mixed_rgb = np.concatenate([converged.rgb[:, :half], noisy.rgb[:, half:]], axis=1)
    mixed_var = np.concatenate([converged.variance[:, :half], noisy.variance[:, half:]], axis=1)
    return {"cases": {"converged": (converged.rgb, converged.variance, 4096),
                      "mixed": (mixed_rgb, mixed_var, 16),
                      "noisy": (noisy.rgb, noisy.variance, 16)},
            "reference": reference}


def _median_time(fn: Any, repeat: int) -> tuple[float, Any]:
    out = fn()
    runs = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - start)
    return statistics.median(runs), out


def measure(model: str | None, size: int, thresholds: list[float], repeat: int) -> dict[str, Any]:
    data = renders(size)
    ref = data["reference"]
    full = Denoiser(model)
    transfer = get_transfer(full.config.transfer)
    results: dict[str, Any] = {"model": str(full.path), "size": size, "cases": {}}
    for name, (rgb, var, spp) in data["cases"].items():
        strength = strength_for(spp)
        base_s, base = _median_time(lambda: full.denoise_array(rgb, variance=var, strength=strength).image, repeat)
        case: dict[str, Any] = {"spp": spp, "seconds_without_skip": base_s, "psnr_noisy": psnr(rgb, ref),
                                "psnr_without_skip": psnr(base, ref), "thresholds": {}}
        for t in thresholds:
            skipping = Denoiser(model, skip_below=t)
            secs, out = _median_time(lambda: skipping.denoise_array(rgb, variance=var, strength=strength).image,
                                     repeat)
            region = noisy_region(rgb, var, transfer, 1.0, t, alignment(full.config))
            run_share = 0.0 if region is None else (region[1] - region[0]) * (region[3] - region[2]) / (size * size)
            diff = np.abs(out.astype(np.float64) - base)
            case["thresholds"][str(t)] = {
                "seconds": secs, "time_saved": 1.0 - secs / base_s, "network_share_of_pixels": run_share,
                "max_abs_change": float(diff.max()),
                "max_rel_change": float((diff / (np.abs(base) + 1e-3)).max()),
                "psnr": psnr(out, ref)}
        results["cases"][name] = case
    return results


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default=None, help="checkpoint (default: the shipped default)")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--thresholds", default="0.001,0.003,0.01")
    p.add_argument("--repeat", type=int, default=3)
    args = p.parse_args()
    load = os.getloadavg()
    results = measure(args.model, args.size, [float(t) for t in args.thresholds.split(",")], args.repeat)
    results.update(command=" ".join(["python -m benchmarks.skip", *sys.argv[1:]]),
                   date=time.strftime("%Y-%m-%d %H:%M"), loadavg_before=load, loadavg_after=os.getloadavg())
    for name, case in results["cases"].items():
        print(f"{name} ({case['spp']} spp): without skipping {case['seconds_without_skip']:.3f} s, "
              f"PSNR noisy {case['psnr_noisy']:.2f} / denoised {case['psnr_without_skip']:.2f} dB")
        for t, r in case["thresholds"].items():
            print(f"  skip below {t}: {r['seconds']:.3f} s ({100 * r['time_saved']:.0f}% saved, network on "
                  f"{100 * r['network_share_of_pixels']:.0f}% of pixels), PSNR {r['psnr']:.2f} dB, "
                  f"max change {r['max_abs_change']:.2e} (rel {r['max_rel_change']:.2e})")
    write_json_atomic(RESULTS, results)
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
