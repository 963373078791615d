"""``denoise`` as a person runs it: a process on an EXR that does not say its spp, against OIDN.

Two renders of the demo scene (a noisy one at ``--noisy-spp`` and a clean one at ``--clean-spp``),
each at two sizes, are written as EXRs without an ``spp`` attribute. Each is denoised by a fresh
``denoise IN OUT --model M --quiet`` process, and by a fresh Python process that reads the same
EXR, runs OIDN colour-only (``pyoidn``) and writes the result, ``--repeat`` times round-robin; the
wall times' medians give each command's **marginal** seconds per megapixel, ``(t_large -
t_small) / (MP_large - MP_small)``: the start-up (Python, torch, the models) cancels, what remains
is what each further megapixel costs. Writes benchmarks/results/denoise_process.json.

    python -m benchmarks.denoise_process [--models high,fast] [--sizes 640x360,1280x720] [--repeat 3]
"""
from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.eval_scenes import RESULTS, finish_record, run_record
from console.usage import COMMAND_ERRORS, OneLineParser, name_list, positive_int, size_list
from imaging.atomic_io import write_json_atomic
from imaging.exr import write_exr

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "scenes" / "examples" / "demo.xml"
OIDN_SCRIPT = ("import sys, pyoidn, numpy as np; from imaging.exr import read_exr, write_exr; "
               "img = read_exr(sys.argv[1]).rgb; "
               "write_exr(sys.argv[2], np.asarray(pyoidn.denoise(np.ascontiguousarray(img), hdr=True)))")


def _render(spp: int, width: int, height: int, path: Path) -> None:
    from rendering.render import render

    write_exr(path, render(DEMO, spp, seed=3, resolution=(width, height)).rgb)  # no spp attribute


def _wall(cmd: list[str]) -> float:
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {done.stderr.strip().splitlines()[-1:]}")
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.denoise_process", description=__doc__.split("\n")[0])
    p.add_argument("--models", type=name_list, default=("high", "fast"))
    p.add_argument("--sizes", type=size_list, default=[(640, 360), (1280, 720)])
    p.add_argument("--noisy-spp", type=positive_int, default=4)
    p.add_argument("--clean-spp", type=positive_int, default=256)
    p.add_argument("--repeat", type=positive_int, default=3)
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if len(args.sizes) != 2:
        p.error("--sizes takes two sizes (the marginal cost is their difference)")
    record = run_record("benchmarks.denoise_process", sys.argv[1:] if argv is None else argv)
    start = time.perf_counter()
    denoise = str(Path(sys.executable).parent / "denoise")
    results: dict[str, Any] = {}
    try:
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            for kind, spp in (("noisy", args.noisy_spp), ("clean", args.clean_spp)):
                files = {}
                for w, h in args.sizes:
                    files[(w, h)] = folder / f"{kind}_{w}x{h}.exr"
                    _render(spp, w, h, files[(w, h)])
                commands = {m: (lambda src, m=m: [denoise, str(src), str(folder / "out.exr"), "--model", m, "--quiet",
                                                  "--overwrite"])
                            for m in args.models}
                commands["oidn"] = lambda src: [sys.executable, "-c", OIDN_SCRIPT, str(src), str(folder / "out.exr")]
                times: dict[str, dict[str, list[float]]] = {n: {f"{w}x{h}": [] for w, h in args.sizes} for n in commands}
                for _ in range(args.repeat):
                    for name, command in commands.items():
                        for size, src in files.items():
                            times[name][f"{size[0]}x{size[1]}"].append(_wall(command(src)))
                (w0, h0), (w1, h1) = args.sizes
                d_mp = (w1 * h1 - w0 * h0) / 1e6
                per = {}
                for name, by_size in times.items():
                    t0, t1 = (statistics.median(by_size[f"{w}x{h}"]) for w, h in args.sizes)
                    per[name] = {"seconds": by_size, "marginal_s_per_mp": (t1 - t0) / d_mp}
                for name in args.models:
                    per[name]["ratio_to_oidn"] = per[name]["marginal_s_per_mp"] / per["oidn"]["marginal_s_per_mp"]
                results[kind] = {"spp": spp, "commands": per}
                print(f"{kind} ({spp} spp, no spp attribute): " + ", ".join(
                    f"{n} {v['marginal_s_per_mp']:.2f} s/MP" + (f" ({v['ratio_to_oidn']:.2f}x OIDN)" if n != "oidn" else "")
                    for n, v in per.items()), flush=True)
    except (*COMMAND_ERRORS, RuntimeError) as exc:
        return p.fail(exc)
    record.update({"sizes": [f"{w}x{h}" for w, h in args.sizes], "results": results})
    out = RESULTS / "denoise_process.json"
    write_json_atomic(out, finish_record(record, start))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
