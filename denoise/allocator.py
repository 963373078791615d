"""Large freed blocks go back to the operating system at once, so resident memory follows the memory in use.

glibc's malloc serves a request of at least its *mmap threshold* with a mapping of its own, unmapped
when it is freed; smaller requests come from the heap, whose freed gaps stay resident. The threshold
starts at 128 KiB and, by default, rises to the size of every mapped block freed, up to 32 MiB. A
tiled denoiser's temporaries are a few to tens of MiB and change size from layer to layer and from
tile to tile: once the threshold has risen they come from the heap, and its gaps add up to about
twice the memory in use (``benchmarks/denoise_memory.py --parts calibrate`` measures a tile with
and without this setting). :func:`fix_mmap_threshold` fixes the threshold, which also stops it
moving, and sets the heap's trim threshold to twice it (glibc's own ratio; fixing one threshold
otherwise leaves the other at 128 KiB). The price of a mapping is a fresh page for every page
of the block the process touches (page faults: system time): measured on 2 cores, the whole
denoise chain of ``u-fast``/``u-balanced`` runs ~10-25 % slower than with glibc's default at 256^2
to 1080p. A 16 MiB threshold ran as fast as the default but let two threads' heaps keep gaps:
a tile planned for 256 MB then peaked anywhere from 1.0 to 1.45x of it from run to run; the
budget is a promise, so the threshold stays at 1 MiB.

The faults are paid per page: :func:`use_huge_pages` asks torch's CPU allocator to back its
blocks of 2 MiB or more with transparent huge pages (``THP_MEM_ALLOC_ENABLE``; numpy does the same
on its own), 512 times fewer faults for the same bytes. Measured on 2 cores (u-fast in bfloat16,
the whole denoising call, best of 3, two runs each): 1080p 0.45-0.60 s/MP against 0.65-0.74,
3840x2160 under a 256 MB budget 1.23 against 1.51-1.52, 256^2 unchanged (0.60-0.76 against
0.68-0.70); the same peak memory. It works where the kernel's transparent huge pages are
``always`` or ``madvise`` (Debian's default) and changes nothing where they are ``never``.

Huge pages pay from a process's second call on. Its first call waits while the kernel finds 2 MiB
pages (with ``defrag`` at ``madvise``, the default, it compacts memory for them): measured on 2
cores, flat-s-allspp in bfloat16 on a 720p image, five fresh processes each, first call 1.61-2.08 s
with them against 1.42-1.50 without, a second call 1.02-1.28 against 1.38-1.50. A process that
denoises one image (the ``denoise`` command) therefore asks for none (``use_huge_pages(False)``).
"""
from __future__ import annotations

import ctypes
import os
import platform

M_TRIM_THRESHOLD = -1  # mallopt's parameter numbers (malloc.h)
M_MMAP_THRESHOLD = -3
DEFAULT_THRESHOLD = 2**20
THP_VARIABLE = "THP_MEM_ALLOC_ENABLE"  # read by torch's CPU allocator (c10) at its first large allocation


def fix_mmap_threshold(threshold: int = DEFAULT_THRESHOLD) -> bool:
    """Serve every allocation of at least ``threshold`` bytes from a mapping of its own, returned
    to the system when freed, and trim the heap's top beyond ``2 * threshold``, for the rest of
    this process (all threads). True when set; False where the C library is not glibc (nothing
    is changed)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(None)
        return bool(libc.mallopt(ctypes.c_int(M_MMAP_THRESHOLD), ctypes.c_int(int(threshold)))) and \
            bool(libc.mallopt(ctypes.c_int(M_TRIM_THRESHOLD), ctypes.c_int(2 * int(threshold))))
    except (OSError, AttributeError):
        return False


def release_free_memory() -> bool:
    """Hand the free memory inside glibc's heaps back to the system (``malloc_trim(0)``: every
    arena, not only the top of the main one). Blocks below the mmap threshold (a whole-image pass's
    row blocks of a few hundred KiB, numpy's small temporaries, torch's) are freed into their
    thread's heap, and a live block after them keeps the freed space resident: measured after the
    noise statistics and the networks of a 1536x1024 image, 15-17 MB each. False where the C
    library is not glibc (nothing is done)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        ctypes.CDLL(None).malloc_trim(ctypes.c_size_t(0))
        return True
    except (OSError, AttributeError):
        return False


def use_huge_pages(on: bool = True) -> bool:
    """Ask torch's CPU allocator to back blocks of 2 MiB or more with transparent huge pages
    (``THP_MEM_ALLOC_ENABLE=1``; ``on`` False: not, ``=0``), unless the environment already says
    otherwise. Torch reads the variable once, at its first such allocation in the process: called
    after that, it changes nothing. True when the variable is (now) 1."""
    return os.environ.setdefault(THP_VARIABLE, "1" if on else "0") == "1"
