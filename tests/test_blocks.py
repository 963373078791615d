"""Row blocks and the thread pool that runs numpy passes over them (imaging.blocks)."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from imaging.blocks import parallel_map, row_blocks


@pytest.mark.parametrize("workers", [0, 1, 2, 5])
def test_parallel_map_keeps_the_order_and_the_serial_sum(workers: int) -> None:
    rng = np.random.default_rng(0)
    data = rng.random(100_000) * 1e6
    blocks = [data[i:i + 7_000] for i in range(0, len(data), 7_000)]
    sums = parallel_map(lambda b: float(b.sum()), blocks, workers)
    assert sums == [float(b.sum()) for b in blocks]
    total = 0.0
    for s in sums:
        total += s
    assert total == sum(float(b.sum()) for b in blocks)


def test_parallel_map_runs_on_several_threads_and_raises_what_fn_raises() -> None:
    seen: set[int] = set()
    barrier = threading.Barrier(2, timeout=10)

    def fn(i: int) -> int:
        seen.add(threading.get_ident())
        barrier.wait()  # only passes if two items run at once
        return i * i

    assert parallel_map(fn, range(4), 2) == [0, 1, 4, 9]
    assert len(seen) == 2

    def bad(i: int) -> int:
        if i == 3:
            raise ValueError("item 3")
        return i

    with pytest.raises(ValueError, match="item 3"):
        parallel_map(bad, range(6), 2)


@pytest.mark.parametrize("height, parts", [(720, 2), (7, 3), (1, 4), (100, 1), (5, 5)])
def test_row_blocks_cover_the_rows_in_at_least_parts_blocks(height: int, parts: int) -> None:
    blocks = list(row_blocks(height, 64, 4.0, 1e9, parts))
    assert blocks[0].start == 0 and blocks[-1].stop == height
    assert all(a.stop == b.start for a, b in zip(blocks, blocks[1:]))
    assert len(blocks) >= min(parts, height)
    small = list(row_blocks(height, 64, 4.0, 64 * 4.0 * 2, parts))  # two rows a block at most
    assert all(b.stop - b.start <= 2 for b in small)
