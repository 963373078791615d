"""Whole-image passes a block of rows at a time, so their scratch memory does not grow with the image.

The output stages (EXR and PNG writing, display tonemapping, metrics, the report) walk an image
in horizontal blocks: :func:`row_blocks` picks as many rows per block as ``max_bytes`` allows for
a pass that costs ``bytes_per_pixel`` of temporaries, and at least one. :func:`parallel_map` runs
such blocks on several threads at once (numpy's loops release the GIL): a pass over ``workers``
blocks at a time sizes each block for ``max_bytes / workers``.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

DEFAULT_BLOCK_BYTES = 16 * 2**20  # a block's temporaries: a small part of any memory budget


def block_rows(width: int, bytes_per_pixel: float, max_bytes: float, most: int) -> int:
    """Rows per block of a pass costing ``bytes_per_pixel`` of scratch: as many as ``max_bytes``
    allows, at least 1, at most ``most`` (at least 1)."""
    return max(1, min(max(1, most), int(max_bytes // (bytes_per_pixel * max(1, width)))))


def row_blocks(height: int, width: int, bytes_per_pixel: float,
               max_bytes: float = DEFAULT_BLOCK_BYTES, parts: int = 1) -> Iterator[slice]:
    """Slices covering rows ``0..height`` in order, each within ``max_bytes`` of a pass costing
    ``bytes_per_pixel`` (at least one row each), and at least ``parts`` of them where the image
    has that many rows (work for ``parts`` threads)."""
    rows = block_rows(width, bytes_per_pixel, max_bytes, -(-height // max(1, parts)))
    for y in range(0, height, rows):
        yield slice(y, min(height, y + rows))


# Below this many pixels a whole-image pass runs on one thread: measured at 128^2 (u-fast, 2 threads),
# handing its blocks to the pool cost ~1 ms a call more than it saved.
PARALLEL_MIN_PIXELS = 2**18


def pass_workers(pixels: int, threads: int) -> int:
    """Threads for a numpy pass over an image of ``pixels``: ``threads`` (at least 1), or 1 below
    :data:`PARALLEL_MIN_PIXELS`."""
    return max(1, threads) if pixels >= PARALLEL_MIN_PIXELS else 1


@lru_cache(maxsize=4)
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="blocks")


def parallel_map(fn: Callable[[T], R], items: Iterable[T], workers: int) -> list[R]:
    """``[fn(item) for item in items]``, up to ``workers`` items at a time on a pool of threads:
    the same results in the same order (a sum over them in that order is the serial one bit for
    bit). Worth it for numpy passes over large blocks, whose loops release the GIL; ``workers`` <= 1
    or a single item runs here. An exception of ``fn`` is raised here."""
    items = list(items)
    if workers <= 1 or len(items) <= 1:
        return [fn(item) for item in items]
    return list(_pool(workers).map(fn, items))
