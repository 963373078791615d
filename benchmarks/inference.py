"""Inference speed: our network (plain and optimised) against OIDN, side by side, per megapixel.

For each size (256x256, 1280x720, 1920x1080) and each preset (fast, balanced, high; random
weights with non-trivial BatchNorm statistics — weights do not change speed) it times the whole
denoising chain (:class:`pipeline.denoise.Denoiser`: sanitise, transfer, tiles, network, inverse)
with the training module (``plain``) and with the folded inference network (``optimised``,
:mod:`model.inference_net`), and OIDN 2 colour-only (``pyoidn``) on the same image. Variants run
round-robin, so a noisy neighbour slows them alike; the median of ``--repeat`` runs is reported
with the load average seen (a busy machine makes every number worse, the ratios less so). It
also checks that optimised equals plain: both against the plain module run in float64.

    .venv/bin/python benchmarks/inference.py [--quick] [--sizes 256x256,1280x720,1920x1080]
        [--presets fast,balanced,high] [--repeat 3] [--threads N]

``--quick``: 256x256 only, one run. Prints a table and writes benchmarks/results/inference.json.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.checkpoint import save_checkpoint  # noqa: E402
from model.config import preset  # noqa: E402
from model.architectures import build_model  # noqa: E402
from pipeline.denoise import Denoiser  # noqa: E402
from pipeline.oidn import oidn_available, oidn_denoise  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "inference.json"
SIZES = ((256, 256), (1280, 720), (1920, 1080))


def _checkpoint(name: str, folder: Path) -> Path:
    torch.manual_seed(0)
    model = build_model(preset(name))
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
        torch.nn.init.normal_(model.tail[-1].weight, std=0.01)
    path = folder / f"{name}.ckpt"
    save_checkpoint(path, model, step=0)
    return path


def _image(width: int, height: int) -> np.ndarray:
    """A noisy HDR-ish render stand-in: gamma-distributed radiance around 0.5."""
    return np.random.default_rng(0).gamma(2.0, 0.25, (height, width, 3)).astype(np.float32)


def _time(fn: Any) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def measure_size(width: int, height: int, pairs: dict[str, tuple[Denoiser, Denoiser]],
                 repeat: int) -> dict[str, Any]:
    """Median seconds of every variant on one image size (round-robin over the repeats).
    ``pairs``: preset -> (plain, optimised) denoisers of the same checkpoint."""
    img = _image(width, height)
    variants = {}
    for name, (plain, opt) in pairs.items():
        variants[f"{name}/plain"] = lambda d=plain: d.denoise_array(img)
        variants[f"{name}/optimised"] = lambda d=opt: d.denoise_array(img)
    if oidn_available():
        variants["oidn"] = lambda: oidn_denoise(img)
    small = _image(64, 64)
    for plain, opt in pairs.values():
        plain.denoise_array(small)
        opt.denoise_array(small)
    if oidn_available():
        oidn_denoise(small)
    times: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(repeat):
        for key, fn in variants.items():
            times[key].append(_time(fn))
    mp = width * height / 1e6
    return {key: {"seconds": statistics.median(v), "s_per_mp": statistics.median(v) / mp, "runs": v}
            for key, v in times.items()}


def equivalence(pairs: dict[str, tuple[Denoiser, Denoiser]], side: int = 64) -> dict[str, Any]:
    """Network outputs (transfer space) of plain and optimised float32 against the plain module in
    float64: the optimised error should be float32 rounding, like the plain one's. Also the
    largest relative radiance difference of the two whole chains."""
    x = torch.rand(1, 3, side, side, generator=torch.Generator().manual_seed(0)) * 0.1
    img = _image(side, side)
    out = {}
    for name, (plain, opt) in pairs.items():
        with torch.inference_mode():
            ref = copy.deepcopy(plain.model).double()(x.double())
            err_plain = float((plain.model(x).double() - ref).abs().max())
            err_opt = float((opt.net(x).double() - ref).abs().max())
        a, b = plain.denoise_array(img).image, opt.denoise_array(img).image
        out[name] = {"max_abs_err_vs_float64_plain": err_plain, "max_abs_err_vs_float64_optimised": err_opt,
                     "output_scale": float(ref.abs().max()),
                     "max_rel_radiance_diff": float(np.max(np.abs(b - a) / (np.abs(a) + 1e-3)))}
    return out


def table(results: dict[str, Any]) -> list[str]:
    lines = [f"{'size':>10} {'preset':>9} {'plain s/MP':>11} {'opt s/MP':>9} {'speed-up':>9} "
             f"{'OIDN s/MP':>10} {'opt/OIDN':>9}"]
    for size, row in results["sizes"].items():
        oidn = row.get("oidn", {}).get("s_per_mp")
        for name in results["presets"]:
            plain, opt = row[f"{name}/plain"]["s_per_mp"], row[f"{name}/optimised"]["s_per_mp"]
            ratio = f"{opt / oidn:9.2f}" if oidn else f"{'-':>9}"
            lines.append(f"{size:>10} {name:>9} {plain:11.3f} {opt:9.3f} {plain / opt:8.2f}x "
                         f"{oidn if oidn else float('nan'):10.3f} {ratio}")
    return lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="256x256 only, one run")
    p.add_argument("--sizes", default=",".join(f"{w}x{h}" for w, h in SIZES))
    p.add_argument("--presets", default="fast,balanced,high")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    sizes = ([(256, 256)] if args.quick
             else [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")])
    repeat = 1 if args.quick else args.repeat
    presets = args.presets.split(",")
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        paths = {name: _checkpoint(name, Path(tmp)) for name in presets}
        pairs = {name: (Denoiser(path, optimize=False), Denoiser(path)) for name, path in paths.items()}
        results: dict[str, Any] = {
            "machine": {"platform": platform.platform(), "processor": platform.processor(),
                        "cpus": os.cpu_count(), "torch": torch.__version__,
                        "torch_threads": torch.get_num_threads(), "loadavg_before": load_before},
            "quick": args.quick, "repeat": repeat, "presets": presets, "sizes": {},
            "equivalence": equivalence(pairs),
        }
        for w, h in sizes:
            results["sizes"][f"{w}x{h}"] = measure_size(w, h, pairs, repeat)
            print(f"... {w}x{h} done", file=sys.stderr)
    results["machine"]["loadavg_after"] = os.getloadavg()
    print("\n".join(table(results)))
    for name, eq in results["equivalence"].items():
        print(f"{name}: |error| vs float64 plain {eq['max_abs_err_vs_float64_plain']:.1e}, optimised "
              f"{eq['max_abs_err_vs_float64_optimised']:.1e} (output scale {eq['output_scale']:.2f}); "
              f"radiance rel. diff {eq['max_rel_radiance_diff']:.1e}")
    print(f"load average before/after: {load_before[0]:.2f} / {results['machine']['loadavg_after'][0]:.2f} "
          f"on {os.cpu_count()} CPUs")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
