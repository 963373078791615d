"""When this process started, on ``time.perf_counter()``'s clock: a command's wall time, its
interpreter start and imports included, as ``time`` (the shell's) counts it."""
from __future__ import annotations

import os
import time
from pathlib import Path


def process_started(stat: str | Path = "/proc/self/stat") -> float | None:
    """The ``time.perf_counter()`` value at which this process started (Linux: its start time in
    ``/proc/self/stat`` against the time since boot); None where that cannot be read."""
    try:
        fields = Path(stat).read_text().rsplit(")", 1)[1].split()
        started_since_boot = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22: starttime, in ticks
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - started_since_boot
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    return time.perf_counter() - age if age >= 0 else None
