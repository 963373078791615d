"""How much memory this process can still get, and the check every reader makes before it allocates.

A file's header says how many pixels it holds; a reader compares what those pixels need with
:func:`available_bytes` before allocating them, so that a header that lies (or an image too large
for the machine) ends in one line naming both sizes instead of an allocation failure deep in a
native library, or the kernel's OOM killer. Linux only: elsewhere the limit is unknown (None) and
only the file-length checks of the readers apply.
"""
from __future__ import annotations

import resource
from pathlib import Path

from imaging.errors import DenoiserError

MB = 2**20
_MEMINFO = Path("/proc/meminfo")
_STATUS = Path("/proc/self/status")
_CGROUP = Path("/sys/fs/cgroup")


def kb_field(path: Path, key: str) -> int | None:
    """A ``key: N kB`` line of a /proc file (``/proc/meminfo``, ``/proc/self/status``), in bytes;
    None when it cannot be read."""
    try:
        for line in path.read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _cgroup_room() -> int | None:
    """What the process's cgroup (v2) still allows: memory.max - memory.current; None if unlimited."""
    try:
        limit = (_CGROUP / "memory.max").read_text().strip()
        used = int((_CGROUP / "memory.current").read_text().strip())
    except (OSError, ValueError):
        return None
    return None if limit == "max" else max(0, int(limit) - used)


def _rlimit_room(kind: int, used_key: str) -> int | None:
    """What an address-space rlimit still allows beyond the process's current size; None if unlimited."""
    soft, _ = resource.getrlimit(kind)
    if soft == resource.RLIM_INFINITY:
        return None
    used = kb_field(_STATUS, used_key)
    return max(0, soft - (used or 0))


def available_bytes() -> int | None:
    """The bytes this process can still allocate: the least of the kernel's estimate of available
    memory (``MemAvailable``), the cgroup's room and the room left by ``RLIMIT_AS`` /
    ``RLIMIT_DATA``; None where none of them can be read."""
    rooms = [kb_field(_MEMINFO, "MemAvailable"), _cgroup_room(),
             _rlimit_room(resource.RLIMIT_AS, "VmSize"), _rlimit_room(resource.RLIMIT_DATA, "VmData")]
    known = [r for r in rooms if r is not None]
    return min(known) if known else None


def megabytes(n: float) -> str:
    """``n`` bytes as whole megabytes with thousands separators (``1,234 MB``), below 1 MB as bytes."""
    return f"{n / MB:,.0f} MB" if n >= MB else f"{n:,.0f} bytes"


def fits_in_memory(need: int, limit: int | None = None) -> tuple[bool, int | None]:
    """(whether ``need`` bytes fit, the limit compared with): ``limit`` if given, else
    :func:`available_bytes` (unknown: always fits)."""
    room = available_bytes() if limit is None else limit
    return (room is None or need <= room), room


def require_memory(need: int, what: str, error: type[DenoiserError] = DenoiserError) -> None:
    """Raise ``error`` with the one line ``WHAT need N MB, more than the M MB of memory available``
    when ``need`` bytes do not fit (:func:`fits_in_memory`): the refusal a command gives before an
    allocation that cannot succeed, instead of the allocation's own failure."""
    fits, room = fits_in_memory(need)
    if not fits:
        raise error(f"{what} need {megabytes(need)}, more than the {megabytes(room)} of memory available")
