"""Files that lie and outputs onto inputs, through the commands: one line ``PROG: error: ...``, exit
code 1 or 2, no traceback, well under 1.5 GB of peak memory, and no input changed.

The headline cases run as their own processes, their peak resident memory read from the kernel's
accounting of that child alone (``os.wait4``): a 4 KB PFM claiming 100000x100000 pixels, a Radiance
HDR claiming 60000x60000, an EXR claiming a 100000x100000 data window, and a checkpoint whose header
says growth 4096 beside the tensors of the shipped flat net (for ``denoise --model`` and ``train
--resume``). The rest run in this process (the CLI mains, stderr captured at the file descriptors).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import safetensors
import safetensors.torch
from PIL import Image

from imaging.exr import read_exr, write_exr
from imaging.png import PNG_MAGIC, to_display
from pipeline.cli import denoise_main, main as render_main, tradeoff_main
from tests.test_bad_input import call, no_temporaries, one_line
from tests.test_denoiser import write_tiny_checkpoint
from training.cli import main as train_main
from training.synthetic import write_synthetic_dataset

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "scenes" / "examples" / "demo.xml"
PEAK_LIMIT_KB = 1536 * 1024  # "well under 1.5 GB": the commands stay far below it (their imports take ~0.3 GB)
WALL_LIMIT_S = 60  # a hang guard, not a speed figure


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_measured(module: str, function: str, argv: list[str], cwd: Path) -> tuple[int, str, int, float]:
    """(exit code, stderr, peak RSS in kB of that process alone, seconds) of ``module.function(argv)``
    run as a child process."""
    code = f"import sys; from {module} import {function} as m; sys.exit(m(sys.argv[1:]))"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    start = time.perf_counter()
    with open(cwd / "stderr.txt", "wb") as err:
        proc = subprocess.Popen([sys.executable, "-c", code, *argv], cwd=cwd, env=env,
                                stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, (cwd / "stderr.txt").read_text(), usage.ru_maxrss, time.perf_counter() - start


def lying_checkpoint(path: Path, source: Path, **changes: object) -> Path:
    """``source``'s tensors under a header whose model config has ``changes``."""
    tensors = safetensors.torch.load_file(str(source))
    with safetensors.safe_open(str(source), framework="pt") as f:
        header = json.loads(f.metadata()["denoiser_checkpoint"])
    header["model_config"].update(changes)
    safetensors.torch.save_file(tensors, str(path), metadata={"denoiser_checkpoint": json.dumps(header)})
    return path


def lying_exr(path: Path, window: tuple[int, int, int, int]) -> Path:
    """A small valid EXR whose data window attribute is replaced by ``window``."""
    write_exr(path, np.ones((8, 8, 3), np.float32))
    data = path.read_bytes()
    at = data.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    path.write_bytes(data[:at] + struct.pack("<4i", *window) + data[at + 16:])
    return path


@pytest.fixture(scope="module")
def lies(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("lies")
    (d / "lie.pfm").write_bytes(b"PF\n100000 100000\n-1.0\n" + bytes(4000))
    (d / "lie.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 60000 +X 60000\n" + b"\x80" * 4000)
    lying_exr(d / "lie.exr", (0, 0, 99999, 99999))
    write_exr(d / "in.exr", np.random.default_rng(0).random((16, 16, 3)).astype(np.float32))
    lying_checkpoint(d / "growth4096.ckpt", ROOT / "model" / "weights" / "flat-s-allspp.ckpt", growth=4096)
    write_tiny_checkpoint(d / "tiny.ckpt")
    return d


@pytest.mark.parametrize("argv, needle", [
    (["lie.pfm", "out.exr"], "lie.pfm: header says 100000x100000 pixels (120,000,000,000 bytes), the file holds 4,000"),
    (["lie.hdr", "out.exr"], "lie.hdr: header says 60000x60000 pixels (at least 14,400,000,000 bytes)"),
    (["lie.exr", "out.exr"], "lie.exr: truncated or corrupt EXR (the chunk table of part 0 runs past the end"),
    (["--model", "growth4096.ckpt", "in.exr", "out.exr"],
     "growth4096.ckpt: weights do not match the model config (it implies at least 6,039,797,760 parameters"),
])
def test_denoise_refuses_lies_in_one_line_and_little_memory(lies: Path, tmp_path: Path, argv: list[str],
                                                            needle: str) -> None:
    before = {p.name: digest(p) for p in lies.iterdir()}
    args = [a if a.startswith("-") else str(lies / a) if (lies / a).exists() else str(tmp_path / a) for a in argv]
    code, err, peak_kb, seconds = run_measured("pipeline.cli", "denoise_main", args, tmp_path)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1 and lines[0].startswith("denoise: error: ") and needle in lines[0], err
    assert peak_kb < PEAK_LIMIT_KB and seconds < WALL_LIMIT_S, (peak_kb, seconds)
    assert not (tmp_path / "out.exr").exists()
    assert {p.name: digest(p) for p in lies.iterdir() if p.name in before} == before


def test_train_resume_from_a_lying_checkpoint(lies: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(lies / "growth4096.ckpt", run / "last.ckpt")
    code, err, peak_kb, seconds = run_measured("training.cli", "main", ["--out", str(run), "--resume"], tmp_path)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1 and "last.ckpt: weights do not match the model config" in lines[0], err
    assert peak_kb < PEAK_LIMIT_KB and seconds < WALL_LIMIT_S, (peak_kb, seconds)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("ds"), scenes=2, res=(32, 32), spp=(4,), val_scenes=(1,))


def test_train_init_from_a_lying_checkpoint(lies: Path, dataset: Path, tmp_path: Path,
                                            capfd: pytest.CaptureFixture) -> None:
    code = call(train_main, ["--data", str(dataset), "--out", str(tmp_path / "run"), "--preset", "flat-s", "--steps",
                             "1", "--batch", "2", "--patch", "28", "--val-every", "0", "--no-progress", "--no-oidn",
                             "--init-from", str(lies / "growth4096.ckpt")])
    one_line(capfd, code, "growth4096.ckpt: weights do not match the model config")


# ----------------------------------------------------------------------------- outputs onto inputs
@pytest.fixture
def work(lies: Path, tmp_path: Path) -> Path:
    shutil.copy(lies / "in.exr", tmp_path / "in.exr")
    return tmp_path


def _denoise(lies: Path, *argv: str) -> int:
    return call(denoise_main, ["--model", str(lies / "tiny.ckpt"), *argv])


@pytest.mark.parametrize("make, how", [
    (lambda d: d / "in.exr", "is the input"),
    (lambda d: (os.link(d / "in.exr", d / "hard.exr"), d / "hard.exr")[1], "is a hard link to the input"),
    (lambda d: ((d / "soft.exr").symlink_to(d / "in.exr"), d / "soft.exr")[1], "is a symbolic link to the input"),
])
def test_denoise_refuses_to_write_onto_its_input(lies: Path, work: Path, capfd: pytest.CaptureFixture, make,
                                                 how: str) -> None:
    before = digest(work / "in.exr")
    out = make(work)
    one_line(capfd, _denoise(lies, str(work / "in.exr"), str(out)), how, "--overwrite")
    for flag in (["--halves", str(work / "in.exr"), str(work / "in.exr")], ["--reference", str(work / "in.exr")]):
        other = [str(out)] if flag[0] == "--halves" else [str(lies / "in.exr"), str(out)]
        one_line(capfd, _denoise(lies, *flag, *other), how)
    assert digest(work / "in.exr") == before


def test_overwrite_replaces_the_input_when_asked(lies: Path, work: Path, capfd: pytest.CaptureFixture) -> None:
    noisy = read_exr(work / "in.exr").rgb
    assert _denoise(lies, str(work / "in.exr"), str(work / "in.exr"), "--overwrite") == 0
    capfd.readouterr()
    assert "tiny" in read_exr(work / "in.exr").metadata["denoised_by"]
    assert read_exr(work / "in.exr").rgb.shape == noisy.shape


def test_denoise_refuses_an_existing_output_unless_asked(lies: Path, work: Path, capfd: pytest.CaptureFixture) -> None:
    """The second run into the same output is refused, the first run's file kept; --overwrite replaces it.
    A folder where the output goes is refused even with --overwrite."""
    assert _denoise(lies, str(work / "in.exr"), str(work / "d1.exr")) == 0
    capfd.readouterr()
    first = digest(work / "d1.exr")
    one_line(capfd, _denoise(lies, str(work / "in.exr"), str(work / "d1.exr")),
             "d1.exr: exists: refusing to replace it", "--overwrite")
    assert digest(work / "d1.exr") == first and no_temporaries(work)
    (work / "mine.png").write_bytes(b"not an output of ours")
    one_line(capfd, _denoise(lies, str(work / "in.exr"), str(work / "mine.png")), "mine.png: exists", "--overwrite")
    assert (work / "mine.png").read_bytes() == b"not an output of ours"
    assert _denoise(lies, str(work / "in.exr"), str(work / "mine.png"), "--overwrite") == 0
    capfd.readouterr()
    assert (work / "mine.png").read_bytes().startswith(PNG_MAGIC)
    (work / "dir.exr").mkdir()
    for extra in ([], ["--overwrite"]):
        one_line(capfd, _denoise(lies, str(work / "in.exr"), str(work / "dir.exr"), *extra), "dir.exr: is a folder")
    assert not list((work / "dir.exr").iterdir())


def test_outputs_are_the_format_their_name_says(lies: Path, work: Path, capfd: pytest.CaptureFixture) -> None:
    for name in ("out.exr", "out.png", "out.pfm", "out.hdr"):
        assert _denoise(lies, str(work / "in.exr"), str(work / name)) == 0, capfd.readouterr().err
    capfd.readouterr()
    assert (work / "out.png").read_bytes().startswith(PNG_MAGIC)
    assert (work / "out.pfm").read_bytes().startswith(b"PF\n")
    assert (work / "out.hdr").read_bytes().startswith(b"#?")
    denoised = read_exr(work / "out.exr").rgb
    with Image.open(work / "out.png") as png:  # the project's tonemapped 8-bit display values
        assert png.mode == "RGB" and np.array_equal(np.asarray(png), to_display(denoised))
    for name in ("out.jpg", "out.tiff", "out"):
        one_line(capfd, _denoise(lies, str(work / "in.exr"), str(work / name)), f"{name}: cannot write",
                 "must end in .exr, .pfm, .hdr (.rgbe, .pic) or .png")
        assert not (work / name).exists()


def test_render_and_tradeoff_refuse_outputs_onto_their_reference(work: Path, capfd: pytest.CaptureFixture) -> None:
    out = work / "run"
    out.mkdir()
    shutil.copy(work / "in.exr", out / "reference.exr")
    shutil.copy(work / "in.exr", out / "metrics.json")  # an input under the name of a file the run removes
    before = {p.name: digest(p) for p in out.iterdir()}
    for ref in ("reference.exr", "metrics.json"):
        code = call(render_main, [str(DEMO), "--res", "8", "8", "--spp", "1", "--reference", str(out / ref),
                                  "--out", str(out), "--no-compare", "--quiet"])
        one_line(capfd, code, f"run/{ref}: is the input", "--overwrite")
    (work / "t").mkdir()
    shutil.copy(work / "in.exr", work / "t" / "tradeoff.csv")
    code = call(tradeoff_main, [str(DEMO), "--res", "8", "8", "--spp", "1", "--reference",
                                str(work / "t" / "tradeoff.csv"), "--out", str(work / "t"), "--quiet"])
    one_line(capfd, code, "t/tradeoff.csv: is the input")
    assert {p.name: digest(p) for p in out.iterdir()} == before


def test_train_refuses_a_run_folder_that_holds_its_inputs(lies: Path, dataset: Path, tmp_path: Path,
                                                          capfd: pytest.CaptureFixture) -> None:
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(lies / "tiny.ckpt", run / "best.ckpt")
    (run / "train_config.json").write_text("{}")
    before = {p.name: digest(p) for p in run.iterdir()}
    for flag, name in (("--init-from", "best.ckpt"), ("--config", "train_config.json")):
        code = call(train_main, ["--data", str(dataset), "--out", str(run), "--steps", "1", flag, str(run / name)])
        one_line(capfd, code, f"run/{name}: is the input", "choose another --out")
    assert {p.name: digest(p) for p in run.iterdir()} == before
