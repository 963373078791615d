"""The rendering core: determinism, box filter, AOVs only on request, passes, sanitising."""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from pipeline.errors import RenderError
from pipeline.render import load_scene, pass_seeds, prepare, render, render_loaded, sanitize_nonfinite
from tests.conftest import lit_plane_scene


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


def test_sanitize_counts_and_replaces_nonfinite() -> None:
    img = np.ones((3, 4, 3), np.float32)
    img[0, 0, 1], img[1, 2, 0], img[1, 2, 2], img[2, 3, 2] = np.nan, np.inf, -np.inf, -1.0
    out, count = sanitize_nonfinite(img)
    assert count == 2 and np.isfinite(out).all() and out[0, 0, 1] == 0 and out[2, 3, 2] == -1.0


@pytest.mark.parametrize("spp", [0, -4, 2.5, "8", True])
def test_bad_spp_is_refused(plane_scene: dict, spp: Any) -> None:
    with pytest.raises(RenderError, match="spp must be a positive integer"):
        render(plane_scene, spp=spp)


def test_bad_seed_and_resolution_are_refused(plane_scene: dict) -> None:
    with pytest.raises(RenderError, match="seed"):
        render(plane_scene, spp=1, seed=-1)
    with pytest.raises(RenderError, match="resolution must be positive"):
        render(plane_scene, spp=1, resolution=(0, 16))
