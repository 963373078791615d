"""Mutation testing of the core modules: does each module's test file catch every small change?

``python -m mutation.runner`` (``make mutation``) copies the checkout once, then for each mutant
of :data:`MODULES` (:mod:`mutation.operators`) writes the changed module into the copy and runs
that module's tests on it (``pytest -x``). A mutant is *killed* when the tests fail (or run past
3x their normal time plus 30 s), *survives* when they pass. Each run is a fork of a process that
has already imported the third-party libraries (numpy, torch, OpenEXR...) and none of ours, so the
child imports the changed module fresh and a mutant costs its tests' time, not the imports'.
The score per module (killed / mutants) and every survivor go to
``benchmarks/results/mutation.json``; docs/robustness.md shows them.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mutation.operators import mutants

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "benchmarks" / "results" / "mutation.json"


@dataclass(frozen=True)
class Module:
    """A module under mutation: its path, its tests and, optionally, the functions mutated."""

    path: str
    tests: tuple[str, ...]
    functions: tuple[str, ...] | None = None


MODULES = (
    Module("imaging/metrics.py", ("tests/test_metrics.py",)),
    Module("denoise/noise_guard.py", ("tests/test_noise_guard.py",)),
    Module("denoise/energy.py", ("tests/test_energy.py",)),
    Module("imaging/exr_layers.py", ("tests/test_exr_layers.py",),
           ("_groups", "find_layers", "pick_color_layer", "find_aux_layer", "Layer.kind", "Layer.word")),
    Module("model/transfer.py", ("tests/test_model_transfer.py",)),
    Module("denoise/tiling.py", ("tests/test_tiling.py",)),
    Module("model/checkpoint.py", ("tests/test_model_checkpoint.py",),
           ("read_checkpoint", "_open_tensors", "_load_tensors", "_header", "_json", "_is_int",
            "_check_header_fields", "model_config_of", "check_tensors", "_check_other_tensors",
            "model_from_checkpoint", "load_model", "restore_optimizer", "_plain_group")),
)
PRELOADED = ("numpy", "torch", "OpenEXR", "Imath", "safetensors.torch", "PIL.Image", "hypothesis", "pytest")


def copy_checkout(dest: Path) -> Path:
    """The checkout's files (what git tracks, and what it does not ignore) under ``dest``."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                            capture_output=True, check=True).stdout.split(b"\0")
    for name in filter(None, listed):
        src = ROOT / name.decode()
        if src.is_file():
            (dest / name.decode()).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name.decode())
    return dest


def _run_tests(copy: Path, tests: tuple[str, ...], limit: float) -> tuple[str, float]:
    """Run ``tests`` in ``copy`` in a forked child: (``passed`` / ``failed`` / ``timeout``, seconds)."""
    start = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # the child: our modules are imported here, from the copy, for the first time
        code = 3
        try:
            os.chdir(copy)
            sys.path.insert(0, str(copy))
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            import pytest

            code = pytest.main(["-x", "-q", "-p", "no:cacheprovider", *tests])
        finally:
            os._exit(int(code))
    deadline = start + limit
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            code = os.waitstatus_to_exitcode(status)
            return ("passed" if code == 0 else "failed"), time.perf_counter() - start
        if time.perf_counter() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return "timeout", time.perf_counter() - start
        time.sleep(0.05)


def run_module(module: Module, copy: Path, log: Any) -> dict[str, Any]:
    """Every mutant of ``module`` against its tests; the tallies and the survivors."""
    target = copy / module.path
    original = target.read_text()
    outcome, base_s = _run_tests(copy, module.tests, 3600)
    if outcome != "passed":
        raise RuntimeError(f"{module.tests} fail on the unchanged code")
    found = list(mutants(original, module.functions))
    result: dict[str, Any] = {"module": module.path, "tests": list(module.tests), "functions": module.functions,
                              "mutants": len(found), "killed": 0, "timeout": 0, "survived": [],
                              "tests_s": round(base_s, 1)}
    try:
        for i, mutant in enumerate(found):
            target.write_text(mutant.source)
            outcome, seconds = _run_tests(copy, module.tests, 3 * base_s + 30)
            if outcome == "passed":
                result["survived"].append({"line": mutant.line, "change": mutant.description})
                log(f"{module.path}:{mutant.line}: {mutant.description} survived")
            else:
                result["killed"] += 1
                result["timeout"] += outcome == "timeout"
            if (i + 1) % 25 == 0:
                log(f"{module.path}: {i + 1}/{len(found)} mutants, {len(result['survived'])} survived")
    finally:
        target.write_text(original)
    result["score"] = round(result["killed"] / max(1, result["mutants"]), 3)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mutation.runner", description=__doc__.split("\n")[0])
    p.add_argument("--modules", default="", help="comma-separated module paths (default: all of MODULES)")
    p.add_argument("--result", type=Path, default=RESULT, help="where the scores go (benchmarks/results/mutation.json)")
    p.add_argument("--list", action="store_true", help="print the mutants and run nothing")
    args = p.parse_args(argv)
    chosen = [m for m in MODULES if not args.modules or m.path in args.modules.split(",")]
    if args.list:
        for module in chosen:
            for mutant in mutants((ROOT / module.path).read_text(), module.functions):
                print(f"{module.path}:{mutant.line}: {mutant.description}")
        return 0
    sys.dont_write_bytecode = True  # a mutant of the same size, written within the same second, must not
    for name in PRELOADED:          # be run from the bytecode cached for the one before it
        __import__(name)
    log = lambda text: print(text, flush=True)  # noqa: E731
    previous = json.loads(args.result.read_text()) if args.result.exists() else {"modules": {}}
    record = {"command": "python -m mutation.runner " + " ".join(argv if argv is not None else sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d %H:%M"), "load_avg_before": os.getloadavg()[0],
              "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                       text=True).stdout.strip(),
              "modules": dict(previous.get("modules", {}))}
    with tempfile.TemporaryDirectory(prefix="mutation-") as tmp:
        copy = copy_checkout(Path(tmp))
        for module in chosen:
            done = record["modules"][module.path] = run_module(module, copy, log)
            done.update(commit=record["commit"], date=record["date"])
            log(f"{module.path}: {done['killed']}/{done['mutants']} killed, score {done['score']}")
            args.result.write_text(json.dumps(record, indent=1) + "\n")
    record["load_avg_after"] = os.getloadavg()[0]
    args.result.write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
