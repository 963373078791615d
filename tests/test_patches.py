"""Patch sampling: flat-patch filter, identical augmentation, determinism."""
from __future__ import annotations

import numpy as np
import pytest

from imaging.errors import ConfigError, DatasetError
from training.patches import (PatchConfig, TrainingPair, augment, detail_choice, detail_probabilities, sample_batch,
                           unique_counts)


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


def test_camera_normals_turn_with_the_image(rng: np.random.Generator) -> None:
    """A sphere centred in the patch, its camera-space normals (X toward the image's left, Y up):
    every flip and transpose of it is the same sphere, so its normals must come back as they were
    (exactly) when augmentation turns them; left as they are, most transforms break them."""
    r, c = np.mgrid[0:8, 0:8].astype(np.float32) - 3.5
    normals = np.stack([-c / 6, -r / 6, -np.sqrt(1 - (r * r + c * c) / 36)], axis=-1).astype(np.float32)
    rgb = rng.random((8, 8, 3), dtype=np.float32)
    noisy = np.concatenate([rgb, rgb, normals], axis=-1)
    kept = 0
    for _ in range(32):
        turned, _ = augment(noisy, rgb, rng, camera_normals=6)
        np.testing.assert_array_equal(turned[..., 6:9], normals)
        left, _ = augment(noisy, rgb, rng)
        kept += np.array_equal(left[..., 6:9], normals)
    assert kept < 16  # only the identity (1 of 8 transforms) keeps them untouched


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


def test_detail_probabilities_mix_uniform_and_spread() -> None:
    refs = np.zeros((4, 8, 8, 3), np.float32)
    refs[1, ::2] = 1.0  # std 0.5
    refs[2, :, ::4] = 2.0  # std 2 * sqrt(0.25 * 0.75) = 0.866
    spread = np.array([0.0, 0.5, np.sqrt(0.75), 0.0])
    for detail in (0.0, 0.3, 1.0):
        p = detail_probabilities(refs, detail)
        np.testing.assert_allclose(p, (1 - detail) / 4 + detail * spread / spread.sum(), rtol=1e-6)
        assert p.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(detail_probabilities(np.zeros((3, 4, 4, 3)), 1.0), 1 / 3)  # all flat: uniform
    chosen = detail_choice(refs, 2, 1.0, np.random.default_rng(0))
    assert sorted(chosen.tolist()) == [1, 2]  # the flat crops keep only a tiny probability
    assert len(set(detail_choice(refs, 4, 1.0, np.random.default_rng(1)).tolist())) == 4


def test_detail_crops_favour_the_textured_half_and_keep_pairs_aligned() -> None:
    """Left half a smooth ramp (passes the unique filter, small spread), right half strong texture:
    detail sampling takes more right-half crops than uniform sampling, input and target aligned."""
    rng = np.random.default_rng(2)
    img = np.empty((32, 128, 3), np.float32)
    img[:, :64] = np.linspace(0.4, 0.5, 32 * 64 * 3, dtype=np.float32).reshape(32, 64, 3)
    img[:, 64:] = rng.random((32, 64, 3), dtype=np.float32)
    pair = TrainingPair(img, img * 2.0, scene=0, spp=4)

    def textured_share(detail: float) -> float:
        noisy, ref = sample_batch([pair], 256, PatchConfig(size=16, augment=False, detail=detail),
                                  np.random.default_rng(3))
        np.testing.assert_array_equal(ref, noisy * 2.0)
        return float((noisy.reshape(256, -1).std(axis=1) > 0.1).mean())

    uniform, detailed = textured_share(0.0), textured_share(1.0)
    assert 0.3 < uniform < 0.7 and detailed > uniform + 0.2


def test_detail_zero_keeps_the_uniform_stream_and_bad_values_are_refused() -> None:
    img = np.random.default_rng(1).random((40, 40, 3), dtype=np.float32)
    pairs = [TrainingPair(img, img * 0.5, 0, 4)]
    a = sample_batch(pairs, 8, PatchConfig(), np.random.default_rng([3, 5]))
    b = sample_batch(pairs, 8, PatchConfig(detail=0.0), np.random.default_rng([3, 5]))
    np.testing.assert_array_equal(a[0], b[0])
    for bad in (-0.1, 1.5, True, "x"):
        with pytest.raises(ConfigError, match="patch detail must be in"):
            PatchConfig(detail=bad)
