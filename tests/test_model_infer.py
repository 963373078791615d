"""Whole-image inference: tiled == untiled, range, aux handling."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from model.config import ModelConfig
from model.infer import denoise_image
from model.architectures import build_model
from model.transfer import HDR_MAX


def _model(**kw: object) -> torch.nn.Module:
    torch.manual_seed(0)
    model = build_model(ModelConfig(layers=3, growth=4, init_features=8, **kw))
    with torch.no_grad():  # non-trivial BatchNorm statistics, as after training
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    return model.eval()


def test_tiled_equals_whole() -> None:
    model = _model()
    color = (np.random.default_rng(2).random((45, 37, 3)) * 3).astype(np.float32)
    whole = denoise_image(model, color, core=64)
    tiled = denoise_image(model, color, core=16)
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-5)


def test_denoise_image_range_and_shape() -> None:
    model = _model()
    rng = np.random.default_rng(0)
    color = (rng.random((20, 24, 3)) * 5).astype(np.float32)
    color[0, 0] = [np.nan, np.inf, -3.0]
    out = denoise_image(model, color, core=8)
    assert out.shape == (20, 24, 3) and out.dtype == np.float32
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= HDR_MAX * (1 + 1e-5)
    assert not model.training


def test_identity_residual_model_returns_input() -> None:
    model = _model(output="residual")
    torch.nn.init.zeros_(model.tail[-1].weight)
    color = np.random.default_rng(1).random((9, 10, 3)).astype(np.float32) * 100
    np.testing.assert_allclose(denoise_image(model, color), color, rtol=1e-5, atol=1e-6)


def test_aux_required_iff_model_uses_it() -> None:
    color = np.ones((8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="aux buffers are required"):
        denoise_image(_model(aux_inputs=True), color)
    with pytest.raises(ValueError, match="takes no aux buffers"):
        denoise_image(_model(), color, np.zeros((8, 8, 6), np.float32))
    out = denoise_image(_model(aux_inputs=True), color, np.zeros((8, 8, 6), np.float32))
    assert out.shape == (8, 8, 3)
