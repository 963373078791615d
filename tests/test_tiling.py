"""Tiling: cores partition the image; a local operator gives the same result tiled or not."""
from __future__ import annotations

import numpy as np
import pytest

from imaging.tiling import core_for_budget, plan_tiles, run_tiled


@pytest.mark.parametrize("h,w,core,margin", [(1, 1, 8, 3), (1, 37, 8, 3), (37, 1, 8, 3),
                                             (33, 47, 10, 4), (64, 64, 64, 5), (20, 20, 7, 0)])
def test_cores_partition_the_image(h: int, w: int, core: int, margin: int) -> None:
    hits = np.zeros((h, w), int)
    for t in plan_tiles(h, w, core, margin):
        hits[t.y0:t.y1, t.x0:t.x1] += 1
        assert t.y1 - t.y0 <= core and t.x1 - t.x0 <= core
        assert 0 <= t.wy0 <= t.y0 and t.y1 <= t.wy1 <= h
        assert t.wx0 == max(0, t.x0 - margin) and t.wx1 == min(w, t.x1 + margin)
    assert (hits == 1).all()


def _box_blur(img: np.ndarray, radius: int) -> np.ndarray:
    """A local operator with receptive-field radius ``radius`` and zero padding."""
    pad = np.pad(img, ((radius, radius), (radius, radius), (0, 0)))
    out = np.zeros_like(img)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            out += pad[dy:dy + img.shape[0], dx:dx + img.shape[1]]
    return out


@pytest.mark.parametrize("shape", [(1, 1), (1, 30), (30, 1), (29, 41), (50, 50)])
def test_tiled_equals_untiled_when_margin_covers_receptive_field(rng, shape) -> None:
    img = rng.random((*shape, 3))
    calls = []
    tiled = run_tiled(lambda x: _box_blur(x, 3), img, core=8, margin=3,
                      progress=lambda n, total: calls.append((n, total)))
    np.testing.assert_allclose(tiled, _box_blur(img, 3), rtol=0, atol=1e-12)
    assert calls[-1][0] == calls[-1][1]


def test_too_small_margin_differs(rng) -> None:
    img = rng.random((30, 30, 3))
    assert not np.allclose(run_tiled(lambda x: _box_blur(x, 3), img, 8, 1), _box_blur(img, 3))


def test_core_for_budget() -> None:
    assert core_for_budget(bytes_per_pixel=1000, max_bytes=1000 * 100**2, margin=10) == 80
    assert core_for_budget(bytes_per_pixel=1e9, max_bytes=1, margin=10) == 16
