"""Training throughput (patches/s) on the CPU, per model preset and per speed option.

Every variant runs the trainer's real step (:func:`training.step.train_step`: forward, loss, NaN
guard, backward, Adam) on 28x28 patches. Variants of one preset are measured round-robin, so a
noisy neighbour slows them all alike; the median and best round are reported, together with the
share of CPU time other processes used meanwhile. An equivalence check computes the loss and gradient of each
batch-64 variant from one initialisation on one batch against a float64 computation of the same
step; exact variants should show the same float32 rounding error as naive, bf16 shows its own
(what "does not change what is learned" means in numbers).

    python -m benchmarks.train_throughput [--presets flat-s flat-m flat-l] [--rounds 3]
        [--steps 3] [--no-compile] [--quick]

Prints a table and writes benchmarks/results/train_throughput.json (presets not measured in this
run keep their earlier entries).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from model.config import preset
from model.architectures import build_model, count_parameters
from training.patches import PatchConfig, TrainingPair, sample_batch
from training.loss import denoising_loss
from training.step import NonFiniteGuard, train_step
from training.batches import to_tensor

RESULTS = Path(__file__).resolve().parent / "results" / "train_throughput.json"
PATCH = 28


@dataclass(frozen=True)
class Variant:
    """One way of running the same training step. ``same_learning``: identical maths to naive
    (up to float summation order); False for bf16 and for other batch sizes."""

    name: str
    channels_last: bool = True
    fused_adam: bool = True
    bf16: bool = False
    compile: bool = False
    threads: int = 0
    batch: int = 64
    micro_batch: int | None = None
    sampling: str = "none"  # "none": fixed tensors; "sync"/"prefetch": sample patches from RAM each step
    same_learning: bool = True


VARIANTS = [
    Variant("naive (NCHW, foreach Adam)", channels_last=False, fused_adam=False),
    Variant("channels_last", fused_adam=False),
    Variant("channels_last + fused Adam [default]"),
    Variant("default + patch sampling in loop", sampling="sync"),
    Variant("default + patch sampling prefetched", sampling="prefetch"),
    Variant("default, 1 thread", threads=1),
    Variant("default + torch.compile", compile=True),
    Variant("default + bf16 autocast", bf16=True, same_learning=False),
    Variant("default, batch 64 as 2x32 micro-batches", micro_batch=32, same_learning=False),
    Variant("default, batch 64 as 4x16 micro-batches", micro_batch=16, same_learning=False),
    Variant("default, batch 32", batch=32, same_learning=False),
    Variant("default, batch 128", batch=128, same_learning=False),
]


def _pairs(seed: int = 0) -> list[TrainingPair]:
    rng = np.random.default_rng(seed)
    pairs = []
    for i in range(8):
        ref = (rng.random((128, 128, 3), dtype=np.float32) * 0.3 + 0.1)
        noisy = np.clip(ref + 0.05 * rng.standard_normal(ref.shape).astype(np.float32), 0, None)
        pairs.append(TrainingPair(noisy, ref, i, 4))
    return pairs


def _make_step(preset_name: str, v: Variant, pairs: list[TrainingPair],
               seed: int = 0) -> tuple[Callable[[int], float], torch.nn.Module]:
    torch.manual_seed(seed)
    model = build_model(preset(preset_name))
    if v.channels_last:
        model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, fused=True if v.fused_adam else None)
    net = torch.compile(model) if v.compile else model
    guard = NonFiniteGuard(1000)
    pool = None
    if v.sampling == "prefetch":
        from concurrent.futures import ThreadPoolExecutor
        pool = ThreadPoolExecutor(1)
    pending: dict[int, object] = {}

    def batch(step: int) -> tuple[torch.Tensor, torch.Tensor]:
        def make(s: int) -> tuple[np.ndarray, np.ndarray]:
            return sample_batch(pairs, v.batch, PatchConfig(size=PATCH), np.random.default_rng([seed, s]))
        if pool is not None:
            fut = pending.pop(step, None)
            noisy, ref = fut.result() if fut is not None else make(step)
            pending[step + 1] = pool.submit(make, step + 1)
        else:
            noisy, ref = make(step)
        return to_tensor(noisy, v.channels_last), to_tensor(ref, v.channels_last)

    fixed = batch(0) if v.sampling == "none" else None

    def step(s: int) -> float:
        noisy, ref = fixed if fixed is not None else batch(s)
        prev = torch.get_num_threads()
        if v.threads:
            torch.set_num_threads(v.threads)
        try:
            return train_step(net, opt, noisy, ref, step=s, lr=1e-3, guard=guard, bf16=v.bf16,
                              micro_batch=v.micro_batch).loss
        finally:
            torch.set_num_threads(prev)
    return step, model


def _busy_jiffies() -> int:
    with open("/proc/stat") as fh:
        parts = [int(x) for x in fh.readline().split()[1:]]
    return sum(parts) - parts[3] - parts[4]  # minus idle and iowait


def _own_jiffies() -> float:
    t = os.times()
    return (t.user + t.system) * os.sysconf("SC_CLK_TCK")


def measure(preset_name: str, variants: list[Variant], rounds: int, steps: int, pairs: list[TrainingPair]) -> dict:
    """Round-robin throughput of each variant of one preset."""
    steppers = {}
    for v in variants:
        t0 = time.perf_counter()
        step, _ = _make_step(preset_name, v, pairs)
        step(0), step(1)
        steppers[v.name] = (v, step, time.perf_counter() - t0)
        print(f"  warmed up {v.name} ({time.perf_counter() - t0:.1f}s)", file=sys.stderr, flush=True)
    rates: dict[str, list[float]] = {v.name: [] for v in variants}
    busy0, own0 = _busy_jiffies(), _own_jiffies()
    counter = 2
    for _ in range(rounds):
        for name, (v, step, _) in steppers.items():
            t0 = time.perf_counter()
            for _ in range(steps):
                step(counter)
                counter += 1
            rates[name].append(v.batch * steps / (time.perf_counter() - t0))
    busy, own = _busy_jiffies() - busy0, _own_jiffies() - own0
    naive = statistics.median(rates[variants[0].name])
    out = {}
    for name, (v, _, warm) in steppers.items():
        med = statistics.median(rates[name])
        out[name] = {"patches_per_s_median": round(med, 2), "patches_per_s_best": round(max(rates[name]), 2),
                     "rounds": [round(r, 2) for r in rates[name]], "speedup_vs_naive": round(med / naive, 2),
                     "warmup_s": round(warm, 1), "same_learning_as_naive": v.same_learning,
                     "config": dataclasses.asdict(v)}
    return {"variants": out, "foreign_cpu_share": round(max(0.0, busy - own) / max(busy, 1), 3)}


def _gradient(preset_name: str, v: Variant | None, pairs: list[TrainingPair]) -> tuple[float, torch.Tensor]:
    """Loss and flat gradient of one fixed batch from one initialisation; ``v=None``: float64."""
    torch.manual_seed(1)
    model = build_model(preset(preset_name))
    noisy, ref = sample_batch(pairs, 64, PatchConfig(size=PATCH), np.random.default_rng([1, 0]))
    if v is None:
        model = model.double()
        out = model(to_tensor(noisy, False).double())
        loss = denoising_loss(out.double(), to_tensor(ref, False).double())
    else:
        if v.channels_last:
            model = model.to(memory_format=torch.channels_last)
        net = torch.compile(model) if v.compile else model
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=v.bf16):
            out = net(to_tensor(noisy, v.channels_last))
        loss = denoising_loss(out, to_tensor(ref, v.channels_last))
    loss.backward()
    return float(loss.detach()), torch.cat([p.grad.reshape(-1).double() for p in model.parameters()])


def equivalence(preset_name: str, variants: list[Variant], pairs: list[TrainingPair]) -> dict:
    """Loss and gradient error of each batch-64 variant against a float64 computation of the same
    step (the naive float32 variant's own error is the floor every exact variant should match)."""
    ref_loss, ref_grad = _gradient(preset_name, None, pairs)
    results = {}
    for v in variants:
        if v.batch != 64 or v.sampling != "none" or v.micro_batch:
            continue
        loss, grad = _gradient(preset_name, v, pairs)
        results[v.name] = {"loss_rel_err_vs_fp64": abs(loss - ref_loss) / abs(ref_loss),
                           "grad_rel_l2_err_vs_fp64": float((grad - ref_grad).norm() / ref_grad.norm())}
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["flat-s", "flat-m", "flat-l"])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=3, help="steps per variant per round")
    parser.add_argument("--no-compile", action="store_true", help="skip the torch.compile variant")
    parser.add_argument("--quick", action="store_true", help="naive vs default only")
    args = parser.parse_args()
    variants = [v for v in VARIANTS if not (args.no_compile and v.compile)]
    if args.quick:
        variants = variants[:3]
    pairs = _pairs()
    result = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                          "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
                          "cpu_capability": torch.backends.cpu.get_cpu_capability()},
              "settings": {"patch": PATCH, "batch": 64, "model_init_seed": 0},
              "presets": {}}
    if RESULTS.exists():  # keep presets measured by earlier runs (each entry carries its own time)
        result["presets"] = json.loads(RESULTS.read_text()).get("presets", {})
    for name in args.presets:
        print(f"{name}:", file=sys.stderr, flush=True)
        load_before = os.getloadavg()
        entry = measure(name, variants, args.rounds, args.steps, pairs)
        entry.update(measured_at=time.strftime("%Y-%m-%dT%H:%M:%S"), loadavg_before=load_before,
                     loadavg_after=os.getloadavg(), rounds=args.rounds, steps_per_round=args.steps)
        entry["params"] = count_parameters(build_model(preset(name)))
        entry["equivalence"] = equivalence(name, variants, pairs)
        result["presets"][name] = entry
        print(f"\n{name} ({entry['params']:,} params; other processes used {entry['foreign_cpu_share']:.0%} "
              f"of busy CPU time meanwhile)")
        for vname, r in entry["variants"].items():
            eq = entry["equivalence"].get(vname)
            eqs = f"  grad err vs fp64 {eq['grad_rel_l2_err_vs_fp64']:.1e}" if eq else ""
            print(f"  {vname:40s} {r['patches_per_s_median']:7.1f} patches/s (best {r['patches_per_s_best']:6.1f})"
                  f"  x{r['speedup_vs_naive']:.2f}{eqs}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
