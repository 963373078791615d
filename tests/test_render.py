"""The rendering core: determinism, box filter, AOVs only on request, passes, crops, sanitising."""
from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rendering import render_crops
from imaging.errors import RenderError
from rendering.render import (check_render_memory, half_variance, load_scene, pass_seeds, prepare, render,
                              render_aovs, render_loaded, zero_nonfinite)
from rendering.render_crops import crop_layout, crop_seed, film_window, max_crop_pixels
from tests.conftest import lit_plane_scene

DEMO = Path(__file__).resolve().parents[1] / "scenes" / "examples" / "demo.xml"


def test_same_seed_same_image_other_seed_other_image(plane_scene: dict) -> None:
    a = render(plane_scene, spp=4, seed=3)
    b = render(plane_scene, spp=4, seed=3)
    c = render(plane_scene, spp=4, seed=4)
    assert a.rgb.shape == (32, 32, 3) and a.rgb.dtype == np.float32
    assert np.isfinite(a.rgb).all() and a.nonfinite == 0 and a.rgb.mean() > 0
    assert np.array_equal(a.rgb, b.rgb)
    assert not np.array_equal(a.rgb, c.rgb)


def _neighbour_noise_correlation(images: list[np.ndarray]) -> float:
    """Correlation of horizontally adjacent pixels of the noise (difference of two renders)."""
    noise = (images[0] - images[1]).mean(axis=2)[4:-4, 4:-4]
    return float(np.corrcoef(noise[:, :-1].ravel(), noise[:, 1:].ravel())[0, 1])


def test_box_filter_decorrelates_pixel_noise(mi: Any) -> None:
    scene = lit_plane_scene(mi, size=64, rfilter="gaussian")
    ours = [render(scene, spp=2, seed=s).rgb for s in (1, 2)]
    own_film = mi.load_dict(scene)  # the scene's own gaussian filter, bypassing our pipeline
    theirs = [np.array(mi.render(own_film, spp=2, seed=s)) for s in (1, 2)]
    assert abs(_neighbour_noise_correlation(ours)) < 0.06
    assert _neighbour_noise_correlation(theirs) > 0.2


def test_a_named_filter_correlates_the_noise_and_refuses_crops(mi: Any) -> None:
    """A dataset for a studio's filter renders with it: its pixels' noise is correlated as the
    studio's renders are; such a film cannot be stitched from crops (samples cross their edges)."""
    scene = lit_plane_scene(mi, size=64, rfilter="box")
    loaded = load_scene(prepare(scene, pixel_filter="gaussian"))
    images = [render_loaded(loaded, spp=2, seed=s).rgb for s in (1, 2)]
    assert _neighbour_noise_correlation(images) > 0.2
    larger = load_scene(prepare(scene, (128, 96), pixel_filter="gaussian"))
    with pytest.raises(RenderError, match="GaussianFilter pixel filter does not fit the memory budget"):
        render_loaded(larger, spp=1, max_memory_mb=0.01)


def test_aovs_only_when_requested(plane_scene: dict) -> None:
    plain = load_scene(prepare(plane_scene))
    assert not str(plain.integrator()).startswith("AOVIntegrator")
    assert render_loaded(plain, spp=2).aovs == {}
    res = render(plane_scene, spp=4, seed=5, aovs=("albedo", "sh_normal"))
    alb, nrm = res.aovs["albedo"], res.aovs["sh_normal"]
    assert alb.shape == nrm.shape == (32, 32, 3)
    assert alb.min() >= 0 and alb.max() <= 1
    np.testing.assert_allclose(alb[16, 16], [0.6, 0.5, 0.4], atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=2), 1.0, atol=1e-3)
    # RGB comes first and is the same radiance as without AOVs.
    assert np.array_equal(res.rgb, render(plane_scene, spp=4, seed=5).rgb)


def test_resolution_override(plane_scene: dict) -> None:
    assert render(plane_scene, spp=1, resolution=(20, 12)).rgb.shape == (12, 20, 3)


def test_multi_pass_render_is_deterministic_and_unbiased(plane_scene: dict) -> None:
    one = render(plane_scene, spp=64, seed=9)
    split = render(plane_scene, spp=64, seed=9, max_samples_per_pass=32 * 32 * 5)  # 13 passes
    again = render(plane_scene, spp=64, seed=9, max_samples_per_pass=32 * 32 * 5)
    assert np.array_equal(split.rgb, again.rgb) and not np.array_equal(split.rgb, one.rgb)
    assert abs(split.rgb.mean() - one.rgb.mean()) < 0.02 * one.rgb.mean()


def test_pass_seeds_are_distinct() -> None:
    seeds = pass_seeds(7, 1000)
    assert seeds[0] == 7 and len(set(seeds)) == 1000 and all(0 <= s < 2**32 for s in seeds)


def test_zero_nonfinite_marks_and_replaces_in_place() -> None:
    img = np.ones((3, 4, 3), np.float32)
    img[0, 0, 1], img[1, 2, 0], img[1, 2, 2], img[2, 3, 2] = np.nan, np.inf, -np.inf, -1.0
    bad = zero_nonfinite(img)
    assert bad.shape == (3, 4) and bad.sum() == 2 and bad[0, 0] and bad[1, 2]
    assert np.isfinite(img).all() and img[0, 0, 1] == 0 and img[2, 3, 2] == -1.0


@pytest.mark.parametrize("spp", [0, -4, 2.5, "8", True])
def test_bad_spp_is_refused(plane_scene: dict, spp: Any) -> None:
    with pytest.raises(RenderError, match="spp must be a positive integer"):
        render(plane_scene, spp=spp)


def test_bad_seed_and_resolution_are_refused(plane_scene: dict) -> None:
    with pytest.raises(RenderError, match="seed"):
        render(plane_scene, spp=1, seed=-1)
    with pytest.raises(RenderError, match="resolution must be positive"):
        render(plane_scene, spp=1, resolution=(0, 16))


# ----------------------------------------------------------------------------- crops (memory budget)
MIN_BUDGET_MB = 1.0  # below the fixed cost: crops of render_crops.MIN_CROP_PIXELS (4096 px)


def _constant_scene(width: int, height: int) -> dict[str, Any]:
    """Only a constant environment visible: every sample's radiance is exactly RADIANCE."""
    return {"type": "scene", "integrator": {"type": "path"},
            "sensor": {"type": "perspective", "fov": 40.0, "film": {"type": "hdrfilm", "width": width,
                                                                    "height": height}},
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": RADIANCE}}}


RADIANCE = [0.5, 0.25, 2.0]


@pytest.mark.parametrize(("width", "height", "max_pixels", "count"), [
    (64, 48, None, 1), (64, 48, 64 * 48, 1), (128, 96, 4096, 3), (100, 41, 1000, 5), (4500, 3, 4096, 6),
    (7, 5, 1, 35)])
def test_crop_layout_tiles_the_film_exactly_once(width: int, height: int, max_pixels: int | None,
                                                 count: int) -> None:
    crops = crop_layout(width, height, max_pixels)
    assert len(crops) == count
    cover = np.zeros((height, width), int)
    for x, y, w, h in crops:
        assert w >= 1 and h >= 1 and (max_pixels is None or w * h <= max_pixels)
        cover[y:y + h, x:x + w] += 1
    assert (cover == 1).all()
    assert len({w for _, _, w, _ in crops}) <= 2 and len({h for _, _, _, h in crops}) <= 2
    if max_pixels is not None and width <= max_pixels:
        assert all(w == width for _, _, w, _ in crops)  # bands the width of the film: fewest crops


def test_budget_bounds_the_crop_pixels() -> None:
    assert max_crop_pixels(3, True, None) is None
    small, large = max_crop_pixels(3, True, 256), max_crop_pixels(3, True, 1024)
    assert small is not None and large is not None and 4 * small < large
    assert max_crop_pixels(9, True, 256) < small < max_crop_pixels(3, False, 256)  # more buffers, fewer pixels
    fixed_mb = render_crops.FIXED_BYTES / render_crops.MB
    assert small * render_crops.bytes_per_pixel(3, True) <= (256 - fixed_mb) * render_crops.MB
    assert max_crop_pixels(3, True, MIN_BUDGET_MB) == render_crops.MIN_CROP_PIXELS
    for bad in (0, -5.0, float("inf"), float("nan")):
        with pytest.raises(RenderError, match="memory budget must be positive and finite"):
            max_crop_pixels(3, False, bad)


def test_crop_seeds_are_distinct_and_crop_zero_keeps_the_seed() -> None:
    seeds = [crop_seed(7, i) for i in range(1000)]
    assert seeds[0] == 7 and len(set(seeds)) == 1000 and all(0 <= s < 2**32 for s in seeds)
    assert not set(seeds[1:]) & set(pass_seeds(7, 1000))  # no crop reuses a pass seed of crop 0


@pytest.mark.parametrize("halves", [False, True])
def test_aov_pass_gives_the_aovs_of_the_render_that_has_them(plane_scene: dict, halves: bool) -> None:
    """render_aovs on the plain scene: the AOVs a render of the scene prepared with them gives (the
    same camera rays), bit for bit; the plain scene renders the same radiance after the pass."""
    aovs = ("albedo", "sh_normal")
    plain = load_scene(prepare(plane_scene))
    before = render_loaded(plain, 4, 5, halves=halves)
    alone = render_aovs(plain, 4, 5, aovs, halves=halves)
    both = render_loaded(load_scene(prepare(plane_scene, aovs=aovs)), 4, 5, aovs, halves=halves)
    assert set(alone.aovs) == set(aovs) and alone.seconds > 0 and alone.nonfinite == 0
    for name in aovs:
        assert np.array_equal(alone.aovs[name], both.aovs[name]), name
    assert np.array_equal(render_loaded(plain, 4, 5, halves=halves).rgb, before.rgb)
    assert np.array_equal(before.rgb, both.rgb)  # a path tracer's radiance is the same wrapped or not
    with pytest.raises(RenderError, match="at least one AOV"):
        render_aovs(plain, 4, 5, ())


@pytest.mark.parametrize("size", [(128, 96), (4500, 3)])  # bands; a grid (one row exceeds the budget)
def test_cropped_constant_scene_has_no_seams(size: tuple[int, int]) -> None:
    res = render(_constant_scene(*size), spp=4, seed=2, halves=True, max_memory_mb=MIN_BUDGET_MB)
    assert res.crops == (3 if size == (128, 96) else 6)
    assert res.rgb.shape == (size[1], size[0], 3) and res.nonfinite == 0
    assert (res.rgb == np.float32(RADIANCE)).all()  # every pixel of every crop, none left unwritten
    assert res.variance is not None and (res.variance == 0).all()


def test_one_crop_render_is_the_same_whatever_the_budget(plane_scene: dict) -> None:
    scene = load_scene(prepare(plane_scene, aovs=("albedo",)))
    images = [render_loaded(scene, 4, 3, ("albedo",), halves=True, max_memory_mb=mb)
              for mb in (None, 1024.0, MIN_BUDGET_MB)]  # 32x32 = 1024 pixels fit any budget
    assert [r.crops for r in images] == [1, 1, 1]
    for r in images[1:]:
        assert np.array_equal(r.rgb, images[0].rgb) and np.array_equal(r.variance, images[0].variance)
        assert np.array_equal(r.aovs["albedo"], images[0].aovs["albedo"])


def test_cropped_render_matches_one_piece_in_distribution(mi: Any) -> None:
    """Same expectation band by band (within 4 standard errors from the halves' variance), same
    noise level, deterministic for a given budget, and the scene's film window is restored."""
    scene = load_scene(prepare(lit_plane_scene(mi, rfilter="box"), (128, 96), aovs=("albedo",)))
    whole = render_loaded(scene, 16, 1, ("albedo",), halves=True, max_memory_mb=None)
    crops = render_loaded(scene, 16, 1, ("albedo",), halves=True, max_memory_mb=MIN_BUDGET_MB)
    again = render_loaded(scene, 16, 1, ("albedo",), halves=True, max_memory_mb=MIN_BUDGET_MB)
    assert (whole.crops, crops.crops) == (1, 3)
    assert np.array_equal(crops.rgb, again.rgb) and not np.array_equal(crops.rgb, whole.rgb)
    assert film_window(scene) == (0, 0, 128, 96)
    assert np.array_equal(render_loaded(scene, 16, 1, ("albedo",), halves=True).rgb, whole.rgb)
    assert whole.variance is not None and crops.variance is not None
    for rows in (slice(0, 32), slice(32, 64), slice(64, 96)):  # the three bands
        n = 128 * 32
        diff = crops.rgb[rows].mean(axis=(0, 1)) - whole.rgb[rows].mean(axis=(0, 1))
        se = np.sqrt((crops.variance[rows].sum(axis=(0, 1)) + whole.variance[rows].sum(axis=(0, 1)))) / n
        assert (np.abs(diff) < 4 * se).all(), (diff, se)
    ratio = crops.variance.mean() / whole.variance.mean()
    assert 0.8 < ratio < 1.25
    np.testing.assert_allclose(crops.aovs["albedo"], np.broadcast_to([0.6, 0.5, 0.4], (96, 128, 3)), atol=1e-5)


def test_peak_rss_sees_memory_held_in_the_block() -> None:
    from imaging.peak_rss import MB, PeakRSS

    with PeakRSS() as memory:
        block = np.ones(64 * MB // 8)  # touched: resident
        threading.Event().wait(0.05)  # the sampler runs while it is held
        del block
    figures = memory.to_dict()
    assert figures["over_start_mb"] is not None and figures["over_start_mb"] >= 60
    assert figures["peak_mb"] == pytest.approx(figures["start_mb"] + figures["over_start_mb"])


def test_render_and_denoise_renders_in_crops_and_reports_render_memory(tmp_path: Path) -> None:
    from pipeline.cli import main
    from tests.test_denoiser import write_tiny_checkpoint

    ckpt = write_tiny_checkpoint(tmp_path / "tiny.ckpt")
    out = tmp_path / "run"
    assert main([str(DEMO), "--spp", "4", "--res", "128", "96", "--model", str(ckpt), "--out", str(out),
                 "--max-memory-mb", str(MIN_BUDGET_MB), "--no-compare", "--quiet"]) == 0
    memory = json.loads((out / "metrics.json").read_text())["render_memory"]
    assert memory["crops"] == 3 and memory["budget_mb"] == MIN_BUDGET_MB
    assert memory["start_mb"] > 0 and memory["peak_mb"] >= memory["start_mb"]


@pytest.mark.parametrize("n_a,n_b", [(4, 4), (3, 5)])
def test_half_variance_estimates_the_variance_of_the_mean(n_a: int, n_b: int) -> None:
    """Halves with per-sample variance s^2: the mean of n_a + n_b samples has variance s^2/n."""
    rng = np.random.default_rng(1)
    s, shape = 0.5, (64, 64, 3)
    a = 2.0 + rng.normal(0, s / np.sqrt(n_a), shape)
    b = 2.0 + rng.normal(0, s / np.sqrt(n_b), shape)
    estimate = half_variance(a, b, n_a, n_b)
    assert estimate.dtype == np.float32 and estimate.shape == shape
    # 12288 one-degree-of-freedom estimates: their mean has a relative std of sqrt(2/12288) = 1.3%.
    assert estimate.mean() == pytest.approx(s**2 / (n_a + n_b), rel=0.05)


def test_half_variance_refuses_bad_halves() -> None:
    with pytest.raises(ValueError, match="shape"):
        half_variance(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)), 1, 1)
    with pytest.raises(ValueError, match="at least one sample"):
        half_variance(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)), 0, 2)


def test_a_film_beyond_the_memory_left_is_refused_before_anything_is_allocated(
        plane_scene: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """One line naming the size, the bytes and the memory left, instead of numpy's allocation
    failure (or the OOM killer): a 32x32 film in halves holds rgb and variance (2 x 12 KiB) and
    the render's scratch (its fixed 32 MB and 128 bytes a pixel)."""
    import imaging.memory_limit

    loaded = load_scene(prepare(plane_scene))
    need = 2 * 32 * 32 * 12 + render_crops.FIXED_BYTES + 32 * 32 * 128
    assert render_crops.render_bytes(32, 32, 3, True, 1024.0) == need
    monkeypatch.setattr(imaging.memory_limit, "available_bytes", lambda: need - 1)
    with pytest.raises(RenderError, match=r"^32x32 pixels: 2 float32 images \(rgb, variance\) and the render's "
                                          r"scratch need 32 MB, more than the 32 MB of memory available$"):
        render_loaded(loaded, spp=2, halves=True)
    monkeypatch.setattr(imaging.memory_limit, "available_bytes", lambda: need)
    assert render_loaded(loaded, spp=2, halves=True).variance is not None
    with pytest.raises(RenderError, match=r"demo.xml: 100000x100000 pixels: 4 float32 images \(rgb, albedo, "
                                          r"denoised, reference\)"):
        check_render_memory(100_000, 100_000, ("albedo",), held=("denoised", "reference"), source="demo.xml")


def test_progress_counts_every_sample_of_every_pass_and_crop(plane_scene: dict) -> None:
    """``progress(done, total)`` after each pass: rising to spp x pixels over the passes of both
    halves of every crop."""
    loaded = load_scene(prepare(plane_scene, (128, 64)))
    calls: list[tuple[int, int]] = []
    result = render_loaded(loaded, spp=8, halves=True, max_samples_per_pass=2 * 4096, max_memory_mb=0.01,
                           progress=lambda done, total: calls.append((done, total)))
    assert result.crops == 2  # of 4096 pixels (render_crops.MIN_CROP_PIXELS)
    assert len(calls) == 2 * 2 * 2  # two passes of 2 spp in each half of each crop
    assert [d for d, _ in calls] == sorted({d for d, _ in calls}) and calls[-1] == (8 * 8192, 8 * 8192)


def test_a_huge_spp_starts_at_once_and_holds_nothing_per_pass(plane_scene: dict) -> None:
    """10^12 passes of one sample: nothing is made per pass before they run (a list of 10^12
    counts or seeds would not fit), so the first pass reports at once."""
    class Stop(Exception):
        pass

    def stop(done: int, total: int) -> None:
        raise Stop(done, total)

    loaded = load_scene(prepare(plane_scene))
    with pytest.raises(Stop) as stopped:
        render_loaded(loaded, spp=10**12, max_samples_per_pass=1, progress=stop)
    assert stopped.value.args == (32 * 32, 10**12 * 32 * 32)
