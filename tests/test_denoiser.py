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
from denoise.chain import image_exposure
from denoise.denoiser import Denoiser, count_invalid
from denoise.energy import correct_in_place
from denoise.noise_guard import DEFAULT_STRENGTH, blend_weight, clean_render, guard, strength_for
from rendering.render import RenderResult
from tests.nets import randomize_batchnorm

TINY = ModelConfig(layers=3, growth=4, init_features=8)


def write_tiny_checkpoint(path: Path, config: ModelConfig = TINY, seed: int = 0, max_spp: int = 0,
                          min_spp: int = 0) -> Path:
    """A random (untrained) model with non-trivial BatchNorm statistics, saved like `train` does
    (``min_spp`` / ``max_spp``: recorded as trained on renders of at least / most that many spp)."""
    torch.manual_seed(seed)
    model = build_model(config)
    randomize_batchnorm(model, 0.1, (0.5, 1.5))
    limits = {k: v for k, v in (("min_spp", min_spp), ("max_spp", max_spp)) if v}
    save_checkpoint(path, model, step=0, train_config=limits or None)
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


def _with_noise(h: int, w: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """An image with NaN, Inf and negative values, and a variance with an infinite value."""
    img = _image(h, w, seed)
    img[3, 4] = [np.nan, np.inf, -1.0]
    variance = (np.random.default_rng(seed + 1).random((h, w, 3)) * 0.2).astype(np.float32)
    variance[h // 2, w // 3, 2] = np.inf
    return img, variance


def test_budget_leaves_the_whole_chain_unchanged(ckpt: Path) -> None:
    """Noise guard on: a 0.05 MB budget (many network tiles, guard tiles, row blocks) gives the
    result of an untiled run, within the tolerance of the network's tiling (rtol 1e-4)."""
    img, variance = _with_noise(61, 47)
    a = Denoiser(ckpt, max_memory_mb=1024).denoise_array(img, variance=variance, strength=3.0)
    b = Denoiser(ckpt, max_memory_mb=0.05).denoise_array(img, variance=variance, strength=3.0)
    assert a.tiles == 1 and b.tiles > 4
    np.testing.assert_allclose(b.image, a.image, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(b.guard_map, a.guard_map, rtol=1e-4, atol=1e-4)
    assert b.guard_weight == pytest.approx(a.guard_weight, rel=1e-4)
    assert (b.nonfinite, b.negative) == (a.nonfinite, a.negative) == (2, 1)


@pytest.mark.parametrize("max_memory_mb", [0.05, 1024])
def test_guard_per_tile_is_the_whole_image_guard(ckpt: Path, max_memory_mb: float) -> None:
    """The guard run tile by tile on the network's output equals the whole-image guard of that
    output bit for bit (image, weight map, mean weight; the energy correction after it off)."""
    img, variance = _with_noise(61, 47, seed=5)
    res = Denoiser(ckpt, max_memory_mb=max_memory_mb, energy=None).denoise_array(
        img, variance=variance, strength=3.0, keep_network=True)
    expected, mean = guard(clean_render(img), res.network, variance, strength=3.0)
    assert np.array_equal(res.image, expected) and not np.array_equal(res.image, res.network)
    assert res.guard_weight == mean
    assert np.array_equal(res.guard_map, blend_weight(clean_render(img), res.network, variance, strength=3.0)[..., 0])


@pytest.mark.parametrize("with_variance", [True, False])
def test_energy_correction_follows_the_guard(ckpt: Path, with_variance: bool) -> None:
    """With or without a variance (guard or none), the output is the uncorrected one matched by
    denoise.energy at the exposure the network used, bit for bit; energy=None leaves it alone."""
    img, variance = _with_noise(61, 47, seed=6)
    img *= np.linspace(0.5, 1.5, 47, dtype=np.float32)[None, :, None]
    variance = variance if with_variance else None
    plain = Denoiser(ckpt, energy=None).denoise_array(img, variance=variance, strength=3.0)
    corrected = Denoiser(ckpt).denoise_array(img, variance=variance, strength=3.0)
    expected = plain.image.copy()
    factor = correct_in_place(img, expected, 2**30, image_exposure(img))
    assert np.array_equal(corrected.image, expected)
    assert corrected.energy_factor == factor and plain.energy_factor is None


def test_bare_network_output_is_not_energy_corrected(tmp_path: Path) -> None:
    """Without a variance (no guard) but with the energy correction, ``network`` is the network's
    output as a denoiser without the correction gives it: its own array, not the corrected image
    (a random direct-output network: its local means are far from the render's)."""
    ckpt = write_tiny_checkpoint(tmp_path / "direct.ckpt", ModelConfig(layers=3, growth=4, init_features=8,
                                                                        output="direct"))
    img = _image(61, 47, seed=7)
    bare = Denoiser(ckpt, energy=None).denoise_array(img).image
    res = Denoiser(ckpt).denoise_array(img, keep_network=True)
    assert res.energy_factor is not None and not np.array_equal(res.image, bare)  # the correction acted
    assert not np.shares_memory(res.network, res.image)
    assert np.array_equal(res.network, bare)


@pytest.mark.parametrize("spp", [1, 4, 64])
def test_an_array_with_its_variance_and_spp_is_denoised_as_its_render(tmp_path: Path, spp: int) -> None:
    """``denoise_array(rgb, variance=v, spp=N)`` gives ``denoise_render``'s image, bit for bit: the
    guard's strength follows the spp (:func:`strength_for`) unless one is given; without an spp it is 1
    (a random direct-output network, so that its change is large and the strength shows)."""
    img = _image(37, 29, seed=8)
    den = Denoiser(write_tiny_checkpoint(tmp_path / "direct.ckpt", ModelConfig(layers=3, growth=4, init_features=8,
                                                                                output="direct")))
    change = den.denoise_array(img, keep_network=True).network - img
    variance = (0.01 * change**2).astype(np.float32)  # weight ~0.01 at strength 1: the strength shows
    rendered = den.denoise_render(RenderResult(img, spp=spp, variance=variance))
    array = den.denoise_array(img, variance=variance, spp=spp)
    assert np.array_equal(array.image, rendered.image) and array.guard_weight == rendered.guard_weight
    weaker = den.denoise_array(img, variance=variance, spp=spp, strength=DEFAULT_STRENGTH)
    assert not np.array_equal(weaker.image, array.image) and weaker.guard_weight < array.guard_weight
    given = den.denoise_array(img, variance=variance, strength=strength_for(spp))
    assert np.array_equal(given.image, array.image)  # this one network runs at every spp
    unknown = den.denoise_array(img, variance=variance)
    assert np.array_equal(unknown.image, weaker.image)


def test_count_invalid_in_row_blocks() -> None:
    img = _image(9, 7)
    img[0, 0, 0], img[4, 6, 2], img[8, 0, 1], img[5, 5, 0] = np.nan, -np.inf, -3.0, np.inf
    assert count_invalid(img) == (3, 1)
    assert all(count_invalid(img, rows) == (3, 1) for rows in (1, 2, 4, 9, 100))
    assert all(count_invalid(img, rows, workers) == (3, 1) for rows in (1, 4, 100) for workers in (2, 3))


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
    albedo = torch.full(img.shape, 0.5, requires_grad=True)  # tensors that need a gradient, as a caller's may
    called = den(torch.from_numpy(img).requires_grad_(), albedo=albedo, normals=torch.zeros(img.shape))
    np.testing.assert_allclose(called.numpy(), out, rtol=1e-6)


def test_a_camera_normals_model_turns_world_normals_with_the_render_s_camera(tmp_path: Path) -> None:
    """A model trained on camera-space normals is given world normals and the camera's rotation
    (a render carries it): the same output as given the rotated normals (exactly; the network's
    is the chain's), unlike the one given the world normals as they are; without the rotation,
    one error."""
    from denoise.chain import denoise_image
    from rendering.camera import rotate_normals
    from rendering.render import RenderResult
    from tests.test_model_unet import trained_like

    config = ModelConfig(arch="dense_unet", layers=1, growth=4, init_features=8, levels=2, transfer="pu", kernel=3,
                         aux_inputs=True, aux_mode="levels", aux_normals="camera")
    model = trained_like(config)
    save_checkpoint(tmp_path / "camera.ckpt", model, step=0)
    den = Denoiser(tmp_path / "camera.ckpt", optimize=False)
    rng = np.random.default_rng(4)
    img, albedo = _image(24, 20), rng.random((24, 20, 3), dtype=np.float32)
    normals = rng.normal(size=(24, 20, 3)).astype(np.float32)
    rotation = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    with pytest.raises(DenoiserError, match="takes normals in the camera's frame: give the camera's rotation"):
        den.denoise_array(img, albedo, normals)
    got = den.denoise_render(RenderResult(rgb=img, aovs={"albedo": albedo, "sh_normal": normals}, spp=4,
                                          to_camera=rotation)).image
    want = den.denoise_array(img, albedo, rotate_normals(normals, rotation), spp=4, to_camera=np.eye(3)).image
    np.testing.assert_array_equal(got, want)
    assert not np.allclose(got, den.denoise_array(img, albedo, normals, spp=4, to_camera=np.eye(3)).image, atol=1e-4)
    network = den.denoise_array(img, albedo, normals, spp=4, to_camera=rotation, keep_network=True).network
    np.testing.assert_array_equal(network, denoise_image(model, img, (albedo, rotate_normals(normals, rotation))))


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
    for spp in (0, -4, 2.5, True):
        with pytest.raises(DenoiserError, match="spp must be a positive integer or None"):
            Denoiser(ckpt).denoise_array(np.zeros((4, 4, 3), np.float32), spp=spp)
    with pytest.raises(DenoiserError, match="spp must be a positive integer"):
        Denoiser("auto").denoise_array(np.zeros((4, 4, 3), np.float32), spp=0)
    with pytest.raises(DenoiserError, match="@bf16: precision must be one of auto, float32, bfloat16"):
        Denoiser(f"{ckpt}@bf16")


def test_the_denoiser_names_what_it_runs_so_that_the_name_loads_it_again(ckpt: Path) -> None:
    """A registry name is printed as it is; a checkpoint file by its path; either loads the same again."""
    for model in ("high", "fast", str(ckpt)):
        den = Denoiser(model)
        assert den.name == model and Denoiser(den.name).sha256 == den.sha256
    assert Denoiser().name == "high"  # the registry's default
    listed = Denoiser(["fast"])  # a list names checkpoints: the one `fast` named before the registry
    assert not listed.registered and listed.label == "flat-s-allspp" and Denoiser("fast").registered
    with pytest.raises(DenoiserError, match="registry name"):
        Denoiser("fsat")


def test_an_unknown_spp_and_filtered_noise_are_named(ckpt: Path) -> None:
    """Without an spp the call says what ran instead (a Python warning from ``__call__``); noise
    spread over neighbours (a [1, 2, 1] blur of white noise) is named unless the filter is known."""
    rng = np.random.default_rng(4)
    white = np.exp(rng.normal(-1.0, 0.3, (64, 64, 3))).astype(np.float32)
    den = Denoiser("fast")
    with pytest.warns(UserWarning, match="spp unknown: ran"):
        den(white)
    assert den.denoise_array(white, spp=4).notes == ()
    k = np.array([0.25, 0.5, 0.25], np.float32)
    blurred = sum(w * white[:, i:i + 62] for i, w in enumerate(k))
    blurred = np.ascontiguousarray(sum(w * blurred[i:i + 62] for i, w in enumerate(k)))
    notes = den.denoise_array(blurred, spp=4).notes
    assert len(notes) == 1 and "spread over neighbouring pixels" in notes[0]
    assert den.denoise_array(blurred, spp=4, pixel_filter="box").notes == ()
    assert "the render's pixel filter is gaussian" in den.denoise_array(white, spp=4, pixel_filter="gaussian").notes[0]
    assert Denoiser(ckpt).denoise_array(white).notes == ()  # one network trained on every spp: nothing to say


def test_device_is_chosen_once_and_a_missing_gpu_is_an_error(ckpt: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--device: the CPU runs the folded networks as before; cuda where there is none is refused
    before any image is read."""
    import model.device

    monkeypatch.setattr(model.device, "cuda_available", lambda: False)
    img = np.random.default_rng(0).random((12, 12, 3), dtype=np.float32)
    on_cpu = Denoiser(ckpt, device="cpu")
    assert on_cpu.device.type == "cpu" and on_cpu.net is not on_cpu.model  # the folded copy
    np.testing.assert_array_equal(on_cpu.denoise_array(img).image, Denoiser(ckpt).denoise_array(img).image)
    assert Denoiser(ckpt, device="auto").device.type == "cpu"
    with pytest.raises(DenoiserError, match="device 'cuda': torch sees no CUDA device"):
        Denoiser(ckpt, device="cuda")
