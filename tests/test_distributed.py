"""DDP training: 2 ranks match 1 process with micro_batch = batch/2; a lost rank; resume and the
hinted resume command; threads per rank; config rules."""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from imaging.errors import ConfigError
from model.checkpoint import read_checkpoint
from training.cli import build_parser, main, resume_command
from training.distributed import RankInfo, ShardSource, available_cpus, choose_threads, ddp_config, rank_from_env
from training.batches import BatchSource
from training.patches import PatchConfig, TrainingPair
from training.synthetic import write_synthetic_dataset
from training.train_config import TrainConfig

TINY = {"model": {"layers": 2, "growth": 4, "init_features": 8}, "patch": {"size": 28}, "batch": 8, "val_every": 0,
        "progress": False, "threads": 1}
# Measured (2-core x86, torch 2.13): weights and Adam moments bit-identical to the 1-process run
# (halving and a 2-term sum are exact either way), BatchNorm running statistics within 2.4e-7
# (merged in float64 vs updated chunk by chunk in float32). The tolerances leave room for other
# kernels and for more ranks, where the all-reduce sums in another order than the accumulation.
RTOL, ATOL = 1e-4, 1e-5
TIMEOUT_S = 900  # seconds a launch may take: ~20 s on an idle 2-core machine, minutes on a busy one


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("ds"), scenes=3, res=(32, 32), spp=(4, 16),
                                   val_scenes=(2,))


def _config(tmp_path: Path, **fields: object) -> str:
    path = tmp_path / "config.json"
    path.write_text(json.dumps({**TINY, **fields}))
    return str(path)


def _stop(proc: subprocess.Popen) -> None:
    """Stop a ``train --nproc`` launcher and any rank it left (ranks run in sessions of their own)."""
    import psutil

    if proc.poll() is not None:
        return
    try:
        ranks = psutil.Process(proc.pid).children(recursive=True)
    except psutil.NoSuchProcess:
        ranks = []
    proc.terminate()
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    for rank in ranks:
        with contextlib.suppress(psutil.NoSuchProcess):
            rank.kill()


def _start(*args: str, env: dict[str, str] | None = None,
           preexec_fn: Callable[[], None] | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "training.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, preexec_fn=preexec_fn)


def _train(*args: str, env: dict[str, str] | None = None,
           preexec_fn: Callable[[], None] | None = None) -> subprocess.CompletedProcess:
    """``train ARGS`` in a fresh process (as a user runs it), stdout/stderr captured."""
    proc = _start(*args, env=env, preexec_fn=preexec_fn)
    try:
        out, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        _stop(proc)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _assert_same_state(a: Path, b: Path) -> None:
    ca, cb = read_checkpoint(a), read_checkpoint(b)
    assert ca.header["step"] == cb.header["step"]
    names = [k for k in ca.tensors if k.startswith(("model/", "optim/"))]
    assert names and sorted(names) == sorted(k for k in cb.tensors if k.startswith(("model/", "optim/")))
    for name in names:  # weights, BatchNorm running statistics, Adam moments
        torch.testing.assert_close(cb.tensors[name], ca.tensors[name], rtol=RTOL, atol=ATOL, msg=name)


def _losses(run: Path) -> list[float]:
    return [json.loads(line)["loss"] for line in (run / "log.jsonl").read_text().splitlines()]


def test_ddp_config_records_ghost_batch_norm() -> None:
    config = TrainConfig(data="d", out="o", batch=8)
    assert ddp_config(config, 2, resume=False).micro_batch == 4
    assert ddp_config(dataclasses.replace(config, micro_batch=2), 2, resume=False).micro_batch == 2
    with pytest.raises(ConfigError, match="batch 8 does not split evenly over 3 ranks"):
        ddp_config(config, 3, resume=False)
    with pytest.raises(ConfigError, match="resume it in one process"):
        ddp_config(config, 2, resume=True)
    with pytest.raises(ConfigError, match="micro_batch 4 does not divide the per-rank batch 2"):
        ddp_config(dataclasses.replace(config, micro_batch=4), 4, resume=True)
    with pytest.raises(ConfigError, match="--compile"):
        ddp_config(dataclasses.replace(config, compile=True), 2, resume=False)


def test_rank_from_env() -> None:
    assert rank_from_env({}) is None
    env = {"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2"}
    assert rank_from_env(env) == RankInfo(1, 2, 1, 2) and not rank_from_env(env).primary
    with pytest.raises(ConfigError, match="bad torchrun environment"):
        rank_from_env({"RANK": "x", "WORLD_SIZE": "2"})


def test_shards_cut_the_single_process_batch(rng: np.random.Generator) -> None:
    pairs = [TrainingPair(rng.random((32, 32, 3), dtype=np.float32), rng.random((32, 32, 3), dtype=np.float32),
                         0, 4)]
    config = TrainConfig(data="d", out="o", batch=8, prefetch=False, patch=PatchConfig(size=28))
    whole = BatchSource(pairs, config).get(5)
    halves = [ShardSource(pairs, config, slice(r * 4, r * 4 + 4)).get(5) for r in (0, 1)]
    for i in (0, 1):  # noisy, ref
        assert torch.equal(torch.cat([h[i] for h in halves]), whole[i])


@pytest.mark.slow
def test_two_ranks_match_one_process_with_micro_batch(dataset: Path, tmp_path: Path) -> None:
    cfg = _config(tmp_path, ckpt_every=2, log_every=1)
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["--data", str(dataset), "--out", str(one), "--config", cfg, "--steps", "4",
                 "--micro-batch", "4"]) == 0
    done = _train("--data", str(dataset), "--out", str(two), "--config", cfg, "--steps", "4", "--nproc", "2")
    assert done.returncode == 0, done.stderr
    assert done.stdout.count("trained to step 4") == 1  # rank 0 alone reports
    _assert_same_state(one / "last.ckpt", two / "last.ckpt")
    assert read_checkpoint(two / "last.ckpt").header["train_config"]["micro_batch"] == 4
    assert len(_losses(two)) == 4  # rank 0 alone logs
    np.testing.assert_allclose(_losses(two), _losses(one), rtol=1e-5)
    # the DDP checkpoint resumes in one process exactly like the single-process run
    assert main(["--out", str(two), "--resume", "--steps", "6", "--no-progress"]) == 0
    assert main(["--out", str(one), "--resume", "--steps", "6", "--no-progress"]) == 0
    _assert_same_state(one / "last.ckpt", two / "last.ckpt")


def _rank_pid(launcher: int, rank: int, deadline: float) -> int:
    import psutil

    while time.time() < deadline:
        for child in psutil.Process(launcher).children(recursive=True):
            try:
                if child.environ().get("RANK") == str(rank):
                    return child.pid
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
        time.sleep(0.2)
    raise AssertionError(f"rank {rank} never started")


@pytest.mark.slow
def test_lost_rank_stops_the_job_and_resume_continues(dataset: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    cfg = _config(tmp_path, ckpt_every=2, log_every=2, micro_batch=4)
    proc = _start("--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "100000", "--nproc", "2")
    try:
        deadline = time.time() + TIMEOUT_S
        victim = _rank_pid(proc.pid, 1, deadline)
        while time.time() < deadline and not (run / "last.ckpt").exists():
            time.sleep(0.1)
        assert (run / "last.ckpt").exists(), "no checkpoint was written"
        os.kill(victim, signal.SIGKILL)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        _stop(proc)
    assert proc.returncode == 1
    last = err.strip().splitlines()[-1]
    assert last.startswith("train: error: rank 1 (pid ") and "was killed by SIGKILL; all 2 ranks were stopped" in last
    assert f"the last complete checkpoint is {run / 'last.ckpt'}" in last
    step = read_checkpoint(run / "last.ckpt").header["step"]  # intact, complete
    assert step >= 2 and step % 2 == 0 and f"(step {step})" in last
    done = _train("--out", str(run), "--resume", "--steps", str(step + 2), "--nproc", "2", "--no-progress")
    assert done.returncode == 0, done.stderr
    assert read_checkpoint(run / "last.ckpt").header["step"] == step + 2
    assert [r["step"] for r in map(json.loads, (run / "log.jsonl").read_text().splitlines())][-1] == step + 2


def test_cli_refuses_bad_ddp_settings(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cfg = _config(tmp_path, batch=6)
    assert main(["--data", str(dataset), "--out", str(tmp_path / "r"), "--config", cfg, "--nproc", "4"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["train: error: batch 6 does not split evenly over 4 ranks"]
    assert main(["--data", str(dataset), "--out", str(tmp_path / "r"), "--config", cfg, "--nproc", "0"]) == 1
    assert "--nproc must be >= 1" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the resume hint
def _run_hint(stderr_line: str) -> subprocess.CompletedProcess:
    """Run the command an error line ends with (``...; resume with: train ...``) exactly."""
    assert "resume with: " in stderr_line, stderr_line
    words = shlex.split(stderr_line.split("resume with: ", 1)[1])
    assert words[0] == "train", words
    return _train(*words[1:])


def test_resume_command_keeps_what_the_checkpoint_does_not_hold() -> None:
    parser = build_parser()
    args = parser.parse_args(["--data", "d", "--out", "runs/a b", "--config", "c.json", "--preset=flat-s", "--lr", "0.1",
                              "--steps", "40", "--batch", "64", "--micro-batch", "4", "--nproc=2", "--threads", "1",
                              "--no-progress", "--ckpt-every", "10"])
    hint = resume_command(parser, args)
    assert hint == ("train --out 'runs/a b' --resume --nproc 2 --data d --steps 40 --ckpt-every 10 --threads 1 "
                    "--no-progress")
    again = parser.parse_args(shlex.split(hint)[1:])
    assert again.resume and again.config is None and again.preset is None and again.batch is None
    assert resume_command(parser, again) == hint  # resuming a resumed run: the same command
    assert resume_command(parser, args, nproc=1).startswith("train --out 'runs/a b' --resume --data d ")


@pytest.mark.slow
def test_hinted_command_resumes_a_ddp_run_started_with_preset_and_config(dataset: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    cfg = _config(tmp_path, ckpt_every=2, log_every=2, micro_batch=4)
    proc = _start("--data", str(dataset), "--out", str(run), "--config", cfg, "--preset", "flat-s", "--steps", "200",
                  "--nproc", "2", "--no-progress")
    try:
        deadline = time.time() + TIMEOUT_S
        victim = _rank_pid(proc.pid, 1, deadline)
        while time.time() < deadline and not (run / "last.ckpt").exists():
            time.sleep(0.05)
        os.kill(victim, signal.SIGKILL)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        _stop(proc)
    assert proc.returncode == 1, err
    last = err.strip().splitlines()[-1]
    step = read_checkpoint(run / "last.ckpt").header["step"]
    assert step < 200 and last.endswith(f"resume with: train --out {run} --resume --nproc 2 --data {dataset} "
                                        "--steps 200 --no-progress"), last
    done = _run_hint(last)
    assert done.returncode == 0, done.stderr
    ckpt = read_checkpoint(run / "last.ckpt")
    assert ckpt.header["step"] == 200
    assert ckpt.header["train_config"]["model"]["layers"] == 10  # still the fast preset, not --config's model


@pytest.mark.slow
def test_hinted_command_resumes_an_interrupted_run(dataset: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    cfg = _config(tmp_path, ckpt_every=2, log_every=2)
    # SIGINT at its default in the child: a runner started in the background (nohup, `cmd &`)
    # ignores SIGINT, its children inherit that, and Python then never raises KeyboardInterrupt
    proc = _start("--data", str(dataset), "--out", str(run), "--config", cfg, "--preset", "flat-s", "--steps", "200",
                  preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.time() + TIMEOUT_S
        while time.time() < deadline and not (run / "last.ckpt").exists():
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        _stop(proc)
    assert proc.returncode == 130, err
    last = err.strip().splitlines()[-1]
    assert last == f"train: interrupted; resume with: train --out {run} --resume --data {dataset} --steps 200"
    done = _run_hint(last)
    assert done.returncode == 0, done.stderr
    assert read_checkpoint(run / "last.ckpt").header["step"] == 200


# ----------------------------------------------------------------------------- threads per rank
def test_threads_follow_the_affinity_mask_and_an_explicit_omp(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3}, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    assert available_cpus() == 1
    choice = choose_threads(None, 1, {})
    assert (choice.count, str(choice)) == (1, "1 torch thread each (1 core available to this process / 1 ranks)")
    assert choose_threads(None, 2, {"OMP_NUM_THREADS": "3"}).source == "OMP_NUM_THREADS=3 in the environment"
    assert choose_threads(None, 2, {"OMP_NUM_THREADS": "3"}).count == 3
    assert choose_threads(5, 2, {"OMP_NUM_THREADS": "3"}).count == 5  # --threads wins
    for bad in ("0", "x", ""):
        with pytest.raises(ConfigError, match="OMP_NUM_THREADS"):
            choose_threads(None, 2, {"OMP_NUM_THREADS": bad})


def _one_cpu() -> None:
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no affinity masks on this OS")
def test_launcher_reports_threads_from_affinity_and_keeps_an_explicit_omp(dataset: Path, tmp_path: Path) -> None:
    cfg = _config(tmp_path, threads=0)  # 0: not set
    base = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    args = ("--data", str(dataset), "--config", cfg, "--steps", "1", "--nproc", "2", "--no-progress")
    pinned = _train("--out", str(tmp_path / "pinned"), *args, env=base, preexec_fn=_one_cpu)  # like taskset -c 0
    assert pinned.returncode == 0, pinned.stderr
    assert "train: 2 ranks, 1 torch thread each (1 core available to this process / 2 ranks)" in pinned.stdout
    explicit = _train("--out", str(tmp_path / "explicit"), *args, env={**base, "OMP_NUM_THREADS": "3"})
    assert explicit.returncode == 0, explicit.stderr
    assert "train: 2 ranks, 3 torch threads each (OMP_NUM_THREADS=3 in the environment)" in explicit.stdout


def test_a_rank_frees_its_ddp_model_before_it_leaves_the_process_group(dataset: Path, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """train_distributed (one rank, in this process) releases the run and its DDP wrapper, whose reducer
    holds the process group, before it destroys the group: the group is not left to be torn down by
    the garbage collector at interpreter exit, where a rank once aborted after a complete run
    ("terminate called without an active exception")."""
    import socket
    import weakref

    import torch.distributed as dist

    import training.distributed as ddp

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    for key, value in {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "RANK": "0", "WORLD_SIZE": "1"}.items():
        monkeypatch.setenv(key, value)
    monkeypatch.setattr(ddp, "_stop_with_launcher", lambda: None)  # no parent-death signal for pytest
    wrapped: list[weakref.ref] = []
    network = ddp.RankRun.network
    monkeypatch.setattr(ddp.RankRun, "network", lambda self: wrapped.append(weakref.ref(w := network(self))) or w)
    config = TrainConfig.from_dict({**TINY, "data": str(dataset), "out": str(tmp_path / "run"), "steps": 2})
    result = ddp.train_distributed(config, RankInfo(rank=0, world=1))
    assert result.step == 2 and len(wrapped) == 1
    assert wrapped[0]() is None and not dist.is_initialized()
