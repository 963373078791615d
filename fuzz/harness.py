"""Run one mutated file through its reader's command and judge the outcome.

A run passes when the command ends in a valid result (exit code 0) or in the project's own error:
exit code 1 or 2 and exactly one line on stderr, ``PROG: error: ...`` (beside it only Mitsuba's
own log lines, its warnings about a scene it loads). It fails on anything else:
an exception that escapes the command (a traceback), more or other output on stderr, another exit
code, more than ``time_limit`` seconds, more than ``memory_limit_mb`` of resident memory beyond
what the process held before (the kernel's high-water mark, reset before the run), or any file it
was given changed. The command runs in this process, its stdout and stderr captured at the file
descriptors (what native libraries print counts).
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import re
import shutil
import sys
import tempfile
import time
import traceback
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from fuzz.targets import Context, Seed, Target
from imaging.memory_limit import kb_field

FAILURES = ("exception", "stderr", "exit", "slow", "memory", "changed")
ANSI = re.compile(r"\x1b\[[0-9;]*m")
LIBRARY_LOG = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d (WARN|INFO|DEBUG) ")  # Mitsuba's log lines
MB = 2**20


@dataclass
class Outcome:
    """``status``: ``ok`` (a result), ``error`` (the one-line error) or one of :data:`FAILURES`."""

    status: str
    code: int | None
    stderr: str
    seconds: float
    peak_mb: float | None
    detail: str = ""

    @property
    def failed(self) -> bool:
        return self.status in FAILURES

    def describe(self) -> str:
        first = self.detail or self.stderr
        return (f"{self.status} (exit {self.code}, {self.seconds:.1f} s, peak +{self.peak_mb or 0:.0f} MB): "
                f"{first.strip()[-2000:]}")


def status_kb(key: str) -> int | None:
    """A field of /proc/self/status (``VmRSS``, ``VmHWM``, ``VmSize``) in kB; None if unreadable."""
    found = kb_field(Path("/proc/self/status"), key)
    return None if found is None else found // 1024


def reset_peak() -> bool:
    """Reset this process's resident high-water mark (Linux ``clear_refs``); False where it cannot."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


@contextlib.contextmanager
def captured_output() -> Iterator[Path]:
    """Send file descriptors 1 and 2 and Python's ``sys.stdout`` and ``sys.stderr`` (which a test
    runner may have replaced) to one temporary file, appending, for the block; yields its path."""
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    handle, name = tempfile.mkstemp(prefix="fuzz-output-")
    os.close(handle)
    fd = os.open(name, os.O_WRONLY | os.O_APPEND)
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(name, "a", buffering=1, errors="replace") as text, \
                contextlib.redirect_stdout(text), contextlib.redirect_stderr(text):
            os.dup2(fd, 1)
            os.dup2(fd, 2)
            yield Path(name)
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for f in (*saved, fd):
            os.close(f)


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def judge(target: Target, code: int | None, stderr: str, detail: str) -> str:
    """The status of a finished run (module notes), before time, memory and files are looked at."""
    if detail:
        return "exception"
    if code == 0:
        return "ok"
    if code not in (1, 2):
        return "exit"
    lines = [line for line in ANSI.sub("", stderr).splitlines() if line.strip() and not LIBRARY_LOG.match(line)]
    ok = len(lines) == 1 and lines[0].startswith(f"{target.prog}: error: ") and "Traceback" not in stderr
    return "error" if ok else "stderr"


def run_input(target: Target, mutated: Seed, folder: Path, ctx: Context, time_limit: float = 5.0,
              memory_limit_mb: float = 1024.0) -> Outcome:
    """Lay out ``target``'s files in the empty ``folder`` with ``mutated`` in place of its seed,
    run the command and judge it (module notes). ``folder`` is emptied first."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    target.lay_out(folder, mutated)
    given = _digests(folder)
    code, detail = None, ""
    before_kb = status_kb("VmRSS") or 0
    measured = reset_peak()
    with captured_output() as output:
        start = time.perf_counter()
        try:
            code = target.run(folder, ctx, mutated.name)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException as exc:  # noqa: BLE001 -- any escape is what the fuzzer looks for
            if isinstance(exc, KeyboardInterrupt):
                raise
            detail = "".join(traceback.format_exception(exc))
        seconds = time.perf_counter() - start
    stderr = output.read_text(errors="replace")
    output.unlink()
    peak_kb = status_kb("VmHWM") if measured else None
    peak_mb = None if peak_kb is None else max(0.0, (peak_kb - before_kb) / 1024)
    status = judge(target, code, stderr, detail)
    if status not in FAILURES:
        if seconds > time_limit:
            status = "slow"
        elif peak_mb is not None and peak_mb > memory_limit_mb:
            status = "memory"
        else:
            now = _digests(folder)
            if any(now.get(name) != digest for name, digest in given.items()):
                status, detail = "changed", f"changed: {[n for n, d in given.items() if now.get(n) != d]}"
    return Outcome(status, code, stderr, seconds, peak_mb, detail)
