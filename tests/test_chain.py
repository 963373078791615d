"""Whole-image inference: tiled == untiled, range, aux handling."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from model.checkpoint import save_checkpoint
from model.config import PRESETS, ModelConfig
from denoise.flips import FLIPS, check_flips
from denoise.chain import (BOUND_RADIUS, ChainRun, denoise_image, flip_average, log_average_luminance,
                           neighbourhood_max, noisy_region)
from model.architectures import alignment, build_model
from model.transfer import HDR_MAX, get_transfer


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


def test_denoise_image_runs_in_eval_mode_and_restores_training() -> None:
    model = _model()
    color = (np.random.default_rng(1).random((16, 16, 3)) * 5).astype(np.float32)
    want = denoise_image(model, color, core=16)  # eval mode
    model.train()
    got = denoise_image(model, color, core=16)  # the BN statistics are used, not the batch's
    assert model.training and all(m.training for m in model.modules())
    np.testing.assert_array_equal(got, want)


def _tiny_unet() -> torch.nn.Module:
    from tests.test_model_unet import TINY, trained_like
    return trained_like(TINY)


def _flat_with_output() -> torch.nn.Module:
    """:func:`_model` with a non-zero output conv (at init the flat net returns its input)."""
    model = _model()
    with torch.no_grad():
        torch.nn.init.normal_(model.tail[-1].weight, std=0.05)
    return model


@pytest.mark.parametrize("flips", [2, 4])
@pytest.mark.parametrize("kind", ["flat", "unet"])
def test_flipped_tiles_equal_the_flipped_whole_image(kind: str, flips: int) -> None:
    """Each window is padded to the alignment before it is mirrored, so a u-net's mirrored window
    keeps the whole image's pooling grid (without that padding the tiles differ by ~5 here)."""
    model = _flat_with_output() if kind == "flat" else _tiny_unet()
    color = (np.random.default_rng(flips).random((75, 98, 3)) ** 3 * 5).astype(np.float32)
    whole = denoise_image(model, color, core=512, flips=flips)
    tiled = denoise_image(model, color, core=16, flips=flips)
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=2e-5)
    assert np.abs(whole - denoise_image(model, color, core=512)).max() > 1e-3  # the flips do something


@pytest.mark.parametrize("kind", ["flat", "unet"])
def test_four_flips_make_the_network_mirror_equivariant(kind: str) -> None:
    model = _flat_with_output() if kind == "flat" else _tiny_unet()
    align = alignment(model.config)
    x = torch.rand(1, model.config.image_channels, 2 * align if align > 1 else 19, 3 * align if align > 1 else 23)
    with torch.no_grad():
        y = flip_average(model, x, 4, align)
        for dims in FLIPS[4][1:]:
            torch.testing.assert_close(flip_average(model, x.flip(dims), 4, align), y.flip(dims),
                                       rtol=1e-5, atol=1e-5)
        assert torch.equal(flip_average(model, x, 1, align), model(x))


def test_flips_other_than_1_2_4_are_refused() -> None:
    assert [check_flips(n) for n in (1, 2, 4)] == [1, 2, 4]
    with pytest.raises(ValueError, match="flips must be one of 1, 2, 4"):
        check_flips(3)
    with pytest.raises(ValueError, match="flips"):
        denoise_image(_model(), np.ones((8, 8, 3), np.float32), flips=0)
    aux = np.zeros((8, 8, 6), np.float32)
    with pytest.raises(ValueError, match="without albedo/normal"):
        denoise_image(_model(aux_inputs=True), np.ones((8, 8, 3), np.float32), aux, flips=2)


def _brute_max(image: np.ndarray, r: int) -> np.ndarray:
    h, w = image.shape[:2]
    return np.array([[image[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1].max() for x in range(w)]
                     for y in range(h)], dtype=image.dtype)


@pytest.mark.parametrize("radius", [0, 1, 3, 8, 40])
def test_neighbourhood_max_is_the_clipped_window_max(radius: int) -> None:
    image = torch.from_numpy(np.random.default_rng(radius).random((23, 17, 3)).astype(np.float32))
    np.testing.assert_array_equal(neighbourhood_max(image, radius).numpy(), _brute_max(image.numpy(), radius))


def test_an_exploding_output_is_bounded_by_the_input_around_it() -> None:
    """A network that returns a blob of huge values (as an under-trained multi-scale net did
    around a firefly) cannot make a pixel brighter than the brightest input within BOUND_RADIUS."""
    model = _model(output="direct")
    with torch.no_grad():
        bn, _, conv = model.tail  # BN-ReLU-conv3x3: a constant 1 into all-ones weights
        bn.weight.zero_()
        bn.bias.fill_(1.0)
        conv.weight.fill_(1.0)  # transfer-space output >= 4 * channels: far beyond radiance HDR_MAX
    color = np.full((40, 48, 3), 0.1, np.float32)
    color[20, 30] = [3.0, 2.0, 1.0]  # one firefly
    out = denoise_image(model, color, core=16)
    pu = get_transfer(model.config.transfer)
    bound = pu.inverse(torch.from_numpy(_brute_max(pu.forward(torch.from_numpy(color)).amax(2).numpy(),
                                                   BOUND_RADIUS))).numpy()
    np.testing.assert_allclose(out, np.repeat(bound[..., None], 3, axis=2), rtol=1e-5)
    assert out.max() == pytest.approx(3.0, rel=1e-5) and out[0, 0, 0] == pytest.approx(0.1, rel=1e-5)


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


def test_aux_as_two_buffers_is_aux_as_one() -> None:
    model = _model(aux_inputs=True)
    rng = np.random.default_rng(3)
    color = rng.random((20, 23, 3), dtype=np.float32)
    albedo, normals = rng.random((20, 23, 3), dtype=np.float32), rng.random((20, 23, 3), dtype=np.float32) - 0.5
    albedo[2, 2, 0] = np.nan
    whole = denoise_image(model, color, np.concatenate([albedo, normals], axis=2), core=8)
    assert np.array_equal(denoise_image(model, color, (albedo, normals), core=8), whole)
    with pytest.raises(ValueError, match="aux must be HxWx6"):
        denoise_image(model, color, (albedo, normals[:, :5]))


def test_whole_image_passes_do_not_depend_on_their_budget() -> None:
    """Exposure, the skip test and copying the skipped parts, in blocks of one row (one cell)
    or all at once: the same image, the same region."""
    model = _model(noise_input=True)
    rng = np.random.default_rng(4)
    color = (rng.random((150, 140, 3), dtype=np.float32) * 1e-5)  # dark: scaled by the exposure
    variance = np.zeros_like(color)
    variance[70:90, 10:30] = 1e-9  # one noisy corner of the image
    color[5, 5] = [np.nan, np.inf, -1.0]
    args = dict(core=32, variance=variance, skip_below=1e-3)
    small, large = (denoise_image(model, color, max_bytes=b, **args) for b in (1.0, 1e9))
    assert np.array_equal(small, large) and np.array_equal(small[:64], np.nan_to_num(color[:64], posinf=HDR_MAX).clip(0))
    transfer, align = get_transfer("log"), alignment(model.config)
    assert noisy_region(color, variance, transfer, 2.0**13, 1e-3, align, 1.0) == \
        noisy_region(color, variance, transfer, 2.0**13, 1e-3, align, 1e9) == (64, 128, 0, 64)


_TILE_CHILD = """
import gc, json, sys
import numpy as np
from denoise.chain import denoise_image
from denoise.denoiser import Denoiser

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024

den = Denoiser(sys.argv[1], max_memory_mb=float(sys.argv[2]), optimize=sys.argv[3] == "folded")
side = den.core_size() + 2 * den.margin  # the largest window the planner makes
rng = np.random.default_rng(0)
image = rng.random((side, side, 3), dtype=np.float32)
variance = rng.random(image.shape, dtype=np.float32) * 0.01
gc.collect()
open("/proc/self/clear_refs", "w").write("5")
start = status("VmRSS")
out = denoise_image(den.net, image, core=side, variance=variance)
print(json.dumps({"scratch_mb": (status("VmHWM") - start - out.nbytes) / 2**20, "side": side}))
"""


@pytest.mark.slow
@pytest.mark.parametrize("preset,setting,budget", [("flat-s", "folded", 128), ("flat-s", "module", 128),
                                                   ("flat-m", "folded", 256), ("unet-s", "folded", 256)])
def test_a_tile_planned_under_a_budget_stays_under_it(tmp_path: Path, preset: str, setting: str,
                                                      budget: float) -> None:
    """One window as large as the Denoiser plans under ``budget`` MB, denoised in a fresh process
    (random weights: memory does not depend on them): its resident scratch beyond the output
    within 1.1x the budget, and above half of it (the estimate is not idly conservative)."""
    path = tmp_path / f"{preset}.ckpt"
    save_checkpoint(path, build_model(PRESETS[preset]), step=0)
    proc = subprocess.run([sys.executable, "-c", _TILE_CHILD, str(path), str(budget), setting], capture_output=True,
                          text=True, check=True, cwd=Path(__file__).resolve().parents[1])
    m = json.loads(proc.stdout.strip().splitlines()[-1])
    assert 0.5 * budget <= m["scratch_mb"] <= 1.1 * budget, m


@pytest.mark.parametrize("rows, workers", [(1, 2), (7, 3), (256, 2), (5, 1)])
def test_log_average_luminance_on_threads_is_the_serial_one(rows: int, workers: int) -> None:
    """Blocks summed in their order whatever thread computed them: the same float."""
    img = np.random.default_rng(4).gamma(2.0, 0.3, (41, 23, 3)).astype(np.float32)
    img[3, 4] = np.nan
    img[9, 1, 2] = np.inf
    assert log_average_luminance(img, rows, workers) == log_average_luminance(img, rows, 1)


@pytest.mark.parametrize("skip", [None, 1e-3])
def test_a_rectangle_of_the_chain_is_that_part_of_the_whole_image(skip: float | None) -> None:
    """ChainRun.rect on any rectangle, cut into any cores: the whole image's output there (margins
    from the whole image, the skip test's region and the sanitised render outside it)."""
    model = build_model(ModelConfig(arch="dense_unet", layers=1, growth=4, init_features=8, levels=2)).eval()
    rng = np.random.default_rng(5)
    color = rng.gamma(2.0, 0.3, (70, 90, 3)).astype(np.float32)
    variance = np.full_like(color, 1e-2)
    variance[:, :64] = 0.0  # a clean 64-px cell column the skip test leaves out
    whole = denoise_image(model, color, core=4096, variance=variance, skip_below=skip)
    run = ChainRun(model, color, variance=variance, skip_below=skip)
    assert run.region == (None if skip is None else (0, 70, 64, 90))
    with run:
        for (y0, y1, x0, x1), core in [((0, 70, 0, 90), (16, 16)), ((13, 45, 5, 77), (8, 24)), ((60, 70, 0, 39), 4)]:
            np.testing.assert_allclose(run.rect(y0, y1, x0, x1, core), whole[y0:y1, x0:x1], rtol=1e-4, atol=1e-5)
    assert run.windows > 0
