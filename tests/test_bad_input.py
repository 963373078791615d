"""Bad input to every command: one line on stderr naming the problem (and the file), a non-zero exit
code, no traceback, and nothing written that looks complete but is not.

Commands: ``render-and-denoise`` (pipeline.cli.main), ``denoise`` (pipeline.cli.denoise_main),
``train`` (training.cli.main), ``generate-dataset`` (dataset_gen.cli.main), called in-process. stderr
is captured at the file-descriptor level, so what native libraries (OpenEXR, Mitsuba) print counts.
A full disk is simulated by failing ``fsync`` (and the checkpoint writer) with ENOSPC; a read-only
folder is a real one (mode 555, made immutable with ``chattr +i`` when running as root).
"""
from __future__ import annotations

import errno
import json
import os
import pickle
import re
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import safetensors.torch
import torch

from dataset_gen.cli import main as generate_main
from dataset_gen.manifest import read_records
from imaging.atomic_io import TMP_PREFIX
from imaging.errors import SceneError
from imaging.exr import read_exr, write_exr
from rendering.scene_io import prepare_xml
from model.checkpoint import read_checkpoint
from training.cli import main as train_main
from training.dataset import load_val_images, read_manifest
from training.synthetic import write_synthetic_dataset
from pipeline.cli import denoise_main
from pipeline.cli import main as render_main
from tests.test_denoiser import write_tiny_checkpoint

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "scenes" / "examples" / "demo.xml"
HEAD = ("<scene version='3.0.0'><integrator type='path'/><sensor type='perspective'><film type='hdrfilm'>"
        "<integer name='width' value='8'/><integer name='height' value='8'/></film></sensor>")
SCENES = {
    "malformed.xml": "<scene version='3.0.0'><shape type='sphere'>",
    "missing_mesh.xml": HEAD + "<shape type='ply'><string name='filename' value='nope.ply'/></shape></scene>",
    "missing_texture.xml": HEAD + "<shape type='sphere'><bsdf type='diffuse'><texture type='bitmap' "
                           "name='reflectance'><string name='filename' value='nope.png'/></texture></bsdf>"
                           "</shape></scene>",
    "unknown_plugin.xml": HEAD + "<shape type='blobby'/></scene>",
    "no_integrator.xml": HEAD.replace("<integrator type='path'/>", "") + "<shape type='sphere'/></scene>",
    "bad_value.xml": HEAD + "<shape type='sphere'><float name='radius' value='abc'/></shape></scene>",
}
MARKER = "PICKLE-RAN"


class _Evil:
    """Unpickling this creates a marker file: proof that a loader went through pickle."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple:
        return (Path.touch, (self.marker,))


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Every kind of bad file, next to good ones: scenes, EXRs, checkpoints."""
    d = tmp_path_factory.mktemp("bad")
    for name, text in SCENES.items():
        (d / name).write_text(text)
    (d / "folder.xml").mkdir()
    good = write_tiny_checkpoint(d / "good.ckpt")
    data = good.read_bytes()
    (d / "truncated.ckpt").write_bytes(data[: len(data) // 2])
    safetensors.torch.save_file({"weight": torch.zeros(3)}, str(d / "foreign.ckpt"))
    ckpt = read_checkpoint(good)
    header = {**ckpt.header, "model_config": {**ckpt.header["model_config"], "layers": 5}}
    safetensors.torch.save_file(ckpt.tensors, str(d / "other_arch.ckpt"),
                                metadata={"denoiser_checkpoint": json.dumps(header)})
    (d / "pickle.ckpt").write_bytes(pickle.dumps(_Evil(d / MARKER)))
    torch.save({"model": _Evil(d / MARKER)}, d / "torch_save.ckpt")
    write_exr(d / "good.exr", np.ones((8, 8, 3), np.float32))
    exr = (d / "good.exr").read_bytes()
    (d / "truncated.exr").write_bytes(exr[: len(exr) // 2])
    (d / "not_exr.exr").write_text("hello")
    (d / "empty.exr").write_bytes(b"")
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"Y": np.ones((8, 8), np.float32)}) as f:
        f.write(str(d / "gray.exr"))
    write_exr(d / "other_size.exr", np.ones((9, 8, 3), np.float32))
    return d


def call(fn: Callable[[list[str]], int], argv: list[str]) -> int:
    """Exit code of a CLI main, usage errors (SystemExit) included."""
    try:
        return fn(argv)
    except SystemExit as exc:
        return int(exc.code)


def one_line(capfd: pytest.CaptureFixture, code: int, *needles: str, stdout_empty: bool = True) -> str:
    """Assert a failed command left exactly one stderr line holding ``needles``; return it."""
    out, err = capfd.readouterr()
    lines = err.strip().splitlines()
    assert code != 0, err
    assert len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], lines[0]
    if stdout_empty:
        assert out.strip() == "", out
    return lines[0]


def no_temporaries(folder: Path) -> bool:
    return not list(folder.rglob(f"{TMP_PREFIX}*"))


@pytest.fixture
def readonly_dir(tmp_path: Path) -> Iterator[Path]:
    """A folder nobody can create files in, root included (``chattr +i``)."""
    d = tmp_path / "readonly"
    d.mkdir()
    d.chmod(0o555)

    def writable() -> bool:
        try:
            (d / "probe").touch()
        except OSError:
            return False
        (d / "probe").unlink()
        return True

    immutable = False
    if writable():  # root ignores mode bits
        try:
            immutable = subprocess.run(["chattr", "+i", str(d)], capture_output=True).returncode == 0
        except FileNotFoundError:
            pass
        if not immutable or writable():
            pytest.skip("cannot make a read-only folder here (root without chattr)")
    yield d
    if immutable:
        subprocess.run(["chattr", "-i", str(d)], check=True)
    d.chmod(0o755)


@pytest.fixture
def disk_full(monkeypatch: pytest.MonkeyPatch) -> Callable[[int], None]:
    """``disk_full(n)``: the first ``n`` fsyncs succeed, every later one fails with ENOSPC."""
    def arm(allowed: int) -> None:
        real, calls = os.fsync, [0]

        def fsync(fd: int) -> None:
            calls[0] += 1
            if calls[0] > allowed:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            real(fd)

        monkeypatch.setattr(os, "fsync", fsync)
    return arm


# ----------------------------------------------------------------------------- render-and-denoise
def _render_args(files: Path, out: Path, *extra: str) -> list[str]:
    return ["--model", str(files / "good.ckpt"), "--quiet", "--spp", "1", "--res", "8", "8",
            "--out", str(out), *extra]


@pytest.mark.parametrize("scene, needles", [
    ("missing.xml", ["missing.xml", "file not found"]),
    ("folder.xml", ["folder.xml", "is a directory"]),
    ("malformed.xml", ["malformed.xml", "malformed XML"]),
    ("missing_mesh.xml", ["missing_mesh.xml", "nope.ply"]),
    ("missing_texture.xml", ["missing_texture.xml", "nope.png"]),
    ("unknown_plugin.xml", ["unknown_plugin.xml", "blobby"]),
    ("no_integrator.xml", ["no_integrator.xml", "no <integrator>"]),
    ("bad_value.xml", ["bad_value.xml", "abc"]),
])
def test_render_bad_scene(files: Path, tmp_path: Path, capfd: pytest.CaptureFixture, scene: str,
                          needles: list[str]) -> None:
    out = tmp_path / "out"
    one_line(capfd, call(render_main, [str(files / scene), *_render_args(files, out)]), *needles)
    assert not (out / "metrics.json").exists() and not (out / "denoised.exr").exists()


@pytest.mark.parametrize("extra, needles, code", [
    (["--param", "nosuch=1"], ["demo.xml", "'nosuch' is not a parameter"], 1),
    (["--param", "resx=0"], ["demo.xml", "film size is 0x"], 1),   # zero resolution from the scene
    (["--param", "spp=abc"], ["demo.xml", "abc"], 1),
    (["--spp", "-4"], ["--spp", "-4"], 2),
    (["--spp", "abc"], ["--spp", "abc"], 2),
    (["--spp", "0"], ["--spp"], 2),
    (["--res", "0", "8"], ["--res"], 2),
    (["--max-memory-mb", "inf"], ["max memory"], 1),
])
def test_render_bad_arguments(files: Path, tmp_path: Path, capfd: pytest.CaptureFixture, extra: list[str],
                              needles: list[str], code: int) -> None:
    model = ["--model", str(files / "good.ckpt")]  # default resolution: --param resx=... must count
    rc = call(render_main, [str(DEMO), *model, "--quiet", "--spp", "1", "--out", str(tmp_path / "out"), *extra])
    assert rc == code
    one_line(capfd, rc, *needles)


@pytest.mark.parametrize("flag, name, needles", [
    ("--reference", "truncated.exr", ["truncated.exr", "truncated or corrupt"]),
    ("--reference", "not_exr.exr", ["not_exr.exr", "not an OpenEXR file"]),
    ("--reference", "gray.exr", ["gray.exr", "no R/G/B"]),
    ("--reference", "other_size.exr", ["other_size.exr", "reference is 8x9, render is 8x8"]),
    ("--model", "truncated.ckpt", ["truncated.ckpt", "truncated or not a safetensors checkpoint"]),
    ("--model", "foreign.ckpt", ["foreign.ckpt", "not a denoiser checkpoint"]),
    ("--model", "other_arch.ckpt", ["other_arch.ckpt", "weights do not match the model config"]),
    ("--model", "pickle.ckpt", ["pickle.ckpt"]),
    ("--model", "missing.ckpt", ["missing.ckpt", "not found"]),
])
def test_render_bad_reference_or_model(files: Path, tmp_path: Path, capfd: pytest.CaptureFixture, flag: str,
                                       name: str, needles: list[str]) -> None:
    out = tmp_path / "out"
    one_line(capfd, call(render_main, [str(DEMO), *_render_args(files, out), flag, str(files / name)]), *needles)
    assert not (out / "metrics.json").exists()


def test_render_output_not_writable(files: Path, readonly_dir: Path, capfd: pytest.CaptureFixture) -> None:
    one_line(capfd, call(render_main, [str(DEMO), *_render_args(files, readonly_dir / "run")]),
             "readonly/run", "cannot create output folder")
    one_line(capfd, call(render_main, [str(DEMO), *_render_args(files, readonly_dir)]),
             "readonly", "not writable")
    blocker = readonly_dir.parent / "a_file"
    blocker.write_text("")
    one_line(capfd, call(render_main, [str(DEMO), *_render_args(files, blocker)]), "a_file")


def test_render_disk_full(files: Path, tmp_path: Path, capfd: pytest.CaptureFixture,
                          disk_full: Callable[[int], None]) -> None:
    out = tmp_path / "out"
    disk_full(2)  # config.json and noisy.exr fit, denoised.exr does not
    line = one_line(capfd, call(render_main, [str(DEMO), *_render_args(files, out)]), "No space left on device")
    assert str(out / "denoised.exr") in line
    assert (out / "noisy.exr").exists() and read_exr(out / "noisy.exr").rgb.shape == (8, 8, 3)
    assert not (out / "denoised.exr").exists() and not (out / "metrics.json").exists()
    assert no_temporaries(out)


# ----------------------------------------------------------------------------- denoise
@pytest.mark.parametrize("name, needles", [
    ("missing.exr", ["missing.exr", "file not found"]),
    ("truncated.exr", ["truncated.exr", "truncated or corrupt"]),
    ("not_exr.exr", ["not_exr.exr", "not an OpenEXR file"]),
    ("empty.exr", ["empty.exr", "not an OpenEXR file"]),
    ("gray.exr", ["gray.exr", "no R/G/B"]),
    (".", ["is a directory"]),
])
def test_denoise_bad_input_or_reference(files: Path, tmp_path: Path, capfd: pytest.CaptureFixture, name: str,
                                        needles: list[str]) -> None:
    out = tmp_path / "out.exr"
    model = ["--model", str(files / "good.ckpt")]
    one_line(capfd, call(denoise_main, [str(files / name), str(out), *model]), *needles)
    one_line(capfd, call(denoise_main, [str(files / "good.exr"), str(out), *model,
                                        "--reference", str(files / name)]), *needles)
    assert not out.exists() and no_temporaries(tmp_path)


@pytest.mark.parametrize("argv, needles", [
    (["{f}/good.exr", "{t}/o.exr", "--model", "{f}/good.ckpt", "--reference", "{f}/other_size.exr"],
     ["other_size.exr", "reference is 8x9, input is 8x8"]),
    (["{f}/good.exr", "{t}/o.exr", "--model", "{f}/torch_save.ckpt"], ["torch_save.ckpt"]),
    (["{f}/good.exr", "{t}/o.exr", "--model", "{f}/other_arch.ckpt"], ["other_arch.ckpt"]),
    (["{f}/good.exr", "{t}/o.exr", "--model", "{f}"], ["cannot read"]),
    (["{f}/good.exr", "{t}/no/such/o.exr", "--model", "{f}/good.ckpt"], ["o.exr", "output folder does not exist"]),
    (["{f}/good.exr", "{t}", "--model", "{f}/good.ckpt"], ["cannot write"]),
    (["{f}/good.exr", "{t}/o.exr", "--model", "{f}/good.ckpt", "--max-memory-mb", "0"], ["max memory"]),
])
def test_denoise_bad_arguments(files: Path, tmp_path: Path, capfd: pytest.CaptureFixture, argv: list[str],
                               needles: list[str]) -> None:
    args = [a.format(f=files, t=tmp_path) for a in argv]
    one_line(capfd, call(denoise_main, args), *needles)
    assert not (tmp_path / "o.exr").exists() and no_temporaries(tmp_path)


def test_denoise_usage_error_is_one_line(capfd: pytest.CaptureFixture) -> None:
    rc = call(denoise_main, ["only-one-argument"])
    assert rc == 2
    one_line(capfd, rc, "denoise: error:", "output")


def test_denoise_output_not_writable_and_disk_full(files: Path, readonly_dir: Path, tmp_path: Path,
                                                   capfd: pytest.CaptureFixture,
                                                   disk_full: Callable[[int], None]) -> None:
    model = ["--model", str(files / "good.ckpt")]
    one_line(capfd, call(denoise_main, [str(files / "good.exr"), str(readonly_dir / "o.exr"), *model]),
             "readonly/o.exr", "cannot write")
    disk_full(0)
    out = tmp_path / "o.exr"
    one_line(capfd, call(denoise_main, [str(files / "good.exr"), str(out), *model]),
             "o.exr", "No space left on device")
    assert not out.exists() and no_temporaries(tmp_path)


# ----------------------------------------------------------------------------- train
@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("ds"), scenes=2, res=(32, 32), spp=(4,),
                                   val_scenes=(1,))


def _broken_copy(dataset: Path, tmp_path: Path, how: str) -> Path:
    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    images = data / "images"
    if how == "malformed dataset.json":
        (data / "dataset.json").write_text("{")
    elif how == "other configuration":
        (data / "dataset.json").write_text(json.dumps({"version": 2, "spp": [4]}))
    elif how == "missing image":
        (images / "scene0000_0004spp.hdr.exr").unlink()
    elif how == "truncated image":
        raw = (images / "scene0000_ref.hdr.exr").read_bytes()
        (images / "scene0000_ref.hdr.exr").write_bytes(raw[: len(raw) // 2])
    elif how == "image of another size":
        write_exr(images / "scene0000_ref.hdr.exr", np.ones((16, 16, 3), np.float32))
    elif how == "malformed manifest":
        (data / "manifest.jsonl").write_text('{"index": "../../etc", "split": "train", "spp": [4]}\n')
    elif how == "not a folder":
        shutil.rmtree(data)
        data.write_text("")
    return data


@pytest.mark.parametrize("how, needles", [
    ("not a folder", ["data/dataset.json", "Not a directory"]),
    ("malformed dataset.json", ["dataset.json", "cannot read"]),
    ("other configuration", ["dataset.json", "unsupported dataset version 2"]),
    ("missing image", ["scene0000_0004spp.hdr.exr", "file not found"]),
    ("truncated image", ["scene0000_ref.hdr.exr", "truncated or corrupt"]),
    ("image of another size", ["scene 0", "differs from reference"]),
    ("malformed manifest", ["manifest.jsonl:1", "malformed manifest line"]),
])
def test_train_bad_dataset(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture, how: str,
                           needles: list[str]) -> None:
    data = _broken_copy(dataset, tmp_path, how)
    run = tmp_path / "run"
    rc = call(train_main, ["--data", str(data), "--out", str(run), "--preset", "flat-s", "--steps", "1",
                           "--patch", "28", "--no-progress"])
    line = one_line(capfd, rc, *needles)
    assert line.startswith("train: error: ")
    assert not (run / "last.ckpt").exists()


@pytest.mark.parametrize("extra, needles, code", [
    (["--steps", "abc"], ["--steps", "abc"], 2),
    (["--steps", "-5"], ["steps must be a positive integer"], 1),
    (["--lr", "-1"], ["lr must be > 0"], 1),
    (["--lr", "abc"], ["--lr"], 2),
    (["--batch", "0"], ["batch must be a positive integer"], 1),
])
def test_train_bad_numbers(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture, extra: list[str],
                           needles: list[str], code: int) -> None:
    rc = call(train_main, ["--data", str(dataset), "--out", str(tmp_path / "run"), *extra])
    assert rc == code
    one_line(capfd, rc, *needles)


@pytest.mark.parametrize("name", ["truncated.ckpt", "foreign.ckpt", "other_arch.ckpt", "pickle.ckpt",
                                  "torch_save.ckpt"])
def test_train_resume_from_bad_checkpoint(files: Path, tmp_path: Path, capfd: pytest.CaptureFixture,
                                          name: str) -> None:
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(files / name, run / "last.ckpt")
    one_line(capfd, call(train_main, ["--out", str(run), "--resume"]), "last.ckpt")
    assert not (files / MARKER).exists()


def _tiny_train(dataset: Path, run: Path, *extra: str) -> list[str]:
    return ["--data", str(dataset), "--out", str(run), "--preset", "flat-s", "--steps", "2", "--batch", "2",
            "--patch", "28", "--val-every", "0", "--no-progress", "--no-oidn", *extra]


def test_train_output_not_writable(dataset: Path, readonly_dir: Path, capfd: pytest.CaptureFixture) -> None:
    one_line(capfd, call(train_main, _tiny_train(dataset, readonly_dir / "run")), "readonly/run")


def test_train_disk_full_at_checkpoint(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture,
                                       disk_full: Callable[[int], None]) -> None:
    run = tmp_path / "run"
    disk_full(1)  # train_config.json fits, the first checkpoint does not
    one_line(capfd, call(train_main, _tiny_train(dataset, run, "--ckpt-every", "1")),
             "last.ckpt", "No space left on device")
    assert not (run / "last.ckpt").exists() and no_temporaries(run)


def test_train_checkpoint_writer_error_is_one_line(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The safetensors writer reports a full disk as its own exception type, not OSError."""
    def full(*args: object, **kwargs: object) -> None:
        raise safetensors.SafetensorError("Error while serializing: I/O error: No space left on device "
                                          "(os error 28)")

    monkeypatch.setattr(safetensors.torch, "save_file", full)
    run = tmp_path / "run"
    one_line(capfd, call(train_main, _tiny_train(dataset, run)), "last.ckpt", "No space left on device")
    assert not (run / "last.ckpt").exists() and no_temporaries(run)


# ----------------------------------------------------------------------------- generate-dataset
GEN = ["--res", "8", "--spp", "1", "--ref-spp", "2", "--families", "cornell_box", "--quiet"]


@pytest.mark.parametrize("argv, needles, code", [
    (["--scenes", "1", "--spp", "-1"], ["--spp", "-1"], 2),
    (["--scenes", "1", "--spp", "abc"], ["--spp", "abc"], 2),
    (["--scenes", "1", "--res", "0"], ["--res", "0"], 2),
    (["--scenes", "x"], ["--scenes", "x"], 2),
    (["--scenes", "-1", *GEN], ["--scenes must be >= 1"], 1),
    (["--scenes", "1", *GEN, "--ref-spp", "3"], ["reference spp must be even"], 1),
    (["--scenes", "1", *GEN, "--aovs", "xyz"], ["unknown AOV 'xyz'"], 1),
])
def test_generate_bad_arguments(tmp_path: Path, capfd: pytest.CaptureFixture, argv: list[str],
                                needles: list[str], code: int) -> None:
    rc = call(generate_main, [*argv, "--out", str(tmp_path / "ds")])
    assert rc == code
    one_line(capfd, rc, *needles)
    assert not (tmp_path / "ds" / "manifest.jsonl").exists()


def test_generate_bad_output_folder(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    one_line(capfd, call(generate_main, ["--scenes", "1", "--out", str(blocker), *GEN]),
             "a_file", "not a directory")
    one_line(capfd, call(generate_main, ["--scenes", "1", "--out", str(blocker / "sub"), *GEN]),
             "a_file/sub", "cannot write")
    # a folder of another configuration: one made by another tool, then one with other settings
    one_line(capfd, call(generate_main, ["--scenes", "1", "--out", str(dataset), *GEN]),
             "dataset.json", "unknown keys ['synthetic']")
    assert call(generate_main, ["--scenes", "1", "--out", str(tmp_path / "ds"), *GEN]) == 0
    capfd.readouterr()
    other = [*GEN[:4], "--ref-spp", "4", *GEN[6:]]
    one_line(capfd, call(generate_main, ["--scenes", "2", "--out", str(tmp_path / "ds"), *other]),
             "ds", "other settings (ref_spp: 2 vs 4)")
    assert [r["index"] for r in read_records(tmp_path / "ds")] == [0]
    (tmp_path / "ds" / "dataset.json").write_text("{")
    one_line(capfd, call(generate_main, ["--scenes", "1", "--out", str(tmp_path / "ds"), *GEN]),
             "ds/dataset.json", "not a dataset config")


def test_generate_not_writable(readonly_dir: Path, capfd: pytest.CaptureFixture) -> None:
    one_line(capfd, call(generate_main, ["--scenes", "1", "--out", str(readonly_dir / "ds"), *GEN]),
             "readonly/ds", "cannot write")


def test_generate_disk_full_then_rerun(tmp_path: Path, capfd: pytest.CaptureFixture,
                                       monkeypatch: pytest.MonkeyPatch, disk_full: Callable[[int], None]) -> None:
    ds = tmp_path / "ds"
    disk_full(1)  # dataset.json fits, no image does
    line = one_line(capfd, call(generate_main, ["--scenes", "2", "--out", str(ds), *GEN]),
                    "2 scene(s) failed", "No space left on device", "scene0000", stdout_empty=False)
    assert "re-run" in line
    assert read_records(ds) == [] and no_temporaries(ds)
    monkeypatch.undo()  # space again: the same command completes
    assert call(generate_main, ["--scenes", "2", "--out", str(ds), *GEN]) == 0
    assert [r["index"] for r in read_records(ds)] == [0, 1] and no_temporaries(ds)


# ----------------------------------------------------------------------------- security
def test_checkpoints_never_go_through_pickle(files: Path, tmp_path: Path, capfd: pytest.CaptureFixture) -> None:
    for name in ("pickle.ckpt", "torch_save.ckpt"):
        one_line(capfd, call(denoise_main, [str(files / "good.exr"), str(tmp_path / "o.exr"),
                                            "--model", str(files / name)]), name)
    assert not (files / MARKER).exists()
    sources = [p for pkg in ("pipeline", "model", "dataset_gen", "scenes") for p in (ROOT / pkg).rglob("*.py")]
    loaders = re.compile(r"(?<!safetensors\.)\btorch\.load\(|\bpickle\.loads?\(|^\s*import pickle|"
                         r"allow_pickle\s*=\s*True|\bjoblib\.load\(", re.MULTILINE)
    for path in sources:
        found = loaders.search(path.read_text())
        assert found is None, f"{path.relative_to(ROOT)} uses {found.group(0)!r}"


@pytest.mark.parametrize("doctype, message", [
    ("<!DOCTYPE s [<!ENTITY x SYSTEM 'file:///etc/passwd'>]>", "external entity"),
    ("<!DOCTYPE s [<!ENTITY a 'aaaaaaaaaa'><!ENTITY b '&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;'>"
     "<!ENTITY c '&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;'><!ENTITY d '&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;'>"
     "<!ENTITY e '&d;&d;&d;&d;&d;&d;&d;&d;&d;&d;'><!ENTITY f '&e;&e;&e;&e;&e;&e;&e;&e;&e;&e;'>"
     "<!ENTITY g '&f;&f;&f;&f;&f;&f;&f;&f;&f;&f;'><!ENTITY h '&g;&g;&g;&g;&g;&g;&g;&g;&g;&g;'>]>",
     "malformed XML"),
])
def test_scene_xml_entities_are_not_expanded(tmp_path: Path, doctype: str, message: str) -> None:
    """Scene files are only parsed (no external entities, no entity bombs), then loaded by Mitsuba."""
    entity = "&x;" if "SYSTEM" in doctype else "&h;"
    scene = tmp_path / "entities.xml"
    scene.write_text(f"<?xml version='1.0'?>{doctype}" + HEAD + f"<shape type='sphere' id='{entity}'/></scene>")
    with pytest.raises(SceneError, match=message) as exc:
        prepare_xml(scene)
    assert "root:" not in str(exc.value)  # /etc/passwd was not read into the scene


def test_manifest_cannot_point_outside_the_dataset(dataset: Path, tmp_path: Path) -> None:
    """Image paths come from the scene index alone; path-like fields in a manifest are ignored."""
    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    outside = tmp_path / "outside.exr"
    write_exr(outside, np.full((32, 32, 3), 1234.0, np.float32))
    rel = os.path.relpath(outside, data / "images")
    (data / "manifest.jsonl").write_text(json.dumps(
        {"index": 1, "split": "val", "spp": [4], "scene": rel, "path": str(outside), "image": rel,
         "reference": str(outside)}) + "\n")
    (image,) = load_val_images(data, read_manifest(data), aux=False)
    assert image.ref.max() < 1234.0 and image.noisy.max() < 1234.0
    np.testing.assert_array_equal(image.ref, read_exr(data / "images" / "scene0001_ref.hdr.exr").rgb)
    for bad in ('{"index": "../outside", "split": "val", "spp": [4]}', '{"index": -1, "split": "val", "spp": [4]}'):
        (data / "manifest.jsonl").write_text(bad + "\n")
        with pytest.raises(Exception, match="manifest.jsonl:1"):
            read_manifest(data)
