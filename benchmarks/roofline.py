"""How fast can the paper's network possibly run on this CPU? Lower bounds from its convolutions alone.

The speed goals of issues 4 (training 4x the naive 28x28 patches/s) and 6 (inference: ``balanced``
no slower than OIDN, ``fast`` twice as fast) are set against what the network must compute. This
benchmark measures, on this machine:

* the CPU's practical float32 peak: a large square matrix product (``torch.mm``, 2048^2), GFLOP/s;
* every convolution of a preset **in isolation** (its exact channels and kernel, channels_last, warm,
  best of ``--repeat``), summed over the network: inference forward at 1 MP (1024x1024, no
  gradients) and a training step's forward + backward (input and weight gradients) on a batch of
  64 patches of 28x28. BatchNorm, ReLU, concatenation, loss and optimiser are left out, so the sum
  is a lower bound on the whole network's time that no fusion or layout change can beat without
  changing the convolutions themselves (their arithmetic: depth, growth, resolution).

It prints, per preset, the bound next to the goal: the inference bound in seconds per megapixel
against OIDN's measured s/MP (benchmarks/results/inference.json, same machine), and the training
bound in patches/s against 4x the naive rate (benchmarks/results/train_throughput.json).

    python -m benchmarks.roofline [--presets flat-s,flat-m,flat-l,paper] [--repeat 5]

Writes benchmarks/results/roofline.json.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from model.architectures import build_model
from model.config import preset

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
PATCH, BATCH = 28, 64
INFER_SIDE = 1024


def _best_time(fn: Any, repeat: int) -> float:
    """Fastest of ``repeat`` runs after a warm-up: for a lower bound (and a peak) the best case."""
    fn()  # warm-up: oneDNN picks and caches its kernel
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def matmul_peak(repeat: int, n: int = 2048) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    return 2 * n**3 / _best_time(lambda: torch.mm(a, b), repeat) / 1e9


def conv_shapes(name: str) -> list[tuple[int, int, int]]:
    """(in channels, out channels, kernel) of every convolution of a preset, in order."""
    return [(m.in_channels, m.out_channels, m.kernel_size[0])
            for m in build_model(preset(name)).modules() if isinstance(m, nn.Conv2d)]


def conv_forward_s(cin: int, cout: int, k: int, n: int, h: int, w: int, repeat: int) -> float:
    x = torch.randn(n, cin, h, w).contiguous(memory_format=torch.channels_last)
    weight = torch.randn(cout, cin, k, k).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        return _best_time(lambda: F.conv2d(x, weight, padding=k // 2), repeat)


def conv_train_s(cin: int, cout: int, k: int, repeat: int) -> float:
    x = torch.randn(BATCH, cin, PATCH, PATCH).contiguous(memory_format=torch.channels_last).requires_grad_()
    weight = torch.randn(cout, cin, k, k).contiguous(memory_format=torch.channels_last).requires_grad_()
    grad = torch.randn(BATCH, cout, PATCH, PATCH).contiguous(memory_format=torch.channels_last)

    def step() -> None:
        y = F.conv2d(x, weight, padding=k // 2)
        gx, gw = torch.autograd.grad(y, (x, weight), grad)
        del gx, gw
    return _best_time(step, repeat)


def measure(name: str, repeat: int) -> dict[str, Any]:
    shapes = conv_shapes(name)
    unique = sorted(set(shapes))
    fwd = {s: conv_forward_s(*s, 1, INFER_SIDE, INFER_SIDE, repeat) for s in unique}
    train = {s: conv_train_s(*s, repeat) for s in unique}
    infer_s = sum(fwd[s] for s in shapes)
    step_s = sum(train[s] for s in shapes)
    macs = sum(cin * cout * k * k for cin, cout, k in shapes)
    return {
        "convolutions": len(shapes), "macs_per_pixel": macs,
        "infer_conv_s_per_mp": infer_s / (INFER_SIDE**2 / 1e6),
        "infer_conv_gflops": 2 * macs * INFER_SIDE**2 / infer_s / 1e9,
        "train_conv_s_per_step": step_s,
        "train_patches_per_s_bound": BATCH / step_s,
        "train_conv_gflops": 3 * 2 * macs * BATCH * PATCH**2 / step_s / 1e9,
    }


def _load(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.exists() else {}


def goals(presets: list[str]) -> dict[str, Any]:
    """The goals from the measured figures of benchmarks/inference.py and train_throughput.py."""
    inf = _load(RESULTS / "inference.json")
    tt = _load(RESULTS / "train_throughput.json")
    oidn = {size: row["oidn"]["s_per_mp"] for size, row in inf.get("sizes", {}).items() if "oidn" in row}
    naive = {}
    for name in presets:
        variants = tt.get("presets", {}).get(name, {}).get("variants", {})
        row = variants.get("naive (NCHW, foreach Adam)")
        naive[name] = row["patches_per_s_median"] if row else None
    return {"oidn_s_per_mp": oidn, "naive_patches_per_s": naive}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", default="flat-s,flat-m,flat-l,paper")
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args()
    names = args.presets.split(",")
    peak = matmul_peak(args.repeat)
    rows = {name: measure(name, args.repeat) for name in names}
    target = goals(names)
    print(f"float32 matmul peak (2048^2, {torch.get_num_threads()} threads): {peak:.1f} GFLOP/s")
    print(f"{'preset':10}{'MAC/px':>9}{'conv s/MP':>11}{'GFLOP/s':>9}{'train bound p/s':>17}"
          f"{'GFLOP/s':>9}{'naive p/s':>11}{'4x naive':>10}")
    for name, r in rows.items():
        nv = target["naive_patches_per_s"].get(name)
        print(f"{name:10}{r['macs_per_pixel']:>9,}{r['infer_conv_s_per_mp']:>11.2f}{r['infer_conv_gflops']:>9.1f}"
              f"{r['train_patches_per_s_bound']:>17.1f}{r['train_conv_gflops']:>9.1f}"
              f"{nv if nv is not None else float('nan'):>11.1f}"
              f"{4 * nv if nv is not None else float('nan'):>10.1f}")
    print("OIDN s/MP (benchmarks/results/inference.json):",
          ", ".join(f"{k} {v:.2f}" for k, v in target["oidn_s_per_mp"].items() if v is not None))
    result = {"machine": {"cpu": platform.processor() or platform.machine(),
                          "threads": torch.get_num_threads(), "torch": torch.__version__,
                          "cpu_capability": torch.backends.cpu.get_cpu_capability()},
              "matmul_peak_gflops": peak, "infer_side": INFER_SIDE, "patch": PATCH, "batch": BATCH,
              "presets": rows, "goals": target}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "roofline.json").write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
