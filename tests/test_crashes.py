"""kill -9 in the middle of ``train`` and ``render-and-denoise``: the re-run resumes or restarts cleanly,
no file is corrupt, nothing finished is lost. (``generate-dataset``: tests/test_dataset_gen.py.)

Each command runs as a subprocess that is killed with SIGKILL once it is part-way; then every file
it left is checked (checkpoints load with finite weights, EXRs and JSON parse, no half-written
temporaries under a final name) and the same command is run again.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from imaging.atomic_io import TMP_PREFIX
from imaging.exr import read_exr
from model.checkpoint import read_checkpoint
from training.cli import main as train_main
from training.synthetic import write_synthetic_dataset
from pipeline.cli import main as render_main
from tests.test_denoiser import write_tiny_checkpoint

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "scenes" / "examples" / "demo.xml"


def _kill_when(args: list[str], ready: Callable[[], bool], timeout: float = 600.0) -> bool:
    """Start ``args``, SIGKILL it as soon as ``ready()``; False if it ended before that."""
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + timeout
    try:
        while time.time() < deadline and proc.poll() is None:
            if ready():
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
                return True
            time.sleep(0.02)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return False


def _finite_weights(path: Path) -> bool:
    tensors = read_checkpoint(path).prefixed("model/")
    return all(bool(torch.isfinite(v).all()) for v in tensors.values() if v.is_floating_point())


def _checkpoint_step(path: Path) -> int:
    try:
        return int(read_checkpoint(path).header["step"])
    except Exception:  # not there yet
        return -1


@pytest.fixture
def keep_threads() -> Iterator[None]:
    """``train --threads 1`` sets torch's global thread count; give the next tests theirs back."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.mark.slow
def test_kill_9_during_train_then_resume_matches_a_straight_run(tmp_path: Path, keep_threads: None) -> None:
    data = write_synthetic_dataset(tmp_path / "ds", scenes=2, res=(32, 32), spp=(4,), val_scenes=())
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"model": {"layers": 2, "growth": 4, "init_features": 8}, "patch": {"size": 28}, "batch": 4,
                                  "log_every": 1, "ckpt_every": 1, "val_every": 0, "progress": False,
                                  "threads": 1, "prefetch": True}))
    killed, straight = tmp_path / "killed", tmp_path / "straight"
    common = ["--data", str(data), "--config", str(config), "--steps", "60"]
    assert _kill_when([sys.executable, "-m", "training.cli", "--out", str(killed), *common],
                      lambda: _checkpoint_step(killed / "last.ckpt") >= 5), "train ended before the kill"
    # What the kill left: a whole checkpoint (the one before, if it died mid-write) and a log.
    step = _checkpoint_step(killed / "last.ckpt")
    assert 5 <= step < 60 and _finite_weights(killed / "last.ckpt")
    assert not [p for p in killed.iterdir() if p.suffix == ".ckpt" and not p.name.startswith(TMP_PREFIX)
                and p.name not in ("last.ckpt",)]
    assert train_main(["--out", str(killed), "--resume", "--steps", "60", "--no-progress"]) == 0
    assert train_main(["--out", str(straight), *common]) == 0
    assert not list(killed.glob(f"{TMP_PREFIX}*"))
    a, b = read_checkpoint(straight / "last.ckpt"), read_checkpoint(killed / "last.ckpt")
    assert a.header["step"] == b.header["step"] == 60
    for key, value in a.prefixed("model/").items():  # nothing lost, nothing done twice
        torch.testing.assert_close(b.tensors[f"model/{key}"], value, rtol=1e-5, atol=1e-6)
    log = [json.loads(line) for line in (killed / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == list(range(1, 61))


def _outputs_are_whole(out: Path) -> None:
    """Every file under its final name is complete: EXRs read, JSON parses, PNGs have their end."""
    assert not list(out.glob(f"{TMP_PREFIX}*.json"))  # a temporary is never taken for a result
    for path in out.iterdir():
        if path.name.startswith(TMP_PREFIX):
            continue
        if path.suffix == ".exr":
            assert np.isfinite(read_exr(path).rgb).all(), path
        elif path.suffix == ".json":
            json.loads(path.read_text())
        elif path.suffix == ".png":
            assert path.read_bytes().endswith(b"IEND\xaeB`\x82"), path


@pytest.mark.slow
def test_kill_9_during_render_and_denoise_then_rerun(tmp_path: Path) -> None:
    ckpt = write_tiny_checkpoint(tmp_path / "tiny.ckpt")
    out = tmp_path / "out"
    base = [str(DEMO), "--model", str(ckpt), "--res", "48", "32", "--out", str(out), "--quiet", "--no-compare"]
    # A finished earlier run in the same folder, with other settings.
    assert render_main([*base, "--spp", "2"]) == 0
    assert json.loads((out / "metrics.json").read_text())["spp"] == 2
    args = [*base, "--spp", "16", "--reference-spp", "2048", "--overwrite"]  # into the earlier run's folder

    def started() -> bool:
        try:
            return json.loads((out / "config.json").read_text())["spp"] == 16
        except (OSError, ValueError):
            return False

    killed = _kill_when([sys.executable, "-m", "pipeline.cli", *args], started)
    assert killed, "render-and-denoise ended before the kill"
    time.sleep(0.05)
    _outputs_are_whole(out)
    # The earlier run's completion marker is gone: unfinished new outputs never pass for finished ones.
    assert not (out / "metrics.json").exists() and not (out / "report.html").exists()
    assert render_main(args) == 0
    _outputs_are_whole(out)
    assert not list(out.glob(f"{TMP_PREFIX}*"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["spp"] == 16 and set(metrics["quality"]) == {"noisy", "denoised"}
    assert read_exr(out / "noisy.exr").metadata["spp"] == 16
