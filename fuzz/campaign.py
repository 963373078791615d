"""The long fuzz campaign: thousands of mutated files per reader, each judged by :mod:`fuzz.harness`.

``python -m fuzz.campaign --inputs 10000`` runs that many more inputs for each target (``make
fuzz``), continuing the lifetime count recorded in ``benchmarks/results/fuzz.json``: input ``i``
of target ``T`` is the mutation drawn from ``random.Random("campaign/T/i")`` (so any input can be
made again from its number), and the next campaign starts where the last one stopped.

The inputs run in a worker process per target (one thread, its address space limited to its size
after start-up plus ``--memory-limit-mb`` x 4, so a runaway allocation fails in that process, not
on the machine). The worker reports each input before and after it runs; the campaign kills a
worker silent for longer than 10 x ``--time-limit`` (a hang inside native code) and restarts it
after a crash (a signal), recording the input in either case. Every failure's input is kept under
``fuzz/crashes/TARGET/INDEX-STATUS@SEEDNAME``, to become a regression test
(``fuzz/regressions/``, replayed by ``tests/test_fuzz.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import random
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "benchmarks" / "results" / "fuzz.json"
CRASHES = ROOT / "fuzz" / "crashes"


def mutation(target: Any, index: int) -> Any:
    """Input ``index`` of ``target``'s campaign (a :class:`fuzz.targets.Seed`)."""
    return target.mutate(random.Random(f"campaign/{target.name}/{index}"))


def _setup(workdir: Path, name: str) -> tuple[Any, Any]:
    import torch

    from fuzz.targets import Context, targets

    torch.set_num_threads(1)
    ctx = Context.create(workdir / "context")
    target = targets(ctx)[name]
    target.prepare(workdir / "seeds" / name)
    return ctx, target


def worker(name: str, start: int, stop: int, workdir: Path, time_limit: float, memory_limit_mb: float) -> None:
    """Run inputs ``start..stop`` of target ``name``, one line per event on stdout."""
    from fuzz.harness import run_input, status_kb

    ctx, target = _setup(workdir, name)
    size = (status_kb("VmSize") or 0) * 1024
    resource.setrlimit(resource.RLIMIT_AS, (size + int(4 * memory_limit_mb * 2**20), resource.RLIM_INFINITY))
    out = sys.__stdout__
    for index in range(start, stop):
        seed = mutation(target, index)
        (workdir / "current.name").write_text(seed.name)  # for the campaign, should this input kill us
        (workdir / "current.bin").write_bytes(seed.data)
        print(f"begin {index}", file=out, flush=True)
        outcome = run_input(target, seed, workdir / "run", ctx, time_limit, memory_limit_mb)
        failure = keep_failure(name, index, outcome.status, seed.name, seed.data, outcome.describe()) \
            if outcome.failed else None
        print(json.dumps({"index": index, "status": outcome.status, "seconds": round(outcome.seconds, 4),
                          "peak_mb": outcome.peak_mb, "failure": failure}), file=out, flush=True)


def keep_failure(name: str, index: int, status: str, seed_name: str, data: bytes, detail: str) -> dict[str, Any]:
    """Keep a failing input under fuzz/crashes/NAME/ as ``INDEX-STATUS@SEEDNAME``; describe it for
    the record."""
    folder = CRASHES / name
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{index:07d}-{status.replace(' ', '-')}@{seed_name}"
    path.write_bytes(data)
    return {"index": index, "status": status, "file": str(path.relative_to(ROOT)), "detail": detail[-1500:]}


class _Lines(threading.Thread):
    """Reads a worker's stdout, keeping the time of the last line."""

    def __init__(self, stream: Any) -> None:
        super().__init__(daemon=True)
        self.stream, self.lines, self.last = stream, [], time.monotonic()
        self.lock = threading.Lock()

    def run(self) -> None:
        for line in self.stream:
            with self.lock:
                self.lines.append(line.strip())
                self.last = time.monotonic()

    def take(self) -> list[str]:
        with self.lock:
            out, self.lines = self.lines, []
            return out


class _Tally:
    """A target's counts in one campaign: inputs run, outcomes by status, failures, seconds."""

    def __init__(self) -> None:
        self.inputs, self.statuses, self.failures, self.seconds = 0, {}, [], 0.0

    def add(self, status: str, seconds: float = 0.0, failure: dict[str, Any] | None = None) -> None:
        self.inputs += 1
        self.seconds += seconds
        self.statuses[status] = self.statuses.get(status, 0) + 1
        if failure:
            self.failures.append(failure)

    def as_dict(self) -> dict[str, Any]:
        return {"inputs": self.inputs, "statuses": self.statuses, "failures": self.failures,
                "seconds": round(self.seconds, 1)}


def run_target(name: str, start: int, count: int, workdir: Path, time_limit: float, memory_limit_mb: float,
               log: Any) -> dict[str, Any]:
    """Inputs ``start .. start+count`` of ``name`` through workers (module notes); the tallies."""
    tally, index, stop = _Tally(), start, start + count
    while index < stop:
        cmd = [sys.executable, "-m", "fuzz.campaign", "--worker", name, "--start", str(index), "--stop", str(stop),
               "--workdir", str(workdir), "--time-limit", str(time_limit), "--memory-limit-mb", str(memory_limit_mb)]
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        reader = _Lines(proc.stdout)
        reader.start()
        current, started, hung, done = None, time.monotonic(), False, False
        while not done:
            time.sleep(0.2)
            hung = current is not None and time.monotonic() - started > 10 * time_limit
            if hung:
                proc.kill()
            done = proc.poll() is not None
            if done:
                reader.join(timeout=5)
            for line in reader.take():
                if line.startswith("begin "):
                    current, started = int(line.split()[1]), time.monotonic()
                elif line.startswith("{"):
                    event = json.loads(line)
                    tally.add(event["status"], event["seconds"], event["failure"])
                    if event["failure"]:
                        log(f"{name} input {event['index']}: {event['failure']['detail'][:300]}")
                    index, current = event["index"] + 1, None
        if current is not None:  # the worker died, or hung, on this input
            code = proc.returncode
            status = "hang" if hung else f"signal {-code}" if code < 0 else f"exit {code}"
            tally.add(status, 0.0, keep_failure(name, current, status, (workdir / "current.name").read_text(),
                                               (workdir / "current.bin").read_bytes(), status))
            log(f"{name} input {current}: {status}")
            index = current + 1
        elif proc.returncode != 0 and index < stop:
            raise RuntimeError(f"{name}: the worker failed outside an input (exit {proc.returncode})")
    return tally.as_dict()


def read_record(path: Path = RECORD) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.exists() else {"targets": {}, "runs": []}


def merge(record: dict[str, Any], name: str, tally: dict[str, Any]) -> None:
    """Add a campaign's tallies of ``name`` to the lifetime record."""
    entry = record["targets"].setdefault(name, {"inputs": 0, "statuses": {}, "failures": [], "seconds": 0.0})
    entry["inputs"] += tally["inputs"]
    entry["seconds"] = round(entry["seconds"] + tally["seconds"], 1)
    for status, n in tally["statuses"].items():
        entry["statuses"][status] = entry["statuses"].get(status, 0) + n
    entry["failures"] += tally["failures"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fuzz.campaign", description=__doc__.split("\n")[0])
    p.add_argument("--inputs", type=int, default=10000, help="inputs per target in this campaign (10000)")
    p.add_argument("--targets", default="", help="comma-separated target names (default: all)")
    p.add_argument("--time-limit", type=float, default=5.0, help="seconds an input may take (5)")
    p.add_argument("--memory-limit-mb", type=float, default=1024.0, help="resident MB an input may add (1024)")
    p.add_argument("--record", type=Path, default=RECORD, help="the lifetime record (benchmarks/results/fuzz.json)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    p.add_argument("--start", type=int, help=argparse.SUPPRESS)
    p.add_argument("--stop", type=int, help=argparse.SUPPRESS)
    p.add_argument("--workdir", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        worker(args.worker, args.start, args.stop, args.workdir, args.time_limit, args.memory_limit_mb)
        return 0
    from fuzz.targets import TARGET_NAMES

    names = [n for n in args.targets.split(",") if n] or list(TARGET_NAMES)
    record = read_record(args.record)
    workdir = Path(tempfile.mkdtemp(prefix="fuzz-campaign-"))
    log = lambda text: print(text, flush=True)  # noqa: E731
    run: dict[str, Any] = {"date": time.strftime("%Y-%m-%d %H:%M"), "command": "python -m fuzz.campaign "
                           + " ".join(argv if argv is not None else sys.argv[1:]), "inputs": {},
                           "load_avg_before": os.getloadavg()[0],
                           "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                                    text=True).stdout.strip()}
    try:
        for name in names:
            start = record["targets"].get(name, {}).get("inputs", 0)
            tally = run_target(name, start, args.inputs, workdir, args.time_limit, args.memory_limit_mb, log)
            merge(record, name, tally)
            run["inputs"][name] = tally["inputs"]
            log(f"{name}: {tally['inputs']} inputs, {tally['statuses']}, {len(tally['failures'])} failures")
            args.record.write_text(json.dumps(record, indent=1) + "\n")
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    run["load_avg_after"] = os.getloadavg()[0]
    record["runs"].append(run)
    args.record.write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
