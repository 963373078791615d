"""The allocator setting: freed large blocks leave resident memory at once (glibc)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

_CHILD = """
import json, sys
import numpy as np
from denoise.allocator import fix_mmap_threshold

def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024

fixed = fix_mmap_threshold() if sys.argv[1] == "fixed" else None
block = np.ones(24 * 2**20 // 8)  # mapped; freeing it raises glibc's default threshold to 24 MiB
del block
blocks = [np.ones(8 * 2**20 // 8) for _ in range(20)]  # 20 x 8 MiB, touched
before = rss()
del blocks[::2]  # every other one: 80 MiB freed, none of it at the heap's top
print(json.dumps({"fixed": fixed, "released_mb": (before - rss()) / 2**20}))
"""


def _released(setting: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", _CHILD, setting], capture_output=True, text=True, check=True,
                          cwd=Path(__file__).resolve().parents[1])
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc and /proc")
def test_fixed_threshold_returns_freed_blocks_at_once() -> None:
    fixed = _released("fixed")
    assert fixed["fixed"] is True and fixed["released_mb"] >= 76
    default = _released("default")  # why: the heap keeps the gaps
    assert default["released_mb"] < 40


_THP_CHILD = """
import json, sys
from denoise.allocator import use_huge_pages
asked = use_huge_pages(sys.argv[1] == "on")
import torch
block = torch.ones(16 * 2**20 // 4)  # 16 MiB, touched
huge = sum(int(line.split()[1]) for line in open("/proc/self/smaps") if line.startswith("AnonHugePages:"))
print(json.dumps({"asked": asked, "huge_kb": huge}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and transparent huge pages")
@pytest.mark.parametrize("preset,ask", [(None, "on"), ("0", "on"), (None, "off")],
                         ids=["unset", "user-said-0", "asked-off"])
def test_use_huge_pages_backs_large_torch_blocks(preset: str | None, ask: str) -> None:
    thp = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    if not thp.exists() or "[never]" in thp.read_text():
        pytest.skip("transparent huge pages are off on this kernel")
    env = {k: v for k, v in os.environ.items() if k != "THP_MEM_ALLOC_ENABLE"}
    if preset is not None:
        env["THP_MEM_ALLOC_ENABLE"] = preset  # a user's own setting is kept
    proc = subprocess.run([sys.executable, "-c", _THP_CHILD, ask], capture_output=True, text=True, check=True,
                          cwd=Path(__file__).resolve().parents[1], env=env)
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    wanted = preset is None and ask == "on"
    assert result["asked"] is wanted
    if wanted:
        assert result["huge_kb"] >= 8 * 1024  # most of the 16 MiB block (its 2 MiB-aligned part)
    elif "[madvise]" in thp.read_text():  # (with "always" every large block gets them anyway)
        assert result["huge_kb"] < 8 * 1024


_TRIM_CHILD = """
import json
import numpy as np
from denoise.allocator import fix_mmap_threshold, release_free_memory

def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024

fix_mmap_threshold()
blocks = [np.ones(512 * 2**10 // 8) for _ in range(200)]  # 100 MiB of heap blocks, touched
last = blocks[-1]
del blocks  # freed, but the last block keeps the heap's top: the freed space stays resident
before = rss()
released = release_free_memory()
print(json.dumps({"released": released, "released_mb": (before - rss()) / 2**20}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc and /proc")
def test_release_free_memory_hands_back_the_heaps_gaps() -> None:
    proc = subprocess.run([sys.executable, "-c", _TRIM_CHILD], capture_output=True, text=True, check=True,
                          cwd=Path(__file__).resolve().parents[1])
    m = json.loads(proc.stdout.strip().splitlines()[-1])
    assert m["released"] is True and m["released_mb"] >= 80, m
