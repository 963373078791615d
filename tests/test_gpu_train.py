"""benchmarks/gpu_train.sh, the script for a lent GPU machine: its dry run on a CPU (environment
checked, the recipe's plan printed, nothing rendered or trained) and its usage errors."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "gpu_train.sh"


def _run(tmp_path: Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k != "OUT"}  # OUT: the device tool's folder
    environment.update(PYTHON=sys.executable, DATA_ROOT=str(tmp_path / "data"), GPU_WHEELS=str(tmp_path / "no-wheels"),
                       GPU_DATA=str(tmp_path / "no-data"), **env)
    return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, cwd=tmp_path,
                          env=environment, timeout=300)


def test_dry_run_on_a_cpu_checks_and_plans(tmp_path: Path) -> None:
    done = _run(tmp_path, "unet-m-k5-lowspp", "8", str(tmp_path / "run"), DRY_RUN="1")
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "CUDA available: False" in out
    assert "renders with Mitsuba's llvm_ad_rgb" in out  # this machine has a libLLVM >= 16 (make bootstrap)
    assert f"--recipe unet-m-k5-lowspp --out {tmp_path / 'run'} --data-root {tmp_path / 'data'} --device cuda " \
           "--minutes 8" in out
    assert f"generate-dataset --scenes 150 --out {tmp_path / 'data'}/low256 --res 256x256" in out
    assert "# stage main: train --data" in out
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()


def test_the_run_folder_defaults_under_the_device_tools_out(tmp_path: Path) -> None:
    done = _run(tmp_path, "smoke", "2", DRY_RUN="1", OUT=str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr
    assert f"--out {tmp_path / 'out' / 'smoke'} " in done.stdout


def test_without_libllvm_or_a_cuda_variant_it_renders_with_the_scalar_variant(tmp_path: Path) -> None:
    done = _run(tmp_path, "smoke", "2", str(tmp_path / "run"), DRY_RUN="1", DRJIT_LIBLLVM_PATH=str(tmp_path / "none.so"))
    assert done.returncode == 0, done.stderr
    assert "renders with Mitsuba's scalar_rgb: no libLLVM >= 16 and no working CUDA variant" in done.stdout


def test_a_variant_the_user_names_is_kept(tmp_path: Path) -> None:
    done = _run(tmp_path, "smoke", "2", str(tmp_path / "run"), DRY_RUN="1", DENOISER_MI_VARIANT="scalar_rgb")
    assert done.returncode == 0, done.stderr
    assert "renders with Mitsuba's scalar_rgb (DENOISER_MI_VARIANT)" in done.stdout


@pytest.mark.parametrize("args, message", [(("smoke",), "usage: "), (("smoke", "ten"), "MINUTES must be a number")])
def test_usage_errors(tmp_path: Path, args: tuple[str, ...], message: str) -> None:
    done = _run(tmp_path, *args)
    assert done.returncode == 2 and message in done.stderr


def test_cuda_asked_where_there_is_none_stops_before_anything(tmp_path: Path) -> None:
    done = _run(tmp_path, "smoke", "2", str(tmp_path / "run"))
    assert done.returncode == 1 and "torch sees no CUDA device" in done.stderr
    assert not (tmp_path / "run").exists()


def test_pack_slims_mitsuba_to_the_variants_training_renders_with(tmp_path: Path) -> None:
    import zipfile

    from benchmarks.gpu_pack import pack

    names = ["mitsuba/__init__.py", "mitsuba/libmitsuba.so", "mitsuba/data/srgb.coeff",
             *(f"mitsuba/{v}.cpython-312-x86_64-linux-gnu.so" for v in
               ("scalar_rgb", "scalar_spectral", "llvm_ad_rgb", "llvm_ad_mono_polarized", "cuda_ad_rgb", "cuda_ad_spectral")),
             "mitsuba/plugins/path.so"]
    wheel = tmp_path / "mitsuba-3.9.1-cp312-cp312-manylinux_2_28_x86_64.whl"
    other = tmp_path / "drjit-1.5.0-cp312-cp312-manylinux_2_28_x86_64.whl"
    for path in (wheel, other):
        with zipfile.ZipFile(path, "w") as z:
            for name in names:
                z.writestr(name, name)
    packed = zipfile.ZipFile(pack(wheel, tmp_path / "out"))
    assert {item.compress_type for item in packed.infolist()} == {zipfile.ZIP_LZMA}
    assert all(packed.read(name) == name.encode() for name in packed.namelist())
    kept = packed.namelist()
    assert kept == ["mitsuba/__init__.py", "mitsuba/libmitsuba.so",
                    *(f"mitsuba/{v}.cpython-312-x86_64-linux-gnu.so" for v in ("scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb")),
                    "mitsuba/plugins/path.so"]
    assert zipfile.ZipFile(pack(other, tmp_path / "out")).namelist() == names  # other wheels as they are
