"""Inference speed of the whole denoising chain against OIDN, side by side, per megapixel.

For each size (128x128, 256x256, 1280x720, 1920x1080), each model (registry names, checkpoint
files or expert specs; architecture presets with random weights and non-trivial BatchNorm
statistics — weights do not change speed) and each ``--spp`` it times what a user's call costs:
:meth:`denoise.denoiser.Denoiser.denoise_array` on a render made of two halves (image + variance:
sanitise, exposure, transfer, noise channels, tiles, the folded networks, their combination,
inverse, noise guard, energy correction) of that many samples per pixel, so each model runs the
networks meant for that spp (``unknown``: one image without variance or spp, what ``denoise`` runs
on a file that does not say its spp), the model loaded once as a user's program would, and
OIDN 2 colour-only (``pyoidn``) on the same image. A variant is named ``MODEL[@PRECISION]|SPP``;
``ratios`` gives, per size, each model's median per-process time ratio to OIDN at each spp.
Variants run round-robin, so a noisy neighbour slows them alike; each timed call follows an untimed
call of the same variant, the steady state of a program that denoises frame after frame (a
process's first call: :mod:`benchmarks.denoise_process`). Without it the variant after OIDN paid
for OIDN: ``fast`` at 720p took 1.24 s right after an OIDN call against 0.71 s after another
network's (median of five; docs/experiments.md). The median of ``--repeat`` runs is reported with
the load average seen (a busy machine makes every number worse and small images worst: torch's two
threads wait for each other at every layer). ``--threads`` sets torch's threads (0: the Denoiser's
own choice).

    python -m benchmarks.inference [--quick] [--sizes 128x128,256x256,1280x720,1920x1080]
        [--models fast,balanced,high] [--spp 4,16,128,unknown] [--precisions auto] [--repeat 5]
        [--processes 3] [--threads N] [--out benchmarks/results/inference.json]

``--processes N`` (default 3) repeats all of it in N fresh processes, one after the other, and pools
their runs: on this 2-core VM a process keeps its own speed (the same calls took 10.8-15.0 ms in
five processes at 128^2, and OIDN 25-43 ms), so one process is one sample of it. Each size's
figure is the median of all runs of all processes; beside it the range of the per-process
ratios to OIDN (``process_s_per_mp``: each process's median).

Each model runs in every ``--precisions`` float format (:mod:`denoise.precision`; a bfloat16 column
is named ``model@bfloat16``), or only in the one its ``--models`` entry names (``high@auto``: each
network in its own ``auto`` format); the JSON records whether the CPU computes bfloat16 natively.

Also prints where the time of one call goes at the smallest size (stages of the chain).
``--quick``: 256x256 only, one run. Prints a table and writes ``--out`` (default
benchmarks/results/inference.json). A candidate not yet trained is timed as ``PRESET:FIELD=INT``
(``unet-s:kernel=5``): the preset with those fields, random weights.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.readme_tables import ratio_range_text
from imaging.atomic_io import write_json_atomic
from console.usage import size_list
from model.architectures import build_model
from model.checkpoint import save_checkpoint
from model.config import PRESETS, preset
from denoise.precision import PRECISIONS, native_bfloat16
from model.unet import macs_per_pixel
from denoise.denoiser import Denoiser, select
from model.registry import registry
from imaging.errors import ConfigError, DenoiserError
from denoise.oidn import oidn_available, oidn_denoise

RESULTS = Path(__file__).resolve().parent / "results" / "inference.json"
SIZES = ((128, 128), (256, 256), (1280, 720), (1920, 1080))
SPPS = (4, 16, 128, "unknown")  # the default --spp: the cards' spp and a file that does not say it
STAGES_SPP = 4  # the spp of the stages' breakdown


def _preset_overrides(name: str) -> tuple[str, dict[str, int]] | None:
    """``PRESET[:FIELD=INT...]`` (``unet-s:kernel=5:growth=6``) as the preset and its integer field
    overrides, or None for a name that is no architecture preset."""
    base, _, rest = name.partition(":")
    if base not in PRESETS or base in registry().names:
        return None
    overrides: dict[str, int] = {}
    for item in filter(None, rest.split(":")):
        key, _, value = item.partition("=")
        try:
            overrides[key] = int(value)
        except ValueError:  # no "=", or not an integer after it
            raise ConfigError(f"{name!r}: an override is FIELD=INTEGER, got {item!r}") from None
    return base, overrides


def _checkpoint(name: str, folder: Path) -> str:
    """What ``Denoiser`` loads for a ``--models`` entry: an architecture preset, with optional
    integer field overrides (``unet-s:kernel=5``), gets random weights (as after training: BN
    statistics, a non-zero output conv) in ``folder``; anything else (a registry name, a checkpoint
    file, an expert spec) is passed on as it is."""
    parsed = _preset_overrides(name)
    if parsed is None:
        return name
    torch.manual_seed(0)
    model = build_model(preset(parsed[0], **parsed[1]))
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
        last = model.tail if model.config.multiscale else model.tail[-1]
        torch.nn.init.normal_(last.weight, std=0.01)
    path = folder / (re.sub(r"[^A-Za-z0-9_.-]", "_", name) + ".ckpt")
    save_checkpoint(path, model, step=0)
    return str(path)


def _render(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """A noisy render stand-in and its variance: gamma-distributed radiance around 0.5."""
    rng = np.random.default_rng(0)
    img = rng.gamma(2.0, 0.25, (height, width, 3)).astype(np.float32)
    return img, (0.05 * img * img).astype(np.float32)


def _macs(config: Any) -> float:
    if config.multiscale:
        return macs_per_pixel(config)
    c0, k, mid, n = config.init_features, config.growth, config.bottleneck * config.growth, config.layers
    return config.in_channels * 49 * c0 + sum((c0 + i * k) * mid + 9 * mid * k for i in range(n)) + \
        9 * (c0 + n * k) * 3


def denoiser_macs(den: Denoiser, spp: int | None) -> float:
    """MACs per pixel of a call at ``spp``: the networks that run there."""
    return sum(_macs(member.config) for member in den.active(spp))


def _spp(value: int | str) -> int | None:
    return None if value == "unknown" else int(value)


def call(den: Denoiser, img: np.ndarray, var: np.ndarray, spp: int | str) -> Any:
    """One user's call at ``spp``: the image and its variance, or for ``unknown`` the image alone."""
    if _spp(spp) is None:
        return den.denoise_array(img)
    return den.denoise_array(img, variance=var, spp=_spp(spp))


def measure_size(width: int, height: int, models: dict[str, Denoiser], repeat: int,
                 spps: list[int | str]) -> dict[str, Any]:
    """Median seconds of every model at every spp and of OIDN on one image size (round-robin
    over repeats, each timed call right after an untimed one of the same variant)."""
    img, var = _render(width, height)
    variants = {f"{name}|{spp}": (lambda d=den, s=spp: call(d, img, var, s))
                for name, den in models.items() for spp in spps}
    if oidn_available():
        variants["oidn"] = lambda: oidn_denoise(img)
    times: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(repeat):
        for key, fn in variants.items():
            # untimed: the timed call follows one of its own kind (module docstring); in the first
            # round this is the variant's warm-up (first-call allocations and kernel selection)
            fn()
            start = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - start)
    mp = width * height / 1e6
    return {key: {"seconds": statistics.median(v), "s_per_mp": statistics.median(v) / mp, "runs": v}
            for key, v in times.items()}


def stages(den: Denoiser, width: int, height: int, repeat: int) -> dict[str, float]:
    """Median milliseconds of the chain's stages for one call (profiled with torch's profiler
    would perturb them; these are the callable pieces timed alone)."""
    from denoise.chain import exposure_scale
    from model.noise_input import noise_channels
    from model.transfer import get_transfer
    from denoise.denoiser import count_invalid
    from denoise.noise_guard import guard_in_place

    img, var = _render(width, height)
    transfer = get_transfer(den.config.transfer)
    x = torch.rand(1, den.config.image_channels, height, width)
    out = den.denoise_array(img, variance=var, spp=STAGES_SPP).image
    parts = {
        "count_invalid": lambda: count_invalid(img),
        "exposure": lambda: exposure_scale(img),
        "transfer": lambda: transfer.forward(torch.from_numpy(img)),
        "noise_channels": lambda: noise_channels(img, var, transfer, den.config.noise_radius),
        "network": lambda: den.net(x),
        "guard": lambda: guard_in_place(img, out.copy(), var, np.empty((height, width, 1), np.float32),
                                        den.max_bytes),
        "whole call": lambda: den.denoise_array(img, variance=var, spp=STAGES_SPP),
    }
    result = {}
    with torch.inference_mode():
        for name, fn in parts.items():
            fn()
            runs = []
            for _ in range(repeat):
                start = time.perf_counter()
                fn()
                runs.append(time.perf_counter() - start)
            result[name] = 1000 * statistics.median(runs)
    return result


def _key(name: str, precision: str) -> str:
    """The column of a model in a float format: its name for ``auto`` (what a user gets),
    ``name@precision`` else."""
    return name if precision == "auto" else f"{name}@{precision}"


def ratios(sizes: dict[str, Any]) -> dict[str, dict[str, dict[str, float]]]:
    """Per size, each model's median per-process time ratio to OIDN at each spp (``MODEL|SPP``
    variants): ``{size: {model: {spp: ratio}}}``; empty without OIDN."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for size, row in sizes.items():
        oidn = row.get("oidn", {}).get("process_s_per_mp")
        if not oidn:
            continue
        for key, value in row.items():
            if "|" not in key:
                continue
            model, spp = key.split("|")
            per_process = [a / b for a, b in zip(value["process_s_per_mp"], oidn)]
            out.setdefault(size, {}).setdefault(model, {})[spp] = statistics.median(per_process)
    return out


def table(results: dict[str, Any]) -> list[str]:
    names = [k for k in next(iter(results["sizes"].values())) if k != "oidn"]
    lines = [f"{'size':>10} " + " ".join(f"{n + ' s/MP':>16}" for n in names) + f" {'OIDN s/MP':>10} "
             + " ".join(f"{n + '/OIDN':>22}" for n in names)]
    for size, row in results["sizes"].items():
        oidn = row.get("oidn", {}).get("s_per_mp")
        cells = " ".join(f"{row[n]['s_per_mp']:16.3f}" for n in names)
        ratios = []
        for n in names:
            text = f"{row[n]['s_per_mp'] / oidn:.2f}" if oidn else "-"
            ratios.append(f"{text + ratio_range_text(row, n):>22}")
        lines.append(f"{size:>10} {cells} {oidn if oidn else float('nan'):10.3f} " + " ".join(ratios))
    return lines


def measure_process(spec: dict[str, Any]) -> dict[str, Any]:
    """What one process measures: every size (:func:`measure_size`) and, when ``spec["stages"]``,
    the stages at the first size. ``spec``: checkpoint ``files`` by name, ``precisions`` (a
    model's own list by name) and ``all`` (the others'), ``sizes``, ``repeat``, ``threads``."""
    models = {_key(name, prec): Denoiser(path, threads=spec["threads"] or None, precision=prec)
              for name, path in spec["files"].items() for prec in spec["precisions"].get(name, spec["all"])}
    out: dict[str, Any] = {"models": list(models), "torch_threads": torch.get_num_threads(),
                           "macs_per_pixel": {f"{n}|{s}": denoiser_macs(m, _spp(s))
                                              for n, m in models.items() for s in spec["spp"]},
                           "sha256": {n: m.sha256 for n, m in models.items()},
                           "sizes": {}}
    for w, h in spec["sizes"]:
        row = out["sizes"][f"{w}x{h}"] = measure_size(w, h, models, spec["repeat"], spec["spp"])
        print(f"... {w}x{h}: " + ", ".join(f"{k} {v['s_per_mp']:.2f} s/MP" for k, v in row.items()),
              file=sys.stderr, flush=True)
    if spec["stages"]:
        w, h = spec["sizes"][0]
        out["stages_ms"] = {f"{w}x{h}": {n: stages(m, w, h, spec["repeat"]) for n, m in models.items()}}
    return out


def pool(processes: list[dict[str, Any]]) -> dict[str, Any]:
    """One size table from several processes' (:func:`measure_process`): per size and variant the
    median of all their runs, and each process's own median (``process_s_per_mp``)."""
    sizes: dict[str, Any] = {}
    for size in processes[0]["sizes"]:
        mp = math.prod(int(v) for v in size.split("x")) / 1e6
        sizes[size] = {}
        for key in processes[0]["sizes"][size]:
            runs = [r for p in processes for r in p["sizes"][size][key]["runs"]]
            sizes[size][key] = {"seconds": statistics.median(runs), "s_per_mp": statistics.median(runs) / mp,
                                "runs": runs,
                                "process_s_per_mp": [p["sizes"][size][key]["s_per_mp"] for p in processes]}
    return sizes


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="256x256 only, one run, one process")
    p.add_argument("--sizes", type=size_list, default=list(SIZES))
    p.add_argument("--models", default="fast,balanced,high",
                   help="registry names, checkpoint files, expert specs A+B or architecture presets (random "
                        "weights; PRESET:FIELD=INT[:FIELD=INT] overrides fields); NAME@PRECISION runs that "
                        "model in that float format only")
    p.add_argument("--spp", default=",".join(map(str, SPPS)),
                   help="comma-separated spp of the calls ('unknown': no spp and no variance)")
    p.add_argument("--precisions", default="auto",
                   help="float formats of the networks (denoise.precision.PRECISIONS)")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--processes", type=int, default=3, help="fresh processes whose runs are pooled")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: the Denoiser's choice)")
    p.add_argument("--out", type=Path, default=RESULTS, help=f"JSON written (default {RESULTS})")
    p.add_argument("--worker", nargs=2, metavar=("SPEC", "OUT"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:  # one process's share: read its spec, write its measurements
        spec_file, out_file = args.worker
        write_json_atomic(Path(out_file), measure_process(json.loads(Path(spec_file).read_text())))
        return
    if args.processes < 1 or args.repeat < 1:
        raise SystemExit("inference: --processes and --repeat must be at least 1")
    if args.out.is_dir() or not args.out.parent.is_dir():
        raise SystemExit(f"inference: --out {args.out}: give a file in an existing folder")
    precisions = args.precisions.split(",")
    spps: list[int | str] = [s if s == "unknown" else int(s) for s in args.spp.split(",")]
    if not set(precisions) <= set(PRECISIONS):
        raise SystemExit(f"inference: --precisions takes {', '.join(PRECISIONS)}, got {args.precisions!r}")
    sizes = [(256, 256)] if args.quick else args.sizes
    repeat = 1 if args.quick else args.repeat
    processes = 1 if args.quick else args.processes
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        entries = [entry.partition("@") for entry in args.models.split(",")]  # NAME[@PRECISION]
        try:
            files = {name: str(_checkpoint(name, Path(tmp))) for name, _, _ in entries}
        except ConfigError as exc:
            raise SystemExit(f"inference: {exc}") from None
        fixed = {name: [prec] for name, _, prec in entries if prec}
        if not {p for ps in fixed.values() for p in ps} <= set(PRECISIONS):
            raise SystemExit(f"inference: a model's @PRECISION takes {', '.join(PRECISIONS)}, got {args.models!r}")
        for name, model in files.items():
            try:
                select(model)
            except DenoiserError as exc:
                raise SystemExit(f"inference: {name}: {exc}") from None
        measured = []
        for i in range(processes):
            spec = {"files": files, "precisions": fixed, "all": precisions, "sizes": sizes,
                    "repeat": repeat, "threads": args.threads, "stages": i == 0, "spp": spps}
            spec_file, out_file = Path(tmp) / f"spec{i}.json", Path(tmp) / f"out{i}.json"
            spec_file.write_text(json.dumps(spec))
            print(f"process {i + 1}/{processes}", file=sys.stderr, flush=True)
            worker = subprocess.run([sys.executable, "-m", "benchmarks.inference", "--worker", str(spec_file),
                                     str(out_file)], cwd=Path(__file__).resolve().parents[1])
            if worker.returncode != 0:
                raise SystemExit(f"inference: measuring process {i + 1} failed (its error is above)")
            measured.append(json.loads(out_file.read_text()))
    first = measured[0]
    results: dict[str, Any] = {
        "command": " ".join(["python -m benchmarks.inference", *sys.argv[1:]]),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpus": os.cpu_count(), "torch": torch.__version__,
                    "torch_threads": first["torch_threads"], "loadavg_before": load_before,
                    "native_bfloat16": native_bfloat16(), "loadavg_after": os.getloadavg()},
        "quick": args.quick, "repeat": repeat, "processes": processes, "models": first["models"],
        "macs_per_pixel": first["macs_per_pixel"], "sha256": first["sha256"], "spp": spps,
        "sizes": pool(measured), "stages_ms": first["stages_ms"],
    }
    results["ratios"] = ratios(results["sizes"])
    print("\n".join(table(results)))
    for size, per_model in results["stages_ms"].items():
        for name, parts in per_model.items():
            print(f"{size} {name} ms: " + ", ".join(f"{k} {v:.1f}" for k, v in parts.items()))
    print(f"load average before/after: {load_before[0]:.2f} / {results['machine']['loadavg_after'][0]:.2f} "
          f"on {os.cpu_count()} CPUs")
    write_json_atomic(args.out, results)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
