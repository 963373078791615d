"""Peak scratch memory of the denoising path under --max-memory-mb: one tile, and whole commands.

    python -m benchmarks.denoise_memory [--parts calibrate,commands,path] [--budgets 256,1024]
        [--sizes 1920x1080,3840x2160,7680x4320] [--spp 2] [--before REV] [--quick]
        [--entries fast,balanced,high] [--entry-spp 16,128] [--path-size 3840x2160] [--runs E:SPP:MB,...]

The budget is OIDN's ``maxMemoryMB``: scratch memory beyond the input and output images. Every
figure comes from a fresh child process that measures its own resident memory (``/proc/self``):
before each stage it resets the kernel's high-water mark (``clear_refs``), so a stage's peak is
exact, and **scratch** = the stage's peak - the RSS at its start - the images it creates.

* calibrate: one tile of the chain (:func:`denoise.chain.denoise_image` on an SxS image that is one
  window, the noise variance given to the models that take it) for each preset (random weights:
  memory does not depend on them) at several S, with the Denoiser's allocator setting
  (:mod:`denoise.allocator`: the mmap threshold and huge pages); the folded network (the default) and the training module; a few
  with glibc's default setting, to show what the setting is for. Beside each, the estimate the
  tile planner uses (:func:`denoise.chain.tile_bytes_per_pixel` x pixels + ``TILE_FIXED_BYTES``).
* commands: per image size, the bundled demo scene at ``--spp`` in two halves through
  ``render-and-denoise`` (:func:`pipeline.run.run` as the CLI calls it, ``--no-compare``) per
  budget, then ``denoise`` (:func:`pipeline.denoise_file.denoise_file`) of an EXR holding that
  render's colour and a ``variance`` layer. Stages: the render (Mitsuba's own scratch, bounded by
  the render's crops; its images: colour and variance), the denoise step (its images: the output
  and the guard's weight map), writing the outputs, the report; for ``denoise`` reading the file
  (its images: the file's channels and the colour and variance made from them), the denoise step,
  writing. ``--before REV`` measures the same with the code of REV (``git archive``).

* path: the whole ``denoise`` command as a person counts it, per registry entry (``--entries``),
  render spp (``--entry-spp``: which networks run) and budget: an EXR of the demo scene at
  ``--path-size`` (rendered once at ``--spp`` in two halves: its colour and a ``variance`` layer)
  denoised by :func:`pipeline.denoise_file.denoise_file` with its spp set, in a fresh process
  (``--runs``: only the (entry, spp, budget) triples listed).
  **scratch** = the peak RSS from just before the file is read to the end of writing - the RSS
  then (the loaded process) - the images (the input's colour and variance as float32, the
  output).

Prints a table and writes benchmarks/results/denoise_memory.json (command, date, load average
and machine recorded); ``--quick`` (small sizes, one preset) writes nothing.
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
from collections.abc import Callable
from typing import Any

from imaging.atomic_io import write_json_atomic
from console.usage import size_list

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "denoise_memory.json"
DEMO = ROOT / "scenes" / "examples" / "demo.xml"
MB = 2**20
PRESETS = ("flat-s", "flat-m", "flat-l", "unet-s", "unet-m", "unet-l")
TILE_SIDES = (128, 256, 384, 512, 768)

_COMMON = r"""
import gc, json, sys, time
job = json.loads(sys.argv[1])
MB = 2**20

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024

def reset():
    gc.collect()
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    return status("VmRSS")
"""

_TILE_CHILD = _COMMON + r"""
import numpy as np, torch
if job["allocator"]:
    from denoise.allocator import fix_mmap_threshold, use_huge_pages
    fix_mmap_threshold()
    use_huge_pages()
from model.architectures import build_model
from denoise.folded import prepare_for_inference
from model.config import PRESETS
from denoise.chain import TILE_FIXED_BYTES, denoise_image, tile_bytes_per_pixel
torch.manual_seed(0)
config = PRESETS[job["preset"]]
net = build_model(config).eval()
net = prepare_for_inference(net) if job["folded"] else net
s = job["side"]
rng = np.random.default_rng(0)
image = rng.random((s, s, 3), dtype=np.float32)
variance = rng.random((s, s, 3), dtype=np.float32) * 0.01 if config.noise_input else None
start = reset()
t0 = time.perf_counter()
out = denoise_image(net, image, core=s, variance=variance)
seconds = time.perf_counter() - t0
peak = status("VmHWM")
estimate = TILE_FIXED_BYTES + tile_bytes_per_pixel(config, job["folded"]) * s * s
print(json.dumps({"scratch_mb": (peak - start - out.nbytes) / MB, "estimate_mb": estimate / MB,
                  "start_mb": start / MB, "seconds": seconds}))
"""

_COMMAND_CHILD = _COMMON + r"""
import numpy as np
stages = []

def measured(owner, name, label, images=lambda result: 0):
    fn = getattr(owner, name)
    def wrapper(*args, **kwargs):
        start = reset()
        t0 = time.perf_counter()
        result = fn(*args, **kwargs)
        peak = status("VmHWM")
        made = images(result)
        stages.append({"stage": label, "start_mb": start / MB, "peak_mb": peak / MB, "images_mb": made / MB,
                       "scratch_mb": (peak - start - made) / MB, "seconds": time.perf_counter() - t0})
        return result
    setattr(owner, name, wrapper)

def nbytes(*arrays):
    return sum(a.nbytes for a in arrays if a is not None)

kept = {}
base = reset()
if job["command"] == "render-and-denoise":
    import pipeline.run as run_mod
    from pipeline.evaluation import RenderSettings
    def render_images(r):
        kept["render"] = r
        return nbytes(r.rgb, r.variance, *r.aovs.values())
    measured(run_mod, "_start", "setup (model)")
    measured(run_mod, "_load_scene", "setup (scene)")
    measured(run_mod, "render_input", "render", render_images)
    measured(run_mod, "denoise_output", "denoise", lambda o: nbytes(o.image, o.result.guard_map))
    measured(run_mod, "_write_images", "write images")
    measured(run_mod, "_metrics", "metrics")
    measured(run_mod, "write_report", "report")
    settings = RenderSettings(scene=job["scene"], resolution=tuple(job["res"]), max_memory_mb=job["budget"])
    cfg = run_mod.RunConfig(render=settings, out=job["out"], spp=job["spp"], compare_oidn=False)
    metrics = run_mod.run(cfg)
    extra = {"render_memory": metrics.get("render_memory")}
    if job.get("write_input"):
        from imaging.exr import write_exr
        r = kept["render"]
        write_exr(job["write_input"], r.rgb, layers={"variance": r.variance}, metadata={"spp": job["spp"]})
else:
    import denoise.denoiser as denoise_mod
    import pipeline.denoise_file as file_mod
    def input_images(image):
        file = sum(a.nbytes for part in image.exr.parts for a in part.channels.values()) if image.exr else 0
        return file + nbytes(image.rgb, image.variance, image.albedo, image.normals)
    measured(denoise_mod.Denoiser, "__init__", "setup (model)")
    measured(file_mod, "read_input", "read", input_images)
    measured(denoise_mod.Denoiser, "denoise_array", "denoise", lambda r: nbytes(r.image, r.guard_map))
    measured(file_mod, "_write", "write")
    cfg = file_mod.DenoiseFileConfig(inputs=[job["input"]], output=job["out"] + "/denoised.exr",
                                     max_memory_mb=job["budget"])
    extra = {"guard": file_mod.denoise_file(cfg)["noise_guard"]}
peak = max(s["peak_mb"] for s in stages)
print(json.dumps({"base_mb": base / MB, "peak_mb": peak, "stages": stages, **extra}))
"""


_RENDER_CHILD = r"""
import json, sys
job = json.loads(sys.argv[1])
from imaging.exr import write_exr
from pipeline.evaluation import RenderSettings, render_input
settings = RenderSettings(scene=job["scene"], resolution=tuple(job["res"]), max_memory_mb=1024)
render = render_input(settings.load(), job["spp"], settings)
write_exr(job["out"], render.rgb, layers={"variance": render.variance}, metadata={"spp": job["spp"]})
print(json.dumps({"written": job["out"]}))
"""

PATH_CHILD = _COMMON + r"""
import pipeline.denoise_file as file_mod
seen = {}
read_input = file_mod.read_input

def measured_read(*args, **kwargs):  # the high-water mark from just before the image is read
    seen["base"] = reset()
    seen["t0"] = time.perf_counter()
    image = read_input(*args, **kwargs)
    seen["images"] = 2 * image.rgb.nbytes + image.variance.nbytes  # the input, its variance, the output
    return image

file_mod.read_input = measured_read
cfg = file_mod.DenoiseFileConfig(inputs=[job["input"]], output=job["out"], model=job["entry"], spp=job["spp"],
                                 max_memory_mb=job["budget"], overwrite=True)  # one scratch output per run
record = file_mod.denoise_file(cfg)
peak = status("VmHWM")
print(json.dumps({"base_mb": seen["base"] / MB, "peak_mb": peak / MB, "images_mb": seen["images"] / MB,
                  "scratch_mb": (peak - seen["base"] - seen["images"]) / MB, "models": record["models_run"],
                  "precision": record["precision"], "denoise_s": record["denoise_s"],
                  "seconds": time.perf_counter() - seen["t0"]}))
"""


def run_child(code: Path, script: str, job: dict[str, Any], env: dict[str, str] | None = None) -> dict[str, Any]:
    """``script`` in a fresh Python process whose working directory and import path are ``code``."""
    proc = subprocess.run([sys.executable, "-c", script, json.dumps(job)], capture_output=True, text=True,
                          cwd=code, env={**os.environ, "PYTHONPATH": str(code), **(env or {})})
    if proc.returncode != 0:
        raise SystemExit(f"denoise_memory: child {job} failed: {proc.stderr.strip().splitlines()[-3:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def calibrate(presets: tuple[str, ...], sides: tuple[int, ...]) -> list[dict[str, Any]]:
    """One tile per preset, side and setting: measured scratch against the planner's estimate."""
    rows = []
    settings = [("folded", True, True), ("module", False, True)]
    for preset in presets:
        for label, folded, allocator in settings + ([("folded, glibc default", True, False)]
                                                   if preset in ("flat-s", "flat-m") else []):
            for side in sides if label != "module" else sides[:3]:
                job = {"preset": preset, "folded": folded, "allocator": allocator, "side": side}
                r = {**job, "setting": label, **run_child(ROOT, _TILE_CHILD, job)}
                rows.append(r)
                print(f"tile {preset:10} {label:22} {side:4}^2: scratch {r['scratch_mb']:7.1f} MB, estimate "
                      f"{r['estimate_mb']:7.1f} MB ({r['scratch_mb'] / r['estimate_mb']:4.2f}x)", flush=True)
    return rows


def export(rev: str, into: Path) -> Path:
    """The tracked files of ``rev`` unpacked into ``into`` (the shipped weights copied beside)."""
    into.mkdir(parents=True)
    archive = subprocess.run(["git", "archive", rev], cwd=ROOT, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    weights = into / "model" / "weights"
    weights.mkdir(parents=True, exist_ok=True)
    for ckpt in (ROOT / "model" / "weights").glob("*.ckpt"):
        target = weights / ckpt.name
        if not target.exists():
            target.symlink_to(ckpt)
    return into


def _stage(row: dict[str, Any], name: str) -> dict[str, Any]:
    return next(s for s in row["stages"] if s["stage"] == name)


def _print_command(row: dict[str, Any]) -> None:
    d = _stage(row, "denoise")
    others = [s for s in row["stages"] if s["stage"] not in ("denoise",) and not s["stage"].startswith("setup")]
    budget = row["budget_mb"]
    render = row.get("render_memory") or {}
    line = (f"{row['res'][0]}x{row['res'][1]} {row['command']:18} {row['setting']:>7} {budget:6g} MB: denoise scratch "
            f"{d['scratch_mb']:7.0f} MB ({d['scratch_mb'] / budget:5.2f}x budget, images {d['images_mb']:.0f} MB, "
            f"{d['seconds']:.0f} s); " + ", ".join(f"{s['stage']} {s['scratch_mb']:.0f}" for s in others)
            + f" MB; process peak {row['peak_mb']:.0f} MB (base {row['base_mb']:.0f})")
    if render.get("peak_mb") is not None:
        line += f"; render's own peak {render['peak_mb']:.0f} MB ({render['over_start_mb']:.0f} over its start)"
    print(line, flush=True)


def commands(sizes: list[tuple[int, int]], budgets: list[float], spp: int, before: Path | None,
             work: Path) -> list[dict[str, Any]]:
    """render-and-denoise, then denoise of its render, per size and budget (and with the code of
    ``before``)."""
    rows = []
    codes = [("after", ROOT)] + ([("before", before)] if before is not None else [])
    for res in sizes:
        source = work / f"input-{res[0]}x{res[1]}.exr"
        for setting, code in codes:
            for command in ("render-and-denoise", "denoise"):
                for budget in budgets:
                    out = work / f"{setting}-{command}-{res[0]}x{res[1]}-{budget:g}"
                    out.mkdir(parents=True, exist_ok=True)
                    job = {"command": command, "scene": str(DEMO), "res": list(res), "spp": spp,
                           "budget": budget, "out": str(out), "input": str(source)}
                    if command == "render-and-denoise" and not source.exists():
                        job["write_input"] = str(source)
                    row = {**job, "setting": setting, "budget_mb": budget, **run_child(code, _COMMAND_CHILD, job)}
                    rows.append(row)
                    _print_command(row)
    return rows


def path(runs: list[tuple[str, int, float]], size: tuple[int, int], spp: int, work: Path,
         done: Callable[[list[dict[str, Any]]], None] = lambda rows: None) -> list[dict[str, Any]]:
    """The whole ``denoise`` command per (entry, spp, budget) of ``runs`` on one rendered EXR of
    ``size``; ``done`` is given the rows so far after each (a long run keeps what it measured)."""
    work.mkdir(parents=True, exist_ok=True)
    source = work / f"input-{size[0]}x{size[1]}.exr"
    run_child(ROOT, _RENDER_CHILD, {"scene": str(DEMO), "res": list(size), "spp": spp, "out": str(source)})
    rows = []
    for entry, entry_spp, budget in runs:
        job = {"input": str(source), "out": str(work / "out.exr"), "entry": entry, "spp": entry_spp, "budget": budget}
        row = {"res": list(size), "entry": entry, "spp": entry_spp, "budget_mb": budget,
               **run_child(ROOT, PATH_CHILD, job)}
        row["x_budget"] = row["scratch_mb"] / budget
        rows.append(row)
        print(f"{size[0]}x{size[1]} {entry:8} {entry_spp:4} spp {budget:6g} MB: scratch {row['scratch_mb']:6.0f} MB "
              f"({row['x_budget']:4.2f}x budget; peak {row['peak_mb']:.0f}, process {row['base_mb']:.0f}, "
              f"images {row['images_mb']:.0f} MB), {'+'.join(row['models'])}, {row['seconds']:.0f} s", flush=True)
        done(rows)
    return rows


def path_runs(text: str | None, entries: str, entry_spps: str, budgets: list[float]) -> list[tuple[str, int, float]]:
    """``--runs ENTRY:SPP:MB,...`` as given, else every entry, spp and budget."""
    if text:
        runs = []
        for item in text.split(","):
            entry, spp, budget = item.split(":")
            runs.append((entry, int(spp), float(budget)))
        return runs
    return [(e, int(n), b) for e in entries.split(",") for n in entry_spps.split(",") for b in budgets]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--parts", default="calibrate,commands")
    p.add_argument("--budgets", default="256,1024", help="comma-separated MB (256,1024)")
    p.add_argument("--sizes", type=size_list, default=size_list("1920x1080,3840x2160,7680x4320"))
    p.add_argument("--spp", type=int, default=2)
    p.add_argument("--before", metavar="REV", help="also measure the commands with the code of this git revision")
    p.add_argument("--quick", action="store_true", help="one preset, small tiles, 640x360 only; writes nothing")
    p.add_argument("--entries", default="fast,balanced,high", help="path: registry entries")
    p.add_argument("--entry-spp", default="16,128", help="path: the spp each entry is told (which networks run)")
    p.add_argument("--path-size", type=size_list, default=size_list("3840x2160"), help="path: the image size")
    p.add_argument("--runs", help="path: ENTRY:SPP:MB,... instead of every entry, spp and budget")
    args = p.parse_args()
    parts = args.parts.split(",")
    if not set(parts) <= {"calibrate", "commands", "path"}:
        raise SystemExit(f"denoise_memory: unknown part in --parts {args.parts!r}")
    sizes = [(640, 360)] if args.quick else args.sizes
    budgets = [float(b) for b in args.budgets.split(",")]
    result = json.loads(RESULTS.read_text()) if RESULTS.exists() and not args.quick else {}
    for part in parts:  # each part records its own command, date and load: the other keeps its own
        record: dict[str, Any] = {
            "command": " ".join(["python -m benchmarks.denoise_memory", *sys.argv[1:]]),
            "date": time.strftime("%Y-%m-%d %H:%M"),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
            "load_avg_before": os.getloadavg()}
        if part == "calibrate":
            record["rows"] = calibrate(("flat-s",) if args.quick else PRESETS, (128, 256) if args.quick else TILE_SIDES)
        elif part == "path":
            size = (640, 360) if args.quick else args.path_size[0]
            record.update(scene=str(DEMO.relative_to(ROOT)), render_spp=args.spp)

            def keep(rows: list[dict[str, Any]]) -> None:
                if not args.quick:
                    write_json_atomic(RESULTS, {**result, part: {**record, "rows": rows, "complete": False}})

            with tempfile.TemporaryDirectory(prefix="denoise-memory-") as tmp:
                record["rows"] = path(path_runs(args.runs, args.entries, args.entry_spp, budgets), size, args.spp,
                                      Path(tmp), keep)
        else:
            record.update(scene=str(DEMO.relative_to(ROOT)), spp=args.spp, before_rev=args.before)
            with tempfile.TemporaryDirectory(prefix="denoise-memory-") as tmp:
                before = export(args.before, Path(tmp) / "before") if args.before else None
                record["rows"] = commands(sizes, budgets, args.spp, before, Path(tmp) / "work")
        record["load_avg_after"] = os.getloadavg()
        result[part] = record
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(RESULTS, result)
        print(f"wrote {RESULTS.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
