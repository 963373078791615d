"""The Denoiser object: kinds in == kinds out, tiled == untiled, invalid input counted, errors."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from imaging.errors import DenoiserError
from model.architectures import build_model
from model.checkpoint import save_checkpoint
from model.config import ModelConfig
from pipeline.denoise import Denoiser, count_invalid

TINY = ModelConfig(layers=3, growth=4, init_features=8)


def write_tiny_checkpoint(path: Path, config: ModelConfig = TINY, seed: int = 0) -> Path:
    """A random (untrained) model with non-trivial BatchNorm statistics, saved like `train` does."""
    torch.manual_seed(seed)
    model = build_model(config)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    save_checkpoint(path, model, step=0)
    return path


@pytest.fixture
def ckpt(tmp_path: Path) -> Path:
    return write_tiny_checkpoint(tmp_path / "tiny.ckpt")


def _image(h: int, w: int, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random((h, w, 3)) * 4).astype(np.float32)


def test_tiled_equals_untiled_within_1e4(ckpt: Path) -> None:
    img = _image(61, 47)
    whole = Denoiser(ckpt, max_memory_mb=1024)
    tiny = Denoiser(ckpt, max_memory_mb=0.05)
    assert whole.core_size() >= 61 and tiny.core_size() < 47
    a = whole.denoise_array(img)
    b = tiny.denoise_array(img)
    assert a.tiles == 1 and b.tiles > 4
    np.testing.assert_allclose(b.image, a.image, rtol=1e-4, atol=1e-4)


def test_call_returns_same_kind(ckpt: Path, mi: Any) -> None:
    den = Denoiser(ckpt)
    img = _image(16, 20)
    ref = den(img)
    assert isinstance(ref, np.ndarray) and ref.shape == img.shape and ref.dtype == np.float32
    out_t = den(torch.from_numpy(img))
    assert isinstance(out_t, torch.Tensor)
    np.testing.assert_allclose(out_t.numpy(), ref, rtol=1e-6)
    out_mi = den(mi.TensorXf(img))
    assert isinstance(out_mi, mi.TensorXf)
    np.testing.assert_allclose(np.array(out_mi), ref, rtol=1e-6)
    out_bmp = den(mi.Bitmap(img))
    assert isinstance(out_bmp, mi.Bitmap)
    np.testing.assert_allclose(np.array(out_bmp), ref, rtol=1e-6)
    rgba = np.concatenate([img, np.full((16, 20, 1), 0.5, np.float32)], axis=2)
    out4 = den(rgba)
    assert out4.shape == (16, 20, 4) and np.all(out4[..., 3] == 0.5)
    np.testing.assert_allclose(out4[..., :3], ref, rtol=1e-6)


def test_invalid_pixels_counted_and_not_propagated(ckpt: Path) -> None:
    img = _image(24, 24)
    img[3, 4] = [np.nan, np.inf, -np.inf]
    img[10, 10, 1] = -2.0
    assert count_invalid(img) == (3, 1)
    res = Denoiser(ckpt).denoise_array(img)
    assert (res.nonfinite, res.negative) == (3, 1)
    assert np.isfinite(res.image).all() and res.image.min() >= 0.0


def test_aov_model_needs_aovs(tmp_path: Path) -> None:
    path = write_tiny_checkpoint(tmp_path / "aux.ckpt", ModelConfig(layers=2, growth=4, init_features=8,
                                                                    aux_inputs=True))
    den = Denoiser(path)
    img = _image(16, 16)
    assert den.needs_aovs
    with pytest.raises(DenoiserError, match="needs albedo and normals"):
        den.denoise_array(img)
    with pytest.raises(DenoiserError, match="AOV shape"):
        den.denoise_array(img, np.zeros((8, 8, 3)), np.zeros((16, 16, 3)))
    out = den.denoise_array(img, np.full_like(img, 0.5), np.zeros_like(img)).image
    assert out.shape == img.shape and np.isfinite(out).all()


@pytest.mark.parametrize("shape", [(1, 1), (1, 37), (29, 1), (17, 33)])
def test_degenerate_and_odd_sizes(ckpt: Path, shape: tuple[int, int]) -> None:
    out = Denoiser(ckpt, max_memory_mb=0.05)(_image(*shape))
    assert out.shape == (*shape, 3) and np.isfinite(out).all()


def test_bad_arguments_raise_clear_errors(tmp_path: Path, ckpt: Path) -> None:
    with pytest.raises(DenoiserError, match="missing.ckpt"):
        Denoiser(tmp_path / "missing.ckpt")
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(DenoiserError, match="junk.ckpt"):
        Denoiser(junk)
    with pytest.raises(DenoiserError, match="max memory"):
        Denoiser(ckpt, max_memory_mb=0)
    with pytest.raises(DenoiserError, match="HxWx3"):
        Denoiser(ckpt).denoise_array(np.zeros((4, 4), np.float32))
