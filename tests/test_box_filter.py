"""Box-window sums and means: against brute force, exact per tile, beside a firefly."""
from __future__ import annotations

import math

import numpy as np
import pytest

from denoise.box_filter import box_mean_2d, box_sum_2d


def box_mean(img: np.ndarray, radius: int) -> np.ndarray:
    """:func:`box_mean_2d` of each channel of an HxWxC image."""
    return np.stack([box_mean_2d(img[:, :, c], radius) for c in range(img.shape[2])], axis=2)


def _brute_box_mean(img: np.ndarray, r: int) -> np.ndarray:
    h, w, _ = img.shape
    out = np.empty_like(img, dtype=np.float64)
    for y in range(h):
        for x in range(w):
            out[y, x] = img[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1].mean(axis=(0, 1))
    return out


@pytest.mark.parametrize("radius", [0, 1, 3, 20])
def test_box_mean_matches_brute_force(radius: int) -> None:
    img = np.random.default_rng(0).random((7, 5, 2)).astype(np.float32)
    np.testing.assert_allclose(box_mean(img, radius), _brute_box_mean(img, radius), rtol=1e-5)


@pytest.mark.parametrize("radius", [1, 2, 5])
def test_box_mean_of_a_tile_with_its_context_is_the_whole_image_s(radius: int) -> None:
    """Bit for bit: a core's window sums add the same values in the same order whichever
    rectangle holds the core and ``radius`` pixels beside it (cut at the image's borders)."""
    img = (np.random.default_rng(1).random((40, 33, 2)) ** 4 * 1e3).astype(np.float32)
    whole = box_mean(img, radius)
    for y0, y1, x0, x1 in [(0, 11, 0, 9), (11, 29, 9, 24), (29, 40, 24, 33), (5, 6, 0, 33)]:
        wy0, wx0 = max(0, y0 - radius), max(0, x0 - radius)
        tile = box_mean(img[wy0:y1 + radius, wx0:x1 + radius], radius)
        assert np.array_equal(tile[y0 - wy0:y1 - wy0, x0 - wx0:x1 - wx0], whole[y0:y1, x0:x1])


def test_box_mean_beside_a_firefly_keeps_a_dim_window_s_mean() -> None:
    """A running sum loses a dim window's sum to cancellation once a firefly's square (1e12) has
    entered it; the window's own sums do not (exact sum: math.fsum)."""
    img = np.random.default_rng(2).random((12, 300, 1)) * 1e-2
    img[5, 3, 0] = 1e12
    got = box_mean(img, 2)[:, :, 0]
    for y, x in [(5, 20), (5, 299), (7, 150), (0, 0)]:
        window = img[max(0, y - 2):y + 3, max(0, x - 2):x + 3, 0]
        assert got[y, x] == pytest.approx(math.fsum(window.ravel()) / window.size, rel=1e-6)


def test_box_sum_is_the_mean_times_the_window_s_pixels() -> None:
    img = np.random.default_rng(3).random((9, 6)).astype(np.float32)
    ones = np.ones_like(img)
    np.testing.assert_allclose(box_sum_2d(img, 2), box_mean_2d(img, 2) * box_sum_2d(ones, 2), rtol=1e-6)
    assert box_sum_2d(ones, 2)[0, 0] == 9 and box_sum_2d(ones, 2)[4, 3] == 25


def test_negative_radius_is_refused() -> None:
    with pytest.raises(ValueError, match="radius"):
        box_mean_2d(np.zeros((2, 2), np.float32), -1)
    with pytest.raises(ValueError, match="radius"):
        box_sum_2d(np.zeros((2, 2), np.float32), -1)
