"""The figures behind the robustness tests (tests/test_extremes.py): energy preservation, PSNR of a
converged 4096-spp image before and after denoising, and peak memory denoising an 8K image.

    python -m benchmarks.extremes [--model PATH] [--quick] [--size 7680x4320]
        [--max-memory-mb 1024] [--parts energy,converged,memory]

* energy: scenes rendered at 16 spp (the bundled demo; without --quick also three eval scenes from
  ../shared/eval-scenes): mean radiance of the denoised image / that of the noisy input (an unbiased
  estimate), at the render's own exposure and rescaled to mean 1e-4 and 1e3 (then scaled back);
  plus the largest output for an all-zero image and the interior error for constant images.
* converged: the demo at 4096 spp (24 px; without --quick also 64 px) against a 16384-spp
  reference: tonemapped PSNR of the noisy render, the model alone and the model with the noise
  guard (denoise/noise_guard.py, render-and-denoise's default).
* memory: a child process denoises a WxH HDR image (default 7680x4320, --quick 960x540) under
  ``--max-memory-mb``; its peak RSS (ru_maxrss) against its RSS before the call (model loaded,
  image in RAM, one small warm-up image denoised).

Prints a table and writes benchmarks/results/extremes.json (the entry of the other mode is kept).
The model defaults to the registry's default (model.registry); an ensemble's members
run as for the spp of each image (energy: 16; constants, zero and memory: 1; the default runs two
networks at any spp, its U-Nets of one shape).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


from benchmarks.eval_scenes import eval_scenes
from imaging.errors import DenoiserError
from imaging.metrics import psnr
from rendering.render import render
from denoise.denoiser import Denoiser
from denoise.ensemble import SEPARATOR

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "extremes.json"
DEMO = ROOT / "scenes" / "examples" / "demo.xml"
EVAL_SCENES = ("cbox_spectral", "matpreview_plastic", "bitterli_veach_mis")
EXPOSURES = (1e-4, 1e3)
CONSTANTS = (0.01, 0.18, 1.0, 100.0)
PARTS = ("energy", "converged", "memory")


def _scene(name: str, res: tuple[int, int]) -> tuple[Path, dict[str, str], tuple[int, int] | None]:
    if name == "demo":
        return DEMO, {}, res
    return eval_scenes([name])[0].folder / "scene.xml", {"resx": str(res[0]), "resy": str(res[1])}, None


def energy(den: Denoiser, names: list[str], res: tuple[int, int]) -> dict[str, Any]:
    """Mean radiance ratios denoised / noisy at 16 spp, own exposure and rescaled."""
    rows = {}
    for name in names:
        path, params, resolution = _scene(name, res)
        noisy = render(path, 16, seed=3, resolution=resolution, params=params).rgb
        mean = float(noisy.mean())
        row = {"noisy_mean": mean, "ratio": float(den.denoise_array(noisy, spp=16).image.mean()) / mean}
        for target in EXPOSURES:
            scale = target / mean
            out = den.denoise_array(noisy * scale, spp=16).image / scale
            row[f"ratio_at_mean_{target:g}"] = float(out.mean()) / mean
        rows[name] = row
    zero = den.denoise_array(np.zeros((64, 64, 3), np.float32), spp=1).image
    constants = {}
    r = den.margin  # the interior: pixels that see no border
    for value in CONSTANTS:
        interior = den.denoise_array(np.full((2 * r + 16, 2 * r + 16, 3), value, np.float32), spp=1).image[r:-r, r:-r]
        constants[f"{value:g}"] = {"mean_rel_error": float(interior.mean() / value - 1),
                                   "std_rel": float(interior.std() / value)}
    worst = max(abs(row[k] - 1) for row in rows.values() for k in row if k.startswith("ratio"))
    return {"scenes": rows, "zero_max": float(zero.max()), "constants": constants,
            "worst_ratio_error": worst}


def converged(den: Denoiser, sizes: tuple[int, ...]) -> dict[str, Any]:
    """PSNR against a 16384-spp reference of the demo at 4096 spp (a render in two halves): noisy,
    the model alone, and the model with the noise guard (render-and-denoise's default)."""
    rows = {}
    for size in sizes:
        noisy = render(DEMO, 4096, seed=1, resolution=(size, size), halves=True)
        reference = render(DEMO, 16384, seed=2, resolution=(size, size)).rgb
        out = den.denoise_array(noisy.rgb, spp=noisy.spp).image
        guarded = den.denoise_render(noisy).image
        rows[str(size)] = {"psnr_noisy_db": psnr(noisy.rgb, reference), "psnr_denoised_db": psnr(out, reference),
                           "psnr_guarded_db": psnr(guarded, reference),
                           "mean_ratio": float(out.mean() / noisy.rgb.mean()),
                           "mean_ratio_guarded": float(guarded.mean() / noisy.rgb.mean())}
    return rows


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def memory_child(model: str, width: int, height: int, max_memory_mb: float) -> dict[str, Any]:
    """Runs in a fresh process: denoise one WxH image, report RSS figures (MiB) and time."""
    den = Denoiser(model, max_memory_mb=max_memory_mb)
    rng = np.random.default_rng(0)
    image = (rng.random((height, width, 3), dtype=np.float32) * 4.0).astype(np.float32, copy=False)
    den.denoise_array(image[:64, :64], spp=1)  # warm-up: one-time allocations are not the image's
    base = _rss_mb()
    start = time.perf_counter()
    result = den.denoise_array(image, spp=1)  # an ensemble's low-spp members
    seconds = time.perf_counter() - start
    peak = _rss_mb()
    assert np.isfinite(result.image).all()
    return {"width": width, "height": height, "max_memory_mb": max_memory_mb, "core": list(den.cores(height, width)),
            "tiles": result.tiles, "image_mb": image.nbytes / 2**20, "base_rss_mb": base,
            "peak_rss_mb": peak, "over_base_mb": peak - base, "seconds": seconds,
            "megapixels_per_s": width * height / 1e6 / seconds}


def memory(model: str, width: int, height: int, max_memory_mb: float) -> dict[str, Any]:
    code = ("import json, sys; from benchmarks.extremes import memory_child; "  # cwd ROOT: importable
            "print(json.dumps(memory_child(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))))")
    proc = subprocess.run([sys.executable, "-c", code, model, str(width), str(height), str(max_memory_mb)],
                          capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"extremes: memory child failed: {proc.stderr.strip().splitlines()[-1:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _table(result: dict[str, Any]) -> list[str]:
    e, c, m = result["energy"], result["converged"], result["memory"]
    lines = [f"model {result['model']} ({result['mode']}, {result['machine']})", "",
             f"{'energy (denoised/noisy mean)':34}{'own':>8}" + "".join(f"{f'@{t:g}':>9}" for t in EXPOSURES)]
    for name, row in e["scenes"].items():
        lines.append(f"{name:34}{row['ratio']:>8.4f}" + "".join(f"{row[f'ratio_at_mean_{t:g}']:>9.4f}"
                                                              for t in EXPOSURES))
    lines.append(f"worst |ratio - 1|: {e['worst_ratio_error']:.4f}; all-zero image -> max {e['zero_max']:.3g}")
    lines.append("constant images (interior): " + ", ".join(
        f"{v}: mean {row['mean_rel_error']:+.4f} std {row['std_rel']:.4f}" for v, row in e["constants"].items()))
    lines.append("")
    for size, row in c.items():
        lines.append(f"demo {size}px at 4096 spp vs 16384-spp reference: PSNR noisy {row['psnr_noisy_db']:.2f} dB, "
                     f"model {row['psnr_denoised_db']:.2f} dB ({row['psnr_denoised_db'] - row['psnr_noisy_db']:+.2f}), "
                     f"with the noise guard {row['psnr_guarded_db']:.2f} dB "
                     f"({row['psnr_guarded_db'] - row['psnr_noisy_db']:+.2f})")
    lines += ["", f"memory {m['width']}x{m['height']} ({m['image_mb']:.0f} MiB image) under --max-memory-mb "
              f"{m['max_memory_mb']:g}: peak RSS {m['peak_rss_mb']:.0f} MiB, {m['over_base_mb']:.0f} MiB over the "
              f"process before the call; {m['tiles']} tiles of core {m['core']}, {m['seconds']:.1f} s "
              f"({m['megapixels_per_s']:.3f} Mpx/s)"]
    return lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--model", help="checkpoint, preset or ensemble (default: the shipped default)")
    p.add_argument("--quick", action="store_true", help="demo only, small images, 960x540 memory run")
    p.add_argument("--size", help="memory run image WxH (default 7680x4320, --quick 960x540)")
    p.add_argument("--max-memory-mb", type=float, default=1024.0)
    p.add_argument("--parts", default=",".join(PARTS),
                   help="comma-separated parts to measure (the others keep their recorded figures)")
    args = p.parse_args()
    parts = set(args.parts.split(","))
    if not parts <= set(PARTS):
        raise SystemExit(f"extremes: unknown part in --parts {args.parts!r}")
    width, height = (int(v) for v in (args.size or ("960x540" if args.quick else "7680x4320")).split("x"))
    try:
        den = Denoiser(args.model, max_memory_mb=args.max_memory_mb)
    except DenoiserError as exc:
        raise SystemExit(f"extremes: {exc}") from None
    model = SEPARATOR.join(m.spec for m in den.members)  # the memory child loads the same members and ranges
    mode = "quick" if args.quick else "full"
    names = ["demo"] + ([] if args.quick else [s.name for s in eval_scenes(EVAL_SCENES)])
    previous = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    result = {k: v for k, v in previous.get(mode, {}).items() if k in PARTS}
    result.update({
        "command": shlex.join(["python", "-m", "benchmarks.extremes", *sys.argv[1:]]),
        "date": time.strftime("%Y-%m-%d %H:%M"), "parts_measured": sorted(parts),
        "mode": mode, "model": den.name, "model_sha256": den.sha256,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores (load {os.getloadavg()[0]:.1f} at start)",
    })
    if "energy" in parts:
        result["energy"] = energy(den, names, (48, 48) if args.quick else (128, 96))
    if "converged" in parts:
        result["converged"] = converged(den, (24,) if args.quick else (24, 64))
    if "memory" in parts:
        result["memory"] = memory(model, width, height, args.max_memory_mb)
    if not set(PARTS) <= set(result):
        raise SystemExit("extremes: no recorded figures for the parts not measured; run all parts once")
    print("\n".join(_table(result)))
    previous[mode] = result
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(previous, indent=1) + "\n")
    print(f"\nwrote {RESULTS.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
