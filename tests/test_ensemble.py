"""Ensembles: outputs weighted by their estimated error, ``--model A+B`` through the Denoiser and CLI."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from imaging.errors import DenoiserError
from imaging.exr import write_exr
from pipeline.cli import denoise_main
from pipeline.denoise_file import denoise_summary
from denoise.precision import native_bfloat16
from denoise.denoiser import Denoiser, select
from denoise.ensemble import (COMBINE_BYTES_PER_PIXEL, combine, combine_in_place, combine_weights,
                              denoise_combined, weight_bytes_per_pixel, weighted_sum)
from denoise.tiling import plan_tiles
from model.registry import range_suffix, split_range
from denoise.noise_guard import clean_render
from tests.test_denoiser import write_tiny_checkpoint
from tests.test_model_unet import TINY as TINY_UNET
from tests.test_noise_guard import _traced_peak

SIGMA = 0.05


def _case(h: int = 48, w: int = 64, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A smooth truth, a render of it with Gaussian noise of known variance, that variance."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    truth = np.stack([0.5 + 0.3 * np.sin(xx / 9), 0.4 + yy / (2 * h), 0.6 + 0 * xx], axis=2).astype(np.float32)
    noisy = (truth + rng.normal(0, SIGMA, truth.shape)).astype(np.float32)
    return truth, noisy, np.full(truth.shape, SIGMA**2, np.float32)


def test_the_output_with_the_smaller_error_wins_where_it_is_better() -> None:
    """A = the truth; B = the truth plus 0.2 on the left half: on the left the combination takes
    A (its estimated error ~0 against B's 3 * 0.04), on the right both are the truth and so is
    their combination."""
    truth, noisy, var = _case()
    biased = truth.copy()
    biased[:, :32] += 0.2
    w = combine_weights(noisy, [truth, biased], var)
    assert w.shape == (48, 64, 2) and np.allclose(w.sum(axis=2), 1, atol=1e-6) and (w >= 0).all()
    assert w[:, :28, 0].min() > 0.9  # left of the window's reach into the right half
    out = combine(noisy, [truth, biased], var)
    left_err = np.abs(out[:, :28] - truth[:, :28]).mean()
    assert left_err < 0.1 * 0.2
    np.testing.assert_allclose(out[:, 36:], truth[:, 36:], atol=1e-6)


def test_equal_estimated_errors_give_the_mean() -> None:
    """Outputs symmetric about the render have the same window errors: weight 1/2 each."""
    _, noisy, var = _case(seed=1)
    up, down = noisy + 0.1, noisy - 0.1
    np.testing.assert_allclose(combine_weights(noisy, [up, down], var), 0.5, atol=1e-6)
    np.testing.assert_allclose(combine(noisy, [up, down], var), noisy, atol=1e-6)


def test_no_variance_averages_and_one_output_is_itself() -> None:
    truth, noisy, var = _case(seed=2)
    a, b = truth + 0.3, truth - 0.1
    np.testing.assert_allclose(combine(noisy, [a, b], None), truth + 0.1, atol=1e-6)
    np.testing.assert_array_equal(combine(noisy, [a], var), a)


def test_converged_and_unbounded_windows() -> None:
    """V = 0 everywhere: an output equal to the render keeps all the weight against one that
    changed it; a non-finite variance gives equal weights across its window; never NaN."""
    _, noisy, _ = _case(seed=3)
    zero = np.zeros_like(noisy)
    w = combine_weights(noisy, [noisy.copy(), noisy + 0.01], zero)
    np.testing.assert_array_equal(w[:, :, 0], 1.0)
    np.testing.assert_array_equal(combine_weights(noisy, [noisy.copy(), noisy.copy()], zero), 0.5)
    var = np.full_like(noisy, SIGMA**2)
    var[20, 30, 1] = np.inf
    var[5, 5, 0] = np.nan
    w = combine_weights(noisy, [noisy + 0.2, noisy + 0.01], var, radius=3)
    assert np.isfinite(w).all()
    np.testing.assert_array_equal(w[17:24, 27:34], 0.5)
    assert w[40, 60, 1] > 0.9


@pytest.mark.parametrize("max_mb", [0.01, 0.2, 64])
def test_in_place_within_a_memory_bound_is_the_whole_image_result_bit_for_bit(max_mb: float) -> None:
    truth, noisy, var = _case(61, 47, seed=4)
    rng = np.random.default_rng(5)
    outs = [(truth + rng.normal(0, s, truth.shape)).astype(np.float32) for s in (0.01, 0.03, 0.02)]
    whole = combine(noisy, outs, var)
    first = outs[0].copy()
    combine_in_place(noisy, [first, *outs[1:]], var, max_mb * 2**20)
    np.testing.assert_array_equal(first, whole)
    first = outs[0].copy()
    combine_in_place(noisy, [first, *outs[1:]], None, max_mb * 2**20)
    np.testing.assert_array_equal(first, combine(noisy, outs, None))


def test_bad_arguments() -> None:
    _, noisy, var = _case(seed=6)
    with pytest.raises(ValueError, match="no outputs"):
        combine_weights(noisy, [], var)
    with pytest.raises(ValueError, match="shapes differ"):
        combine_weights(noisy, [noisy[:4]], var)
    with pytest.raises(ValueError, match="lam"):
        combine_weights(noisy, [noisy], var, lam=-1)
    with pytest.raises(DenoiserError, match="no empty member"):
        select("flat-s-allspp+")
    assert [m.given for m in select("flat-s-allspp + unet-l-allspp").members] == ["flat-s-allspp", "unet-l-allspp"]


@pytest.fixture(scope="module")
def two_models(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("ckpts")
    return write_tiny_checkpoint(folder / "flat.ckpt"), write_tiny_checkpoint(folder / "unet.ckpt", TINY_UNET, seed=1)


def test_ensemble_denoiser_combines_its_members_outputs(two_models: tuple[Path, Path]) -> None:
    """``A+B``: each member's network output, combined as :func:`combine` does, then guarded;
    within a small memory bound (many tiles) the same to float32 rounding of the tiling."""
    flat, unet = two_models
    truth, noisy, var = _case(37, 29, seed=7)
    members = [Denoiser(p).denoise_array(noisy, variance=var, keep_network=True).network for p in two_models]
    expected = combine(noisy, members, var)
    for max_mb in (1024, 2):
        ens = Denoiser(f"{flat}+{unet}", max_memory_mb=max_mb)
        got = ens.denoise_array(noisy, variance=var, keep_network=True)
        np.testing.assert_allclose(got.network, expected, rtol=1e-4, atol=1e-5)
        assert got.image.shape == noisy.shape and np.isfinite(got.image).all()
    assert ens.name == f"{flat}+{unet}" and ens.label == "flat+unet" and len(ens.members) == 2
    limited = Denoiser(f"{flat}:9-16+{flat}:17-+{unet}")
    assert limited.name == f"{flat}:9-16+{flat}:17-+{unet}" and limited.label == "flat:9-16+flat:17-+unet"
    assert Denoiser(limited.name).label == limited.label  # the name it prints loads it again
    assert ens.margin == max(m.margin for m in ens.members) and not ens.needs_aovs
    plain = ens.denoise_array(noisy).image  # no variance: the mean, no guard
    np.testing.assert_allclose(plain, combine(noisy, [Denoiser(p).denoise_array(noisy).image for p in two_models],
                                              None), rtol=1e-4, atol=1e-5)
    for shape in [(1, 1), (3, 17)]:
        assert ens.denoise_array(np.ones((*shape, 3), np.float32)).image.shape == (*shape, 3)


def test_a_member_trained_for_low_spp_runs_only_there(tmp_path: Path, two_models: tuple[Path, Path]) -> None:
    """A member whose checkpoint was trained on renders of <= 8 spp (``train --max-spp 8``) joins
    the ensemble at 1-8 spp; above, or where the spp is unknown, the others run alone, exactly as
    without it; in an ensemble of such members only, the first runs alone there (the spec's fallback)."""
    flat, _ = two_models
    low = write_tiny_checkpoint(tmp_path / "low.ckpt", TINY_UNET, seed=3, max_spp=8)
    truth, noisy, var = _case(21, 19, seed=5)
    ens, alone = Denoiser([flat, low]), Denoiser(flat)
    assert [m.max_spp for m in ens.members] == [0, 8] and ens.ensemble_record()["members"][1]["max_spp"] == 8
    for spp in (1, 8):
        assert ens.denoise_array(noisy, variance=var, spp=spp).models == ("flat", "low")
    np.testing.assert_allclose(ens.denoise_array(noisy, variance=var, spp=4, keep_network=True).network,
                               combine(noisy, [alone.denoise_array(noisy, variance=var, keep_network=True).network,
                                               Denoiser(low).denoise_array(noisy, variance=var,
                                                                           keep_network=True).network], var),
                               rtol=1e-4, atol=1e-5)
    for spp in (16, None):
        high = ens.denoise_array(noisy, variance=var, strength=2.0, spp=spp)
        assert high.models == ("flat",)
        np.testing.assert_array_equal(high.image, alone.denoise_array(noisy, variance=var, strength=2.0).image)
    assert Denoiser([low, flat]).denoise_array(noisy, spp=64).models == ("flat",)
    assert Denoiser([low, low]).denoise_array(noisy, spp=64).models == ("low",)
    assert Denoiser([low, low]).denoise_array(noisy).models == ("low",)


def test_members_trained_for_an_spp_range_run_only_within_it(tmp_path: Path, two_models: tuple[Path, Path]) -> None:
    """Specialists for low (<= 8) and high (>= 16) spp beside a model trained on every spp: exactly
    two run at any known spp, the all-spp model alone where the spp is unknown."""
    flat, _ = two_models
    low = write_tiny_checkpoint(tmp_path / "low.ckpt", TINY_UNET, seed=3, max_spp=8)
    high = write_tiny_checkpoint(tmp_path / "high.ckpt", TINY_UNET, seed=4, min_spp=16)
    _, noisy, var = _case(17, 13, seed=6)
    ens = Denoiser([flat, low, high])
    assert [(m.min_spp, m.max_spp) for m in ens.members] == [(0, 0), (0, 8), (16, 0)]
    assert [(m["min_spp"], m["max_spp"]) for m in ens.ensemble_record()["members"]] == [(0, 0), (0, 8), (16, 0)]
    for spp, ran in ((1, ("flat", "low")), (8, ("flat", "low")), (12, ("flat",)), (16, ("flat", "high")),
                     (4096, ("flat", "high")), (None, ("flat",))):
        assert ens.denoise_array(noisy, variance=var, spp=spp).models == ran, spp


def test_an_ensemble_spec_limits_a_member_to_an_spp_range(tmp_path: Path, two_models: tuple[Path, Path]) -> None:
    """``MODEL:LO-HI`` (one end may be left out) runs that member only on LO..HI spp, within the range
    its checkpoint was trained on; where no member is meant for the spp the first runs alone; the
    default is built so; a file whose name looks like a range is that file; a range with no end or
    LO > HI is a clear error."""
    flat, unet = two_models
    low = write_tiny_checkpoint(tmp_path / "low.ckpt", TINY_UNET, seed=3, max_spp=8)
    ens = Denoiser([flat, f"{unet}:17-", f"{low}:4-"])
    assert [(m.min_spp, m.max_spp) for m in ens.members] == [(0, 0), (17, 0), (4, 8)]
    assert ens.label == "flat+unet:17-+low:4-"
    assert [m.spec for m in ens.members] == [str(flat), f"{unet}:17-", f"{low}:4-"]  # loads them again as they are
    assert [split_range(f"m{range_suffix(lo, hi)}") for lo, hi in ((0, 0), (17, 0), (0, 16), (4, 8))] == [
        ("m", 0, 0), ("m", 17, 0), ("m", 0, 16), ("m", 4, 8)]
    _, noisy, var = _case(15, 18, seed=7)
    for spp, ran in ((2, ("flat",)), (4, ("flat", "low")), (16, ("flat",)), (17, ("flat", "unet")), (None, ("flat",))):
        assert ens.denoise_array(noisy, variance=var, spp=spp).models == ran, spp
    assert Denoiser(f"{flat}+{unet}:-16").members[1].max_spp == 16
    # a spec written before the registry names the same files by their earlier names
    before = "fast:17-+fast:9-16+fast-lowspp:-8+u-balanced-k5-lowspp+u-high:17-"
    assert [m.spec for m in select(before).members] == before.split("+")
    assert [(m.path.stem, m.lo, m.hi) for m in select(before).members] == [
        ("flat-s-allspp", 17, 0), ("flat-s-allspp", 9, 16), ("flat-s-lowspp", 0, 8), ("unet-m-k5-lowspp", 0, 0),
        ("unet-l-allspp", 17, 0)]
    # where no member is meant for the spp (the spp unknown and every member limited), the first runs alone
    fallback = Denoiser([f"{flat}:9-", f"{low}:-4", f"{unet}:17-"])
    for spp, ran in ((2, ("low",)), (8, ("flat",)), (9, ("flat",)), (17, ("flat", "unet")), (None, ("flat",))):
        assert fallback.denoise_array(noisy, variance=var, spp=spp).models == ran, spp
    odd = write_tiny_checkpoint(tmp_path / "odd:1-2.ckpt")
    assert Denoiser([flat, odd]).members[1].limit == (0, 0)
    for bad in (f"{unet}:-", f"{unet}:9-4"):
        with pytest.raises(DenoiserError, match="LO-HI"):
            Denoiser(f"{flat}+{bad}")
    with pytest.raises(DenoiserError, match="would never run"):
        Denoiser([flat, f"{low}:9-"])  # trained on <= 8 spp


def test_ensemble_specs(tmp_path: Path, two_models: tuple[Path, Path]) -> None:
    """A file whose name holds '+' is one model; a list names its members (a '+' in a path kept);
    an empty or missing member is a clear error."""
    plus = write_tiny_checkpoint(tmp_path / "a+b.ckpt")
    assert [m.path for m in select(plus).members] == [plus] and select(None).name == "high"
    assert len(Denoiser(plus).members) == 1
    assert [m.path for m in select([plus, two_models[0]]).members] == [plus, two_models[0]]
    assert [m.path for m in Denoiser([plus, two_models[1]]).members] == [plus, two_models[1]]
    for empty in ([], [plus, ""]):
        with pytest.raises(DenoiserError, match="no empty member"):
            Denoiser(empty)
    with pytest.raises(DenoiserError, match="no empty member"):
        Denoiser(f"{two_models[0]}+")
    with pytest.raises(DenoiserError, match="nope"):
        Denoiser(f"{two_models[0]}+{tmp_path / 'nope.ckpt'}")


def test_denoise_cli_with_an_ensemble_and_halves(tmp_path: Path, two_models: tuple[Path, Path],
                                                 capsys: pytest.CaptureFixture) -> None:
    truth, _, _ = _case(16, 24, seed=8)
    rng = np.random.default_rng(9)
    for name in ("a", "b"):
        write_exr(tmp_path / f"{name}.exr", (truth + rng.normal(0, SIGMA, truth.shape)).astype(np.float32),
                  metadata={"spp": 8})
    spec = f"{two_models[0]}+{two_models[1]}"
    assert denoise_main(["--halves", str(tmp_path / "a.exr"), str(tmp_path / "b.exr"), str(tmp_path / "o.exr"),
                         "--model", spec, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert (tmp_path / "o.exr").exists() and printed["model"] == spec
    assert printed["models_run"] == ["flat", "unet"] and printed["noise_guard"]["spp"] == 16
    low = write_tiny_checkpoint(tmp_path / "low.ckpt", TINY_UNET, seed=3, max_spp=8)  # the halves make 16 spp
    assert denoise_main(["--halves", str(tmp_path / "a.exr"), str(tmp_path / "b.exr"), str(tmp_path / "o3.exr"),
                         "--model", f"{two_models[0]}+{low}", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["models_run"] == ["flat"]
    assert denoise_main([str(tmp_path / "a.exr"), str(tmp_path / "o2.exr"), "--model", spec + "+"]) == 1
    assert "no empty member" in capsys.readouterr().err


@pytest.mark.parametrize("shape", [(20, 20), (64, 64), (300, 300), (1, 500), (500, 3)])
@pytest.mark.parametrize("k", [2, 3])
def test_scratch_per_pixel_stays_under_its_stated_bounds(shape: tuple[int, int], k: int) -> None:
    """What combine_in_place plans its tiles and row blocks with (+ 16 KiB of Python objects)."""
    rng = np.random.default_rng(10)
    noisy, var = rng.random((*shape, 3), dtype=np.float32), rng.random((*shape, 3), dtype=np.float32) * 0.01
    outs = [rng.random((*shape, 3), dtype=np.float32) for _ in range(k)]
    pixels = shape[0] * shape[1]
    assert _traced_peak(lambda: combine_weights(clean_render(noisy), outs, var)) <= \
        weight_bytes_per_pixel(k) * pixels + 16384
    w = combine_weights(noisy, outs, var)
    assert w.dtype == np.float32
    # a row block's result is scratch too (it is then copied into the first output): + 12 B/px
    for block in (lambda: weighted_sum(outs, w), lambda: combine(noisy, outs, None)):
        assert _traced_peak(block) + 12 * pixels <= COMBINE_BYTES_PER_PIXEL * pixels + 16384


def test_ensemble_at_the_extremes_stays_finite(two_models: tuple[Path, Path]) -> None:
    """NaN / inf / negative radiance, non-finite variance, all-zero and float16-max renders: a
    finite, non-negative output; an all-zero render with zero variance stays zero."""
    ens = Denoiser(f"{two_models[0]}+{two_models[1]}")
    rng = np.random.default_rng(11)
    x = rng.random((24, 40, 3)).astype(np.float32)
    v = x * np.float32(0.01)
    bad = x.copy()
    bad[3, 4], bad[10, 10, 1], bad[20, 20] = np.nan, np.inf, -5
    bad_var = v.copy()
    bad_var[5, 5], bad_var[6, 6, 2] = np.inf, np.nan
    for img, var in [(bad, v), (x, bad_var), (x * 6e4, v * 3.6e9), (x * 1e-8, v * 1e-16), (x[:1, :1], v[:1, :1])]:
        out = ens.denoise_array(img, variance=var).image
        assert out.shape == img.shape and np.isfinite(out).all() and (out >= 0).all()
    zero = np.zeros_like(x)
    np.testing.assert_array_equal(ens.denoise_array(zero, variance=zero).image, 0.0)


@pytest.mark.parametrize("power, first", [(1.0, 0.8), (2.0, 16 / 17)])
def test_weights_are_powers_of_inverse_errors(power: float, first: float) -> None:
    """A converged render (V = 0) and outputs 0.1 and 0.2 above it in each channel: errors 0.03
    and 0.12, weights 4:1 with power 1, 16:1 with power 2."""
    noisy = np.full((9, 11, 3), 0.5, np.float32)
    zero = np.zeros_like(noisy)
    w = combine_weights(noisy, [noisy + 0.1, noisy + 0.2], zero, power=power)
    np.testing.assert_allclose(w[:, :, 0], first, rtol=1e-5)
    with pytest.raises(ValueError, match="power"):
        combine_weights(noisy, [noisy], zero, power=0)


def test_the_record_names_the_float_format_of_each_network_that_ran(
        tmp_path: Path, two_models: tuple[Path, Path], capsys: pytest.CaptureFixture) -> None:
    """An ensemble's members in two formats: the record and the table give the formats of the
    networks that ran, not of every member."""
    truth, _, _ = _case(16, 24, seed=8)
    write_exr(tmp_path / "a.exr", truth, metadata={"spp": 16})
    low = write_tiny_checkpoint(tmp_path / "low.ckpt", TINY_UNET, seed=3, max_spp=8)
    spec = f"{two_models[0]}@float32+{two_models[1]}@bfloat16+{low}@bfloat16"
    den = Denoiser(spec, precision="auto")
    result = den.denoise_array(truth, spp=16)
    bf16 = "bfloat16" if native_bfloat16() else "float32"  # a member's own bfloat16 holds where native
    assert result.models == ("flat", "unet") and result.precisions == ("float32", bf16)
    if native_bfloat16():
        assert result.precision == "float32+bfloat16" and den.precision == "float32+bfloat16+bfloat16"
        assert denoise_main([str(tmp_path / "a.exr"), str(tmp_path / "o.exr"), "--model", spec]) == 0
        assert "ran flat (float32) + unet (bfloat16)," in capsys.readouterr().out
    den = Denoiser(spec, precision="bfloat16")  # asked for: every member, native or not
    assert den.denoise_array(truth, spp=16).precision == "bfloat16"
    assert denoise_main([str(tmp_path / "a.exr"), str(tmp_path / "o2.exr"), "--model", spec, "--json",
                         "--precision", "float32"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["models_run"] == ["flat", "unet"] and printed["precision"] == "float32"
    assert "ran flat + unet in float32," in "\n".join(denoise_summary(printed))
    assert "ran flat (float32) + unet (bfloat16)," in "\n".join(denoise_summary({**printed, "precision":
                                                                                   "float32+bfloat16"}))


@pytest.mark.parametrize("weighted,skip", [(True, None), (False, None), (True, 1e-3)])
def test_combined_band_by_band_is_the_whole_image_combination(two_models: tuple[Path, Path], weighted: bool,
                                                             skip: float | None) -> None:
    """denoise_combined in bands of a few rows, each member on small tiles: combine() of the
    members' whole-image outputs (to float32 rounding of the networks' tiling); one band of the
    whole image: the same."""
    from denoise.chain import ChainRun, denoise_image

    truth, noisy, var = _case(70, 50, seed=3)
    var[:, :25] = 0.0  # a converged part (the skip test leaves it out)
    variance = var if weighted else None
    nets = [Denoiser(p).net for p in two_models]
    outputs = [denoise_image(n, noisy, core=4096, variance=variance, skip_below=skip) for n in nets]
    expected = combine(noisy, outputs, variance)
    for rows, cores in [(16, [(8, 16), (16, 16)]), (70, [(70, 50), (70, 50)]), (32, [(16, 8), (32, 24)])]:
        runs = [ChainRun(n, noisy, variance=variance, skip_below=skip) for n in nets]
        got = denoise_combined(runs, noisy, variance, rows, cores, 2**20)
        np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)


def test_an_ensemble_plan_fits_its_budget(two_models: tuple[Path, Path]) -> None:
    """Denoiser.ensemble_plan: every member's largest window at its bytes per pixel, beside the
    outputs it holds and the fixed cost, within the budget; bands where the whole image's outputs
    would not fit, the whole image where they do."""
    from denoise.ensemble import context_rows
    from denoise.tiling import window_span
    from model.architectures import alignment

    height, width = 2048, 3072
    for budget, whole in [(96, False), (1024, True)]:
        den = Denoiser("+".join(str(p) for p in two_models), max_memory_mb=budget)
        plan = den.ensemble_plan(height, width, den.members, weighted=True)
        assert (plan.rows >= height) == whole, plan
        context = context_rows(True, max(alignment(m.config) for m in den.members))
        rect = min(height, plan.rows + 2 * context)
        held = 12 * (len(den.members) - (1 if whole else 0)) * rect * width
        room = den.max_bytes - den.fixed_bytes(den.members) - held
        assert plan.combine_bytes > 0 and held + 4 * len(den.members) * rect * width + plan.combine_bytes <= \
            den.max_bytes - den.fixed_bytes(den.members) + 1
        for m, core in zip(den.members, plan.cores):
            align = alignment(m.config)
            for y0 in range(0, height, plan.rows):
                r0, r1 = max(0, y0 - context), min(height, y0 + plan.rows + context)
                for t in plan_tiles(r1 - r0, width, core, 0, align):
                    wy = window_span(t.y0 + r0, t.y1 + r0, height, m.margin, align)
                    wx = window_span(t.x0, t.x1, width, m.margin, align)
                    assert (wy[1] - wy[0]) * (wx[1] - wx[0]) * den.bytes_per_pixel(m) <= room
