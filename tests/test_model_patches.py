"""Patch sampling: flat-patch filter, identical augmentation, determinism."""
from __future__ import annotations

import numpy as np
import pytest

from imaging.errors import DatasetError
from model.patches import PatchConfig, TrainingPair, augment, sample_batch, unique_counts


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def test_unique_counts(rng: np.random.Generator) -> None:
    flat = np.full((1, 28, 28, 3), 0.25, np.float32)
    textured = rng.random((1, 28, 28, 3), dtype=np.float32)
    assert unique_counts(flat).tolist() == [1]
    assert unique_counts(textured).tolist() == [28 * 28 * 3]


def test_flat_patch_dropped_textured_kept(rng: np.random.Generator) -> None:
    # Left half of the image flat, right half textured: only crops from the right survive.
    img = np.full((28, 56, 3), 0.5, np.float32)
    img[:, 28:] = rng.random((28, 28, 3), dtype=np.float32)
    pair = TrainingPair(img, img.copy(), scene=0, spp=4)
    noisy, ref = sample_batch([pair], 16, PatchConfig(augment=False), rng)
    assert noisy.shape == (16, 28, 28, 3) and ref.shape == (16, 28, 28, 3)
    assert (unique_counts(noisy) >= 100).all()
    np.testing.assert_array_equal(noisy, ref)  # same crop position for input and target


def test_all_flat_raises(rng: np.random.Generator) -> None:
    img = np.zeros((32, 32, 3), np.float32)
    with pytest.raises(DatasetError, match="almost flat"):
        sample_batch([TrainingPair(img, img, 0, 4)], 4, PatchConfig(max_rounds=3), rng)


def test_image_smaller_than_patch(rng: np.random.Generator) -> None:
    img = rng.random((20, 40, 3), dtype=np.float32)
    with pytest.raises(DatasetError, match="smaller than the 28px patch"):
        sample_batch([TrainingPair(img, img, 7, 4)], 4, PatchConfig(), rng)


def test_augmentation_identical_on_input_and_target(rng: np.random.Generator) -> None:
    base = rng.random((8, 8, 3), dtype=np.float32)
    noisy = np.concatenate([base, rng.random((8, 8, 6), dtype=np.float32)], axis=-1)
    seen = set()
    for _ in range(64):
        out_noisy, out_ref = augment(noisy, base, rng)
        assert out_noisy.shape == (8, 8, 9) and out_ref.shape == (8, 8, 3)
        np.testing.assert_array_equal(out_noisy[..., :3], out_ref)
        seen.add(out_ref.tobytes())
    assert len(seen) > 8  # several distinct flips/transposes/permutations occurred


def test_augmentation_moves_aux_consistently(rng: np.random.Generator) -> None:
    rgb = rng.random((6, 6, 3), dtype=np.float32)
    red = rgb[..., :1]
    noisy = np.concatenate([rgb, rgb + 10.0, red + 20.0, red + 30.0, red + 40.0], axis=-1)
    for _ in range(32):
        out_noisy, out_ref = augment(noisy, rgb, rng)
        np.testing.assert_array_equal(out_noisy[..., 3:6], out_ref + 10.0)  # albedo permuted like RGB
        normal = out_noisy[..., 6:9]
        np.testing.assert_allclose(normal[..., 1] - normal[..., 0], 10.0, atol=1e-5)  # XYZ order kept
        np.testing.assert_allclose(normal[..., 2] - normal[..., 1], 10.0, atol=1e-5)
        # ...but moved spatially with the image: X is the (flipped) red channel wherever it went
        assert any(np.allclose(normal[..., 0] - 20.0, out_ref[..., c], atol=1e-5) for c in range(3))


def test_deterministic_for_same_seed() -> None:
    img = np.random.default_rng(1).random((40, 40, 3), dtype=np.float32)
    pairs = [TrainingPair(img, img * 0.5, 0, 4)]
    a = sample_batch(pairs, 8, PatchConfig(), np.random.default_rng([3, 5]))
    b = sample_batch(pairs, 8, PatchConfig(), np.random.default_rng([3, 5]))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[1], a[0] * 0.5)
