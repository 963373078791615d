"""denoise.precision: the CPU's bfloat16 support read from /proc/cpuinfo, and the folded networks in
bfloat16 against float32.

Tolerances: bfloat16 keeps 8 mantissa bits (relative rounding 2^-9 = 0.2 %); through a tiny
random network the transfer-space output stays within 0.02 of float32 (outputs of order 1); the
noisy image's residual is added in float32, so a network with a zero output layer returns its
input bit for bit in either format.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from imaging.errors import DenoiserError
from denoise.folded import prepare_for_inference
from model.checkpoint import save_checkpoint
from model.config import ModelConfig
from model.transfer import get_transfer
from denoise.precision import FLAT_BF16_MAX_SPP, PRECISIONS, compute_dtype, cpu_flags, native_bfloat16
from pipeline.cli import denoise_main
from denoise.denoiser import Denoiser
from tests.test_inference_net import _trained_like
from tests.test_model_unet import TINY, trained_like

BF16_ATOL = 0.02
CPUINFO = "processor\t: 0\nvendor_id\t: GenuineIntel\nflags\t\t: fpu sse2 avx2 {extra}\n\nprocessor\t: 1\n"


def _cpuinfo(tmp_path: Path, extra: str) -> Path:
    path = tmp_path / f"cpuinfo-{len(extra)}"
    path.write_text(CPUINFO.format(extra=extra))
    return path


def test_flags_and_native_bfloat16(tmp_path: Path) -> None:
    amx, avx512, plain = (_cpuinfo(tmp_path, e) for e in ("amx_tile amx_bf16", "avx512f avx512_bf16", "avx512f"))
    assert cpu_flags(plain) == {"fpu", "sse2", "avx2", "avx512f"}
    assert native_bfloat16(amx) and native_bfloat16(avx512) and not native_bfloat16(plain)
    assert cpu_flags(tmp_path / "missing") == frozenset() and not native_bfloat16(tmp_path / "missing")
    assert compute_dtype("auto", True, amx) == torch.bfloat16
    assert compute_dtype("auto", False, amx) == torch.float32  # flat nets lose ~0.1 dB in bfloat16
    # ... at 128 spp; one that only runs on renders of <= 16 spp nothing (module docstring)
    assert compute_dtype("auto", False, amx, max_spp=FLAT_BF16_MAX_SPP) == torch.bfloat16
    assert compute_dtype("auto", False, amx, max_spp=FLAT_BF16_MAX_SPP + 1) == torch.float32
    assert compute_dtype("auto", False, plain, max_spp=4) == torch.float32
    assert compute_dtype("float32", False, amx, max_spp=4) == torch.float32
    assert compute_dtype("auto", True, plain) == torch.float32
    assert compute_dtype("float32", True, amx) == torch.float32
    assert compute_dtype("bfloat16", False, plain) == torch.bfloat16
    with pytest.raises(ValueError, match="precision must be one of"):
        compute_dtype("half")
    assert PRECISIONS == ("auto", "float32", "bfloat16")


def _models() -> list[torch.nn.Module]:
    flat = _trained_like(ModelConfig(layers=5, growth=4, init_features=8))
    return [flat, trained_like(TINY), trained_like(dataclasses.replace(TINY, noise_input=True))]


@pytest.mark.parametrize("index", [0, 1, 2], ids=["flat", "unet", "unet-noise"])
def test_bfloat16_network_close_to_float32(index: int) -> None:
    model = _models()[index]
    exact, half = prepare_for_inference(model), prepare_for_inference(model, torch.bfloat16)
    assert all(b.dtype == torch.bfloat16 for b in half.buffers() if b.is_floating_point())
    torch.manual_seed(3)
    for h, w in ((1, 1), (19, 45), (32, 24)):
        x = torch.rand(1, model.config.image_channels, h, w)
        with torch.inference_mode():
            want, got = exact(x), half(x)
        assert got.dtype == torch.float32 and got.shape == want.shape
        err = float((got - want).abs().max())
        assert 0 < err < BF16_ATOL  # rounded (so it did run in bfloat16), but close


@pytest.mark.parametrize("index", [0, 1], ids=["flat", "unet"])
def test_bfloat16_residual_is_added_in_float32(index: int) -> None:
    model = _models()[index]
    with torch.no_grad():
        last = model.tail if model.config.multiscale else model.tail[-1]
        last.weight.zero_()
        if model.config.multiscale:
            model.skip.weight.zero_()
            model.skip.bias.zero_()
    net = prepare_for_inference(model, torch.bfloat16)
    x = torch.rand(1, model.config.image_channels, 17, 23) * 0.9 + 0.01  # not representable in bfloat16
    with torch.inference_mode():
        assert torch.equal(net(x), x[:, :3])


def test_denoiser_precision(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "m.ckpt"
    save_checkpoint(path, _models()[1], step=0)
    img = (rng.random((40, 36, 3)) ** 3 * 20).astype(np.float32)
    exact = Denoiser(path, precision="float32")
    half = Denoiser(path, precision="bfloat16")
    assert (exact.precision, half.precision) == ("float32", "bfloat16")
    assert Denoiser(path, optimize=False, precision="bfloat16").precision == "float32"  # the module is float32
    a, b = exact.denoise_array(img).image, half.denoise_array(img).image
    assert a.dtype == b.dtype == np.float32
    pu = get_transfer(exact.config.transfer)  # compared where the network works: transfer space
    ta, tb = (pu.forward(torch.from_numpy(v)).numpy() for v in (a, b))
    assert 0 < float(np.abs(ta - tb).max()) < BF16_ATOL
    with pytest.raises(DenoiserError, match="precision must be one of"):
        Denoiser(path, precision="fp8")


def test_denoise_cli_refuses_an_unknown_precision(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        denoise_main([str(tmp_path / "in.exr"), str(tmp_path / "out.exr"), "--precision", "fp8"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--precision" in err[0] and "fp8" in err[0]


def test_auto_gives_a_flat_low_spp_member_bfloat16_where_native(tmp_path: Path) -> None:
    # An ensemble of the same flat checkpoint at <= FLAT_BF16_MAX_SPP spp and above: under auto only the first
    # computes in bfloat16, and only on a CPU with native bfloat16 (what this machine has).
    path = tmp_path / "flat.ckpt"
    save_checkpoint(path, _models()[0], step=0)
    low, high = Denoiser(f"{path}:-{FLAT_BF16_MAX_SPP}+{path}:{FLAT_BF16_MAX_SPP + 1}-").members
    assert low.precision == ("bfloat16" if native_bfloat16() else "float32")
    assert high.precision == "float32"
    assert Denoiser(f"{path}:-4", precision="float32").members[0].precision == "float32"


def test_the_default_runs_its_flat_net_in_bfloat16_up_to_16_spp_only() -> None:
    bf16 = "bfloat16" if native_bfloat16() else "float32"
    default = Denoiser()
    assert [(m.spec, m.precision) for m in default.members] == [
        ("flat-s-allspp:17-", "float32"), ("flat-s-allspp:9-16", bf16), ("flat-s-lowspp:-8", bf16),
        ("unet-m-k5-lowspp:-16", bf16), ("unet-l-allspp:17-", bf16), ("unet-m-k5-lowspp-b:-16", bf16),
        ("flat-s-allspp", bf16), ("unet-m-k5-lowspp", bf16)]
    assert [m.spec for m in default.active(12)] == ["flat-s-allspp:9-16", "unet-m-k5-lowspp:-16",
                                                    "unet-m-k5-lowspp-b:-16"]
    assert [m.spec for m in default.active(17)] == ["flat-s-allspp:17-", "unet-l-allspp:17-"]
    # the spp unknown: the U-Net on a noisy image, the flat net in bfloat16 on a cleaner one
    assert [m.spec for m in default.active(None, 0.5)] == ["unet-m-k5-lowspp"]
    assert [m.spec for m in default.active(None, 0.08)] == ["unet-m-k5-lowspp"]
    for level in (0.079, 0.01, 0.0):
        assert [(m.spec, m.precision) for m in default.active(None, level)] == [("flat-s-allspp", bf16)]
    assert Denoiser(precision="float32").active(None, 0.06)[0].precision == "float32"  # asked for: it wins


def test_a_members_own_bfloat16_holds_only_where_the_cpu_computes_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """``NAME@bfloat16`` under ``--precision auto``: bfloat16 on a CPU with it natively, the auto
    rule (float32 for a flat net) elsewhere; an asked-for format always wins."""
    import denoise.precision as precision_module
    from denoise.denoiser import member_precision

    for native, expected in ((True, "bfloat16"), (False, "auto")):
        monkeypatch.setattr(precision_module, "native_bfloat16", lambda *_, n=native: n)
        assert member_precision("bfloat16", "auto") == expected
        assert member_precision("float32", "auto") == "float32"
        assert member_precision(None, "auto") == "auto"
        assert member_precision("bfloat16", "float32") == "float32"
        assert member_precision("float32", "bfloat16") == "bfloat16"
