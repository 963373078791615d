"""Peak memory of the render step (rendering.render.render_loaded) at 1080p, 4K and 8K.

    .venv/bin/python benchmarks/render_memory.py [--before REV] [--budgets 256,1024] [--spp 2]
        [--sizes 1920x1080,3840x2160,7680x4320] [--parts calibrate,sizes] [--quick]

Every figure comes from a fresh child process that loads the bundled demo scene, then renders it
as render-and-denoise does (two halves for the noise guard; ``--aovs`` adds albedo and normals).
The child resets its own high-water mark (``/proc/self/clear_refs``) after loading the scene, so
the peak is the render's alone; **scratch** = peak - RSS before the render - the returned images
(what ``--max-memory-mb`` bounds). Each child starts with an empty Dr.Jit kernel cache (its own
HOME), so kernel compilation is always counted: the worst case.

* calibrate: the memory model of rendering/render_crops.py. Scratch of one-piece renders at two
  film sizes (slope = bytes per pixel, intercept = fixed cost) for 3 and 9 channels, with and
  without halves; and of one pass at 1, 16 and 64 spp on one film (slope = bytes per sample in
  flight).
* sizes: 1920x1080, 3840x2160 and 7680x4320 at ``--spp`` with each budget, and "before": the
  same render with the code of ``--before REV`` (git archive of pipeline/, before film crops),
  which has no budget.

Prints a table and writes benchmarks/results/render_memory.json (with the command, the date, the
load average and the machine).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from console.usage import size_list

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "render_memory.json"
DEMO = ROOT / "scenes" / "examples" / "demo.xml"
MB = 2**20
AOVS = ("albedo", "sh_normal")

_CHILD = r"""
import gc, json, sys, time
job = json.loads(sys.argv[1])
import numpy as np
try:  # the working directory is the checkout measured
    from rendering.render import load_scene, prepare, render_loaded
except ImportError:  # a revision from before the foundation package
    from pipeline.render import load_scene, prepare, render_loaded

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024

aovs = tuple(job["aovs"])
scene = load_scene(prepare(job["scene"], tuple(job["res"]), aovs))
kwargs = {"max_samples_per_pass": job["max_samples_per_pass"], "halves": job["halves"]}
if job["budget"] != "none":
    kwargs["max_memory_mb"] = job["budget"]
gc.collect()
with open("/proc/self/clear_refs", "w") as fh:
    fh.write("5")
start = status("VmRSS")
t0 = time.perf_counter()
res = render_loaded(scene, job["spp"], 1, aovs, **kwargs)
seconds = time.perf_counter() - t0
peak = status("VmHWM")
images = [res.rgb, *res.aovs.values()] + ([res.variance] if res.variance is not None else [])
out = sum(a.nbytes for a in images)
print(json.dumps({"start_mb": start / 2**20, "peak_mb": peak / 2**20, "images_mb": out / 2**20,
                  "scratch_mb": (peak - start - out) / 2**20, "seconds": seconds,
                  "crops": getattr(res, "crops", 1), "finite": bool(np.isfinite(res.rgb).all())}))
"""


def run_child(code: Path, res: tuple[int, int], spp: int, budget: float | None, aovs: bool = False,
              halves: bool = True, max_samples_per_pass: int = 1 << 24) -> dict[str, Any]:
    """One render in a fresh process with an empty kernel cache; its memory figures."""
    job = {"code": str(code), "scene": str(DEMO), "res": list(res), "spp": spp, "halves": halves,
           "aovs": list(AOVS if aovs else ()), "budget": "none" if budget is None else budget,
           "max_samples_per_pass": max_samples_per_pass}
    with tempfile.TemporaryDirectory(prefix="render-memory-home-") as home:
        env = {**os.environ, "HOME": home, "PYTHONPATH": str(code)}
        proc = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(job)], capture_output=True, text=True,
                              cwd=code, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"child {job} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _fit(xs: list[float], ys: list[float]) -> tuple[float, float]:
    """Least-squares slope and intercept."""
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx
    return slope, my - slope * mx


def _mbs(runs: list[dict[str, Any]], digits: int) -> str:
    return ", ".join(f"{r['scratch_mb']:.{digits}f}" for r in runs)


def calibrate(quick: bool) -> dict[str, Any]:
    """Bytes per pixel and fixed MB of one-piece renders; bytes per sample in flight."""
    films = [(512, 256), (512, 512)] if quick else [(512, 512), (1024, 512), (1024, 1024)]
    rows: dict[str, Any] = {}
    for aovs in (False, True):
        for halves in (False, True):
            name = f"{3 + 6 * aovs}ch{'-halves' if halves else ''}"
            runs = [run_child(ROOT, film, 2, None, aovs=aovs, halves=halves) for film in films]
            slope, fixed = _fit([w * h for w, h in films], [r["scratch_mb"] * MB for r in runs])
            rows[name] = {"films": [list(f) for f in films], "scratch_mb": [r["scratch_mb"] for r in runs],
                          "bytes_per_pixel": slope, "fixed_mb": fixed / MB}
            print(f"calibrate {name:14} {slope:7.1f} bytes/pixel + {fixed / MB:6.1f} MB fixed "
                  f"(scratch {_mbs(runs, 0)} MB)", flush=True)
    film = (256, 256) if quick else (512, 512)
    spps = [1, 16] if quick else [1, 16, 64]
    runs = [run_child(ROOT, film, s, None, halves=False, max_samples_per_pass=1 << 31) for s in spps]
    per_sample, _ = _fit([film[0] * film[1] * s for s in spps], [r["scratch_mb"] * MB for r in runs])
    rows["samples_in_flight"] = {"film": list(film), "spp_per_pass": spps,
                                 "scratch_mb": [r["scratch_mb"] for r in runs], "bytes_per_sample": per_sample}
    print(f"calibrate one pass of {film[0]}x{film[1]} at {spps} spp: scratch "
          f"{_mbs(runs, 1)} MB -> {per_sample:.3f} bytes/sample", flush=True)
    return rows


def export_before(rev: str, into: Path) -> Path:
    """``git archive REV pipeline`` unpacked into ``into``: the render code before film crops."""
    archive = subprocess.run(["git", "archive", rev, "pipeline"], cwd=ROOT, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return into


def sizes(sizes_: list[tuple[int, int]], budgets: list[float], spp: int, aovs: bool,
          before: Path | None) -> list[dict[str, Any]]:
    rows = []
    for res in sizes_:
        settings: list[tuple[str, Path, float | None]] = [(f"{b:g} MB", ROOT, b) for b in budgets]
        if before is not None:
            settings.insert(0, ("before", before, None))
        for label, code, budget in settings:
            r = run_child(code, res, spp, budget, aovs=aovs)
            r.update(res=list(res), setting=label, budget_mb=budget)
            rows.append(r)
            within = f"{r['scratch_mb'] / budget:5.2f}x budget" if budget else ""
            print(f"{res[0]}x{res[1]} {label:>8}: peak {r['peak_mb']:7.0f} MB, scratch {r['scratch_mb']:7.0f} MB "
                  f"{within:>14}  (start {r['start_mb']:.0f}, images {r['images_mb']:.0f} MB; {r['crops']} crops, "
                  f"{r['seconds']:.1f} s)", flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", metavar="REV", help="git revision whose pipeline/ is 'before' (no budget)")
    p.add_argument("--budgets", default="256,1024", help="comma-separated MB (256,1024)")
    p.add_argument("--spp", type=int, default=2)
    p.add_argument("--aovs", action="store_true", help="also render albedo and normals (9 channels)")
    p.add_argument("--sizes", type=size_list, default=size_list("1920x1080,3840x2160,7680x4320"))
    p.add_argument("--parts", default="calibrate,sizes")
    p.add_argument("--quick", action="store_true", help="small calibration films, 1080p only")
    args = p.parse_args()
    parts = args.parts.split(",")
    sizes_ = args.sizes[:1 if args.quick else None]
    budgets = [float(b) for b in args.budgets.split(",")]
    result: dict[str, Any] = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]), "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "load_avg_before": os.getloadavg(), "scene": str(DEMO.relative_to(ROOT)), "spp": args.spp,
        "channels": 9 if args.aovs else 3, "halves": True,
    }
    if "calibrate" in parts:
        result["calibrate"] = calibrate(args.quick)
    if "sizes" in parts:
        with tempfile.TemporaryDirectory(prefix="render-memory-before-") as tmp:
            before = export_before(args.before, Path(tmp)) if args.before else None
            result["sizes"] = sizes(sizes_, budgets, args.spp, args.aovs, before)
        result["before_rev"] = args.before
    result["load_avg_after"] = os.getloadavg()
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {RESULTS.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
