"""``denoise`` on files from other renderers: multi-layer and multi-part EXRs, PFM, Radiance HDR,
two halves, a variance layer; output in the input's layout or plain RGB."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from benchmarks.denoise_memory import PATH_CHILD, ROOT, run_child
from imaging.errors import DenoiserError
from imaging.exr import read_exr, write_exr
from imaging.exr_layers import read_exr_file
from pipeline.cli import denoise_main
from denoise.denoiser import Denoiser
from pipeline.denoise_file import combine_halves, read_input
from denoise.noise_guard import strength_for
from tests.test_denoiser import write_tiny_checkpoint
from tests.test_exr_layers import blender, mitsuba_aov, multipart, planes
from tests.test_model_unet import TINY as TINY_UNET

H, W = 12, 16


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt")


@pytest.fixture(scope="module")
def denoiser(ckpt: Path) -> Denoiser:
    return Denoiser(ckpt)


def run(capsys: pytest.CaptureFixture, *argv: str) -> dict:
    assert denoise_main([*argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def rgb_of(channels: dict, prefix: str) -> np.ndarray:
    sep = "." if prefix else ""
    return np.stack([channels[f"{prefix}{sep}{c}"] for c in "RGB"], -1).astype(np.float32)


@pytest.mark.parametrize("layout, color", [("blender", "ViewLayer.Combined"), ("mitsuba", "")])
def test_multilayer_exr_keeps_its_layout(tmp_path: Path, rng: np.random.Generator, ckpt: Path,
                                         denoiser: Denoiser, capsys: pytest.CaptureFixture,
                                         layout: str, color: str) -> None:
    channels = blender(rng) if layout == "blender" else mitsuba_aov(rng)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, dict(channels)).write(str(tmp_path / "in.exr"))
    printed = run(capsys, str(tmp_path / "in.exr"), str(tmp_path / "out.exr"), "--model", str(ckpt))
    assert printed["layer"] == color and printed["layout"].startswith("as read")
    out = read_exr_file(tmp_path / "out.exr")
    assert set(out.parts[0].channels) == set(channels)
    expected = denoiser.denoise_array(rgb_of(channels, color)).image
    tol = 2e-3 if channels[next(iter(channels))].dtype == np.float16 else 1e-5
    np.testing.assert_allclose(out.image(out.layers[color]), expected, rtol=tol, atol=1e-4)
    replaced = {f"{color}.{c}" if color else c for c in "RGB"}
    for name, pixels in channels.items():
        if name not in replaced:
            assert np.array_equal(out.parts[0].channels[name], pixels), name
    run(capsys, str(tmp_path / "in.exr"), str(tmp_path / "plain.exr"), "--model", str(ckpt), "--rgb-only")
    plain = read_exr_file(tmp_path / "plain.exr")
    assert sorted(plain.parts[0].channels) == ["B", "G", "R"]
    np.testing.assert_allclose(plain.image(plain.layers[""]), out.image(out.layers[color]), rtol=1e-3)


def test_layer_flag_and_ambiguity(tmp_path: Path, rng: np.random.Generator, ckpt: Path,
                                  capsys: pytest.CaptureFixture) -> None:
    channels = {**planes(rng, "ViewLayer.Combined", "RGB"), **planes(rng, "Other.Combined", "RGB")}
    OpenEXR.File({}, dict(channels)).write(str(tmp_path / "two.exr"))
    assert denoise_main([str(tmp_path / "two.exr"), str(tmp_path / "o.exr"), "--model", str(ckpt)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "('Other.Combined', 'ViewLayer.Combined')" in err and "--layer" in err
    assert not (tmp_path / "o.exr").exists()
    printed = run(capsys, str(tmp_path / "two.exr"), str(tmp_path / "o.exr"), "--model", str(ckpt),
                  "--layer", "Other.Combined")
    out = read_exr_file(tmp_path / "o.exr")
    assert printed["layer"] == "Other.Combined"
    assert np.array_equal(out.image(out.layers["ViewLayer.Combined"]), rgb_of(channels, "ViewLayer.Combined"))
    assert not np.array_equal(out.image(out.layers["Other.Combined"]), rgb_of(channels, "Other.Combined"))


def test_multipart_with_variance_part_uses_the_noise_guard(tmp_path: Path, rng: np.random.Generator,
                                                           ckpt: Path, capsys: pytest.CaptureFixture) -> None:
    multipart(rng, tmp_path / "in.exr")  # parts color (half, spp 32), albedo, normal, variance
    printed = run(capsys, str(tmp_path / "in.exr"), str(tmp_path / "out.exr"), "--model", str(ckpt))
    guard = printed["noise_guard"]
    assert printed["layer"] == "color" and "4 parts" in printed["layout"]
    assert guard["variance"] == "variance" and guard["spp"] == 32
    assert guard["strength"] == strength_for(32) and 0 <= guard["mean_weight"] <= 1
    src, out = read_exr_file(tmp_path / "in.exr"), read_exr_file(tmp_path / "out.exr")
    assert [p.name for p in out.parts] == [p.name for p in src.parts]
    assert out.parts[0].channels["R"].dtype == np.float16 and out.parts[0].header["renderer"] == "other"
    for i in (1, 2, 3):
        for name, pixels in src.parts[i].channels.items():
            assert np.array_equal(out.parts[i].channels[name], pixels)
    unguarded = run(capsys, str(tmp_path / "in.exr"), str(tmp_path / "o2.exr"), "--model", str(ckpt),
                    "--no-noise-guard")
    assert unguarded["noise_guard"] is None


def test_variance_layer_flag(tmp_path: Path, rng: np.random.Generator, ckpt: Path,
                             capsys: pytest.CaptureFixture) -> None:
    channels = {**planes(rng, "", "RGB"), **planes(rng, "var2", "RGB")}
    OpenEXR.File({}, dict(channels)).write(str(tmp_path / "in.exr"))
    assert run(capsys, str(tmp_path / "in.exr"), str(tmp_path / "o.exr"), "--model", str(ckpt))[
        "noise_guard"] is None  # no layer called 'variance'
    printed = run(capsys, str(tmp_path / "in.exr"), str(tmp_path / "o2.exr"), "--model", str(ckpt),
                  "--variance-layer", "var2", "--spp", "8")
    assert printed["noise_guard"]["variance"] == "var2" and printed["noise_guard"]["strength"] == strength_for(8)
    assert denoise_main([str(tmp_path / "in.exr"), str(tmp_path / "o3.exr"), "--model", str(ckpt),
                         "--variance-layer", "nope"]) == 1
    assert "no variance layer named 'nope'" in capsys.readouterr().err


@pytest.mark.parametrize("spp_a, spp_b", [(None, None), (8, 8), (4, 12)])
def test_halves_mean_and_variance(tmp_path: Path, rng: np.random.Generator, spp_a: int | None,
                                  spp_b: int | None) -> None:
    a, b = rng.random((H, W, 3)).astype(np.float32), rng.random((H, W, 3)).astype(np.float32)
    write_exr(tmp_path / "a.exr", a, metadata={"spp": spp_a} if spp_a else None)
    write_exr(tmp_path / "b.exr", b, metadata={"spp": spp_b} if spp_b else None)
    both = combine_halves(read_input(tmp_path / "a.exr"), read_input(tmp_path / "b.exr"))
    n_a, n_b = (spp_a, spp_b) if spp_a else (1, 1)
    np.testing.assert_allclose(both.rgb, (n_a * a + n_b * b) / (n_a + n_b), rtol=1e-6)
    np.testing.assert_allclose(both.variance, (a - b) ** 2 * n_a * n_b / (n_a + n_b) ** 2, rtol=1e-5, atol=1e-9)
    if spp_a == spp_b:
        np.testing.assert_allclose(both.variance, (a - b) ** 2 / 4, rtol=1e-5, atol=1e-9)
    assert both.spp == (spp_a + spp_b if spp_a else None)
    rows = combine_halves(read_input(tmp_path / "a.exr"), read_input(tmp_path / "b.exr"), max_bytes=1.0)
    assert np.array_equal(rows.rgb, both.rgb) and np.array_equal(rows.variance, both.variance)  # one row at a time


def test_halves_command(tmp_path: Path, rng: np.random.Generator, ckpt: Path, denoiser: Denoiser,
                        capsys: pytest.CaptureFixture) -> None:
    a, b = rng.random((H, W, 3)).astype(np.float32), rng.random((H, W, 3)).astype(np.float32)
    write_exr(tmp_path / "a.exr", a, metadata={"spp": 8})
    write_exr(tmp_path / "b.exr", b, metadata={"spp": 8})
    printed = run(capsys, "--halves", str(tmp_path / "a.exr"), str(tmp_path / "b.exr"),
                  str(tmp_path / "o.exr"), "--model", str(ckpt))
    assert printed["noise_guard"]["variance"] == "halves" and printed["noise_guard"]["spp"] == 16
    expected = denoiser.denoise_array((a + b) / 2, variance=(a - b) ** 2 / 4, strength=strength_for(16))
    np.testing.assert_allclose(read_exr(tmp_path / "o.exr").rgb, expected.image, rtol=1e-5, atol=1e-6)
    assert printed["energy"]["mean_factor"] == pytest.approx(expected.energy_factor, rel=1e-6)
    printed = run(capsys, "--halves", str(tmp_path / "a.exr"), str(tmp_path / "b.exr"),
                  str(tmp_path / "o1.exr"), "--model", str(ckpt), "--no-energy")
    assert printed["energy"] is None and printed["noise_guard"]["mean_weight"] is not None
    write_exr(tmp_path / "small.exr", a[:8])
    assert denoise_main(["--halves", str(tmp_path / "a.exr"), str(tmp_path / "small.exr"),
                         str(tmp_path / "o2.exr"), "--model", str(ckpt)]) == 1
    assert "small.exr: half is 16x8" in capsys.readouterr().err


def test_flips_flag(tmp_path: Path, rng: np.random.Generator, ckpt: Path,
                    capsys: pytest.CaptureFixture) -> None:
    img = rng.random((H, W, 3)).astype(np.float32)
    write_exr(tmp_path / "in.exr", img)
    printed = run(capsys, str(tmp_path / "in.exr"), str(tmp_path / "o.exr"), "--model", str(ckpt), "--flips", "4")
    assert printed["flips"] == 4
    expected = Denoiser(ckpt, flips=4).denoise_array(img).image
    np.testing.assert_array_equal(read_exr(tmp_path / "o.exr").rgb, expected)
    assert Denoiser(ckpt, flips=4).bytes_per_pixel() > Denoiser(ckpt).bytes_per_pixel()  # the tiles shrink
    with pytest.raises(DenoiserError, match="flips must be one of 1, 2, 4"):
        Denoiser(ckpt, flips=3)


@pytest.mark.parametrize("argv, needle", [
    (["in.exr", "o.exr", "--flips", "3"], "--flips"),
    (["--halves", "a.exr", "b.exr", "in.exr", "o.exr"], "only the output"),
    (["--halves", "a.exr", "b.exr", "o.exr", "--variance-layer", "v"], "exclude each other"),
    (["in.exr"], "an input and an output"),
])
def test_usage_errors(argv: list[str], needle: str, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        denoise_main(argv)
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and needle in err


@pytest.mark.parametrize("suffix", ["pfm", "hdr"])
def test_pfm_and_hdr_in_and_out(tmp_path: Path, rng: np.random.Generator, ckpt: Path, denoiser: Denoiser,
                                capsys: pytest.CaptureFixture, mi, suffix: str) -> None:
    rgb = (rng.random((H, W, 3)) * 4).astype(np.float32)
    mi.Bitmap(rgb).write(str(tmp_path / f"in.{suffix}"))
    stored = np.array(mi.Bitmap(str(tmp_path / f"in.{suffix}")), np.float32)  # RGBE rounds
    run(capsys, str(tmp_path / f"in.{suffix}"), str(tmp_path / f"out.{suffix}"), "--model", str(ckpt))
    run(capsys, str(tmp_path / f"in.{suffix}"), str(tmp_path / "out.exr"), "--model", str(ckpt))
    expected = denoiser.denoise_array(stored).image
    np.testing.assert_allclose(read_exr(tmp_path / "out.exr").rgb, expected, rtol=1e-5, atol=1e-6)
    back = np.array(mi.Bitmap(str(tmp_path / f"out.{suffix}")), np.float32)
    if suffix == "pfm":
        np.testing.assert_allclose(back, expected, rtol=1e-6, atol=1e-6)
    else:  # RGBE: 8-bit mantissas sharing the largest channel's exponent
        assert (np.abs(back - expected) <= expected.max(axis=2, keepdims=True) / 128 + 1e-6).all()
    assert denoise_main([str(tmp_path / f"in.{suffix}"), str(tmp_path / "o.exr"), "--model", str(ckpt),
                         "--layer", "x"]) == 1
    assert "has no layers" in capsys.readouterr().err


def test_greyscale_pfm_is_read_as_rgb(tmp_path: Path) -> None:
    grey = np.arange(12, dtype="<f4").reshape(3, 4)
    (tmp_path / "g.pfm").write_bytes(b"Pf\n4 3\n-1.0\n" + grey[::-1].tobytes())  # PFM rows go bottom-up
    image = read_input(tmp_path / "g.pfm")
    assert image.rgb.shape == (3, 4, 3) and np.array_equal(image.rgb[..., 1], grey)


def test_unknown_format_and_broken_pfm(tmp_path: Path, ckpt: Path, capsys: pytest.CaptureFixture) -> None:
    (tmp_path / "x.png").write_bytes(b"\x89PNG\r\n\x1a\n....")
    (tmp_path / "cut.pfm").write_bytes(b"PF\n4 3\n-1.0\n" + b"\0" * 10)
    for name, needle in (("x.png", "not an OpenEXR file (nor PFM or Radiance HDR)"),
                         ("cut.pfm", "cut.pfm: header says 4x3 pixels (144 bytes), the file holds 10 bytes")):
        assert denoise_main([str(tmp_path / name), str(tmp_path / "o.exr"), "--model", str(ckpt)]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err, err


def test_exr_written_by_mitsuba_aov_film(tmp_path: Path, ckpt: Path, mi, capsys: pytest.CaptureFixture) -> None:
    """A film of Mitsuba's aov integrator, as Bitmap.write stores it: bare R,G,B denoised, the
    inner integrator's image and the AOVs kept."""
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal",
                                                          "image": {"type": "path"}},
                          "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": W, "height": H}},
                          "ball": {"type": "sphere"}, "sky": {"type": "constant"}})
    mi.render(scene, spp=4)
    scene.sensors()[0].film().bitmap().write(str(tmp_path / "aov.exr"))
    src = read_exr_file(tmp_path / "aov.exr")
    assert {"", "image", "albedo", "nn"} <= set(src.layers)
    printed = run(capsys, str(tmp_path / "aov.exr"), str(tmp_path / "out.exr"), "--model", str(ckpt))
    assert printed["layer"] == ""
    out = read_exr_file(tmp_path / "out.exr")
    assert set(out.parts[0].channels) == set(src.parts[0].channels)
    for name in ("image.R", "albedo.G", "nn.Z"):
        assert np.array_equal(out.parts[0].channels[name], src.parts[0].channels[name])


def test_reference_metrics_show_oidn_with_and_without_the_files_albedo_and_normals(
        tmp_path: Path, ckpt: Path, mi, capsys: pytest.CaptureFixture) -> None:
    """With --reference, OIDN colour-only and, from the file's albedo and normal layers, OIDN +
    albedo + normal on the same input; a file without those layers gets OIDN colour-only alone
    (32x24: FLIP needs more pixels than the other tests' images have)."""
    pytest.importorskip("pyoidn", reason="make installs pyoidn (the oidn extra)")
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal",
                                                          "image": {"type": "path"}},
                          "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 32, "height": 24},
                                     "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                                                 up=[0, 1, 0])},
                          "ball": {"type": "sphere", "bsdf": {"type": "diffuse"}}, "sky": {"type": "constant"}})
    mi.render(scene, spp=2, seed=1)
    scene.sensors()[0].film().bitmap().write(str(tmp_path / "aov.exr"))
    reference = np.asarray(mi.render(scene, spp=256, seed=2))[:, :, :3]
    write_exr(tmp_path / "ref.exr", np.ascontiguousarray(reference, dtype=np.float32))
    quality = run(capsys, str(tmp_path / "aov.exr"), str(tmp_path / "out.exr"), "--model", str(ckpt),
                  "--reference", str(tmp_path / "ref.exr"))["quality"]
    assert set(quality) == {"noisy", "denoised", "oidn", "oidn_aux"}
    assert quality["oidn_aux"] != quality["oidn"] and quality["oidn"]["psnr"] > quality["noisy"]["psnr"]
    write_exr(tmp_path / "rgb.exr", read_exr(tmp_path / "aov.exr").rgb)
    plain = run(capsys, str(tmp_path / "rgb.exr"), str(tmp_path / "out2.exr"), "--model", str(ckpt),
                "--reference", str(tmp_path / "ref.exr"))["quality"]
    assert set(plain) == {"noisy", "denoised", "oidn"} and plain["oidn"] == quality["oidn"]
    assert denoise_main([str(tmp_path / "aov.exr"), str(tmp_path / "out3.exr"), "--model", str(ckpt),
                         "--reference", str(tmp_path / "ref.exr")]) == 0
    printed = capsys.readouterr().out
    assert "oidn_aux" in printed and "oidn " in printed


def test_the_command_asks_for_no_huge_pages(tmp_path: Path, rng: np.random.Generator, ckpt: Path,
                                            monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    """One image a process: huge pages would slow its only call (denoise.allocator)."""
    import pipeline.denoise_file as denoise_file

    asked = []

    def recording(*args, **kwargs) -> Denoiser:
        asked.append(kwargs.get("huge_pages", True))
        return Denoiser(*args, **kwargs)

    monkeypatch.setattr(denoise_file, "Denoiser", recording)
    write_exr(tmp_path / "in.exr", rng.random((H, W, 3)).astype(np.float32))
    run(capsys, str(tmp_path / "in.exr"), str(tmp_path / "out.exr"), "--model", str(ckpt))
    assert asked == [False]


def test_a_denoised_image_beyond_the_memory_left_is_refused_before_denoising(
        tmp_path: Path, rng: np.random.Generator, ckpt: Path, capsys: pytest.CaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The input read, the denoised image (12 bytes a pixel) and the guard's weights (4) must fit
    in the memory left, or the command stops in one line before the network runs."""
    import imaging.memory_limit
    import pipeline.denoise_file as denoise_file

    noisy = rng.random((H, W, 3)).astype(np.float32)
    write_exr(tmp_path / "in.exr", noisy)
    monkeypatch.setattr(denoise_file, "read_input", lambda path, *a, **k: denoise_file.InputImage(
        str(path), noisy, variance=np.full_like(noisy, 0.01)))
    monkeypatch.setattr(imaging.memory_limit, "available_bytes", lambda: H * W * 16 - 1)
    assert denoise_main([str(tmp_path / "in.exr"), str(tmp_path / "out.exr"), "--model", str(ckpt)]) == 1
    assert capsys.readouterr().err.strip() == (
        f"denoise: error: {tmp_path / 'in.exr'}: 16x12 pixels: the denoised image and its guard weights need "
        "3,072 bytes, more than the 3,071 bytes of memory available")
    assert not (tmp_path / "out.exr").exists()


@pytest.mark.slow
def test_the_whole_command_keeps_its_scratch_within_the_budget(tmp_path: Path) -> None:
    """``denoise`` of a 1536x1024 EXR with a variance layer by an ensemble of two networks under
    ``--max-memory-mb 64``, in a fresh process: its peak RSS less the process before the image was
    read, less the input, its variance and the output, within 1.1x the budget (reading, both
    networks on budgeted tiles, combining them, the guard and its weight map, the energy
    correction, writing). The 4K figures: benchmarks/denoise_memory.py --parts path."""
    folder = tmp_path / "ckpts"
    folder.mkdir()
    flat = write_tiny_checkpoint(folder / "flat.ckpt")
    unet = write_tiny_checkpoint(folder / "unet.ckpt", TINY_UNET, seed=1)
    rng = np.random.default_rng(0)
    image = rng.gamma(2.0, 0.5, (1024, 1536, 3)).astype(np.float32)
    write_exr(tmp_path / "in.exr", image, layers={"variance": 0.25 * image * image})
    del image
    # the child process the benchmark measures each registry entry with (benchmarks/denoise_memory.py)
    m = run_child(ROOT, PATH_CHILD, {"input": str(tmp_path / "in.exr"), "out": str(tmp_path / "out.exr"),
                                     "entry": f"{flat}+{unet}", "spp": 16, "budget": 64})
    assert m["models"] == ["flat", "unet"], m
    assert m["scratch_mb"] <= 1.1 * 64, m
