"""Tiling: cores partition the image; a local operator gives the same result tiled or not."""
from __future__ import annotations

import numpy as np
import pytest

from denoise.tiling import band_cores, core_for_budget, cores_for_budget, plan_tiles, run_tiled, run_windows, window_span


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


@pytest.mark.parametrize("workers", [2, 3])
def test_run_windows_on_threads_is_the_serial_result_with_ordered_progress(rng, workers: int) -> None:
    img = rng.random((29, 41, 3))

    def fn(t):
        return _box_blur(img[t.wy0:t.wy1, t.wx0:t.wx1], 3)

    serial = run_windows(fn, 29, 41, 8, 3)
    calls: list[tuple[int, int]] = []
    threaded = run_windows(fn, 29, 41, 8, 3, progress=lambda n, total: calls.append((n, total)), workers=workers)
    assert np.array_equal(threaded, serial)
    assert [n for n, _ in calls] == list(range(1, len(calls) + 1)) and calls[-1][0] == calls[-1][1] > workers


def test_too_small_margin_differs(rng) -> None:
    img = rng.random((30, 30, 3))
    assert not np.allclose(run_tiled(lambda x: _box_blur(x, 3), img, 8, 1), _box_blur(img, 3))


def test_core_for_budget() -> None:
    assert core_for_budget(bytes_per_pixel=1000, max_bytes=1000 * 100**2, margin=10) == 80
    assert core_for_budget(bytes_per_pixel=1e9, max_bytes=1, margin=10) == 16


def _windows(h: int, w: int, core, margin: int, align: int) -> list[int]:
    return [(t.wy1 - t.wy0) * (t.wx1 - t.wx0) for t in plan_tiles(h, w, core, margin, align)]


@pytest.mark.parametrize("h,w,core", [(50, 37, (16, 32)), (64, 64, (64, 8)), (7, 90, (3, 90)), (1, 1, (1, 1))])
def test_rectangular_cores_partition_the_image(h: int, w: int, core: tuple[int, int]) -> None:
    covered = np.zeros((h, w), int)
    for t in plan_tiles(h, w, core, 3):
        covered[t.y0:t.y1, t.x0:t.x1] += 1
        assert t.y1 - t.y0 <= core[0] and t.x1 - t.x0 <= core[1]
    assert (covered == 1).all()


@pytest.mark.parametrize("h,w", [(1080, 1920), (720, 1280), (2160, 3840), (37, 5000), (300, 20)])
@pytest.mark.parametrize("budget_px", [300_000, 2_000_000])
def test_cores_for_budget_fits_and_beats_squares(h: int, w: int, budget_px: int) -> None:
    """Every window within the bound (alignment included), and no more window pixels in all than
    the square core of the same bound."""
    margin, align = 253, 32
    core = cores_for_budget(h, w, 1.0, budget_px, margin, align)
    windows = _windows(h, w, core, margin, align)
    if (h * w) <= budget_px:
        assert len(windows) == 1 and windows[0] == h * w
    assert max(windows) <= budget_px
    square = core_for_budget(1.0, budget_px, margin)
    if max(_windows(h, w, square, margin, align)) <= budget_px:
        assert sum(windows) <= sum(_windows(h, w, square, margin, align))


def test_cores_for_budget_full_height_strips_for_1080p() -> None:
    """The case it is for: 1920x1080 with a 253-px margin in two strips, 1.3x its pixels."""
    core = cores_for_budget(1080, 1920, 1.0, 2_000_000, 253, 32)
    windows = _windows(1080, 1920, core, 253, 32)
    assert len(windows) == 2 and sum(windows) < 1.3 * 1080 * 1920


def test_cores_for_budget_falls_back_to_the_smallest_cores() -> None:
    assert cores_for_budget(500, 500, 1.0, 10.0, 253, 32, minimum=16) == (32, 32)


def test_band_cores_for_the_whole_image_is_cores_for_budget() -> None:
    plan = band_cores(1080, 1080, 1920, 300.0, 200 * 2**20, 250, 32)
    assert plan is not None
    core, bound = plan
    assert core == cores_for_budget(1080, 1920, 300.0, 200 * 2**20, 250, 32)
    assert bound == sum((t.wy1 - t.wy0) * (t.wx1 - t.wx0) for t in plan_tiles(1080, 1920, core, 250, 32))


@pytest.mark.parametrize("rows,margin,align", [(96, 250, 32), (64, 15, 1), (320, 343, 32), (33, 7, 1)])
def test_band_cores_windows_fit_wherever_the_band_lies(rows: int, margin: int, align: int) -> None:
    """Every window of a band's tiles (cores cut from the band's first row, on the alignment grid,
    margins from the whole image) within the budget, and their pixels within the bound, for a band
    at the top, in the middle and at the bottom of the image."""
    height, width, bpp, budget = 2160, 3840, 350.0, 256 * 2**20
    plan = band_cores(rows, height, width, bpp, budget, margin, align)
    assert plan is not None
    core, bound = plan
    for y0 in (0, height // 2 // align * align, height - rows):
        total = 0
        for t in plan_tiles(rows, width, core, 0, align):
            wy = window_span(t.y0 + y0, t.y1 + y0, height, margin, align)
            wx = window_span(t.x0, t.x1, width, margin, align)
            assert (wy[1] - wy[0]) * (wx[1] - wx[0]) * bpp <= budget
            total += (wy[1] - wy[0]) * (wx[1] - wx[0])
        assert total <= bound


def test_band_cores_none_where_no_window_fits() -> None:
    assert band_cores(64, 2160, 3840, 350.0, 2**20, 343, 32) is None
