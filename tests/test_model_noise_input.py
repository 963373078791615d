"""Noise channels (model.noise_input): converged -> 0, unknown -> flag 0, scale with the noise."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from model.noise_input import drop_noise, noise_channels
from model.transfer import HDR_MAX, get_transfer

PU = get_transfer("pu")


def test_zero_variance_is_zero_noise_and_known() -> None:
    color = np.full((4, 5, 3), 0.7, np.float32)
    out = noise_channels(color, np.zeros_like(color), PU)
    assert out.shape == (4, 5, 4) and out.dtype == np.float32
    assert np.all(out[..., :3] == 0) and np.all(out[..., 3] == 1)


def test_unknown_variance_is_all_zero() -> None:
    out = noise_channels(np.ones((3, 3, 3), np.float32), None, PU)
    assert np.all(out == 0)


def test_one_standard_deviation_in_transfer_space() -> None:
    color = np.array([[[0.0, 1.0, 100.0]]], np.float32)
    variance = np.array([[[0.01, 0.04, 25.0]]], np.float32)
    out = noise_channels(color, variance, PU)
    want = PU.forward(torch.tensor([0.1, 1.2, 105.0])) - PU.forward(torch.tensor([0.0, 1.0, 100.0]))
    np.testing.assert_allclose(out[0, 0, :3], want.numpy(), rtol=1e-5)
    more = noise_channels(color, variance * 4, PU)
    assert np.all(more[..., :3] > out[..., :3])  # more noise, larger channels


def test_extreme_variance_stays_finite_and_bounded() -> None:
    color = np.array([[[0.0, HDR_MAX, 1.0]]], np.float32)
    variance = np.array([[[np.inf, np.nan, 1e30]]], np.float32)
    out = noise_channels(color, variance, PU)
    assert np.isfinite(out).all() and out.min() >= 0 and out[..., :3].max() <= 1.0


def test_drop_noise_hides_a_share_of_patches() -> None:
    batch = np.ones((400, 2, 2, 7), np.float32)
    drop_noise(batch, 3, 0.25, np.random.default_rng(0))
    dropped = np.all(batch[:, :, :, 3:7] == 0, axis=(1, 2, 3))
    assert 70 < dropped.sum() < 130
    assert np.all(batch[:, :, :, :3] == 1)  # the image itself is untouched
    assert np.all(batch[~dropped] == 1)


def test_radius_averages_the_variance_over_the_window() -> None:
    color = np.zeros((5, 6, 3), np.float32)
    variance = np.zeros_like(color)
    variance[2, 3] = 9.0  # one pixel's estimate; the 3x3 window mean around it is 1
    raw = noise_channels(color, variance, PU)
    smooth = noise_channels(color, variance, PU, radius=1)
    one = float(PU.forward(torch.tensor(1.0)))
    assert raw[2, 3, 0] == pytest.approx(float(PU.forward(torch.tensor(3.0))), rel=1e-5)
    np.testing.assert_allclose(smooth[1:4, 2:5, 0], one, rtol=1e-5)  # every pixel whose window holds it
    assert smooth[0, 0, 0] == 0 and smooth[4, 5, 0] == 0  # outside every window: no noise
    corner = noise_channels(color, np.full_like(color, 4.0), PU, radius=2)
    np.testing.assert_allclose(corner[..., 0], float(PU.forward(torch.tensor(2.0))), rtol=1e-5)  # cut windows
