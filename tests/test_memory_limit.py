"""The memory a process can still get: the kernel's estimate, bounded by an address-space limit."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from imaging import memory_limit
from imaging.memory_limit import available_bytes, fits_in_memory, megabytes


def test_available_is_at_most_the_kernels_estimate() -> None:
    room = available_bytes()
    meminfo = memory_limit.kb_field(memory_limit._MEMINFO, "MemAvailable")
    if meminfo is None:
        pytest.skip("no /proc/meminfo")
    assert room is not None and 0 <= room <= meminfo


def test_an_address_space_limit_bounds_it() -> None:
    """A child process limits its own address space to 512 MB beyond its size: what it may still
    allocate is at most that, and an allocation past it is refused by the check, not attempted."""
    code = textwrap.dedent("""
        import resource
        from imaging import memory_limit
        size = memory_limit.kb_field(memory_limit._STATUS, "VmSize")
        resource.setrlimit(resource.RLIMIT_AS, (size + 512 * 2**20, resource.RLIM_INFINITY))
        room = memory_limit.available_bytes()
        print(room, memory_limit.fits_in_memory(600 * 2**20)[0], memory_limit.fits_in_memory(100 * 2**20)[0])
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    room, big, small = done.stdout.split()
    assert 400 * 2**20 < int(room) <= 512 * 2**20 and (big, small) == ("False", "True")


def test_fits_with_a_given_limit_and_messages() -> None:
    assert fits_in_memory(10, 10) == (True, 10) and fits_in_memory(11, 10) == (False, 10)
    assert megabytes(3 * 2**30) == "3,072 MB" and megabytes(1000) == "1,000 bytes"


def test_require_memory_refuses_in_one_line_naming_both(monkeypatch: pytest.MonkeyPatch) -> None:
    from imaging.errors import RenderError

    monkeypatch.setattr(memory_limit, "available_bytes", lambda: 2**30)
    memory_limit.require_memory(2**30, "it")
    with pytest.raises(RenderError, match=r"^4x4 pixels need 2,048 MB, more than the 1,024 MB of memory available$"):
        memory_limit.require_memory(2**31, "4x4 pixels", RenderError)
