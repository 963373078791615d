"""End-to-end training through the ``train`` CLI on a tiny synthetic dataset; resume; errors."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import torch

import training.step
from model.checkpoint import load_model, read_checkpoint
from training.cli import main
from training.synthetic import write_synthetic_dataset
from training.train_config import TrainConfig

TINY_MODEL = {"layers": 2, "growth": 4, "init_features": 8}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("ds"), scenes=2, res=(32, 32), spp=(4, 16),
                                   val_scenes=(1,))


def _config(tmp_path: Path, **fields: object) -> str:
    """A config file of ``fields``, with 28-px crops (the tiny datasets' images are 32 px, under the
    default crop) and the step schedule without warm-up (a few steps at full LR) unless they say."""
    path = tmp_path / f"config{len(list(tmp_path.glob('config*')))}.json"
    path.write_text(json.dumps({"patch": {"size": 28}, "lr_warmup": 0, "lr_cosine_steps": 0, **fields}))
    return str(path)


def _log(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]


def test_end_to_end_small_preset(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    run = tmp_path / "run"
    rc = main(["--data", str(dataset), "--out", str(run), "--preset", "flat-s", "--steps", "12", "--batch", "8",
               "--patch", "28", "--log-every", "3", "--val-every", "6", "--ckpt-every", "6", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    assert "trained to step 12" in capsys.readouterr().out
    for name in ("last.ckpt", "best.ckpt", "log.jsonl", "curves.png", "train_config.json"):
        assert (run / name).stat().st_size > 0, name
    assert (run / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    log = _log(run)
    assert [r["step"] for r in log if r["type"] == "train"] == [3, 6, 9, 12]
    schedule = TrainConfig(data="-", out="-", steps=12)  # the default: warm-up, then a cosine over the run
    assert all(r["loss"] > 0 and r["lr"] == pytest.approx(schedule.lr_at(r["step"] - 1))
               for r in log if r["type"] == "train")
    vals = [r for r in log if r["type"] == "val"]
    assert [r["step"] for r in vals] == [6, 12]
    per_spp = vals[-1]["per_spp"]
    assert set(per_spp) == {"4", "16"}
    for spp in ("4", "16"):
        assert set(per_spp[spp]["psnr"]) == {"ours", "noisy", "oidn"}
        assert per_spp[spp]["psnr"]["noisy"] is not None and per_spp[spp]["relmse"]["ours"] is not None
    assert per_spp["16"]["psnr"]["noisy"] > per_spp["4"]["psnr"]["noisy"]
    if importlib.util.find_spec("pyoidn") is not None:
        assert per_spp["4"]["psnr"]["oidn"] > per_spp["4"]["psnr"]["noisy"]
    model, config, meta = load_model(run / "last.ckpt")
    assert meta["step"] == 12 and config.layers == 10 and config.growth == 8
    assert meta["train_config"]["batch"] == 8 and meta["data_config"]["spp"] == [4, 16]
    saved = json.loads((run / "train_config.json").read_text())
    assert saved["model"] == config.to_dict() and saved["steps"] == 12


def test_log_loss_trains_and_is_recorded(dataset: Path, tmp_path: Path) -> None:
    # The log loss: log(patch loss + eps) < 0 for patches far better than 1; the run learns
    # (validation above the noisy input) and records the choice in its checkpoint.
    run = tmp_path / "run"
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, val_every=20, progress=False, log_every=10)
    assert main(["--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "40",
                 "--lr", "0.003", "--log-loss-eps", "0.001"]) == 0
    log = _log(run)
    assert all(r["loss"] < 0 for r in log if r["type"] == "train")
    val = [r for r in log if r["type"] == "val"][-1]
    assert val["per_spp"]["4"]["psnr"]["ours"] > val["per_spp"]["4"]["psnr"]["noisy"]
    assert read_checkpoint(run / "last.ckpt").header["train_config"]["log_loss_eps"] == 0.001


@pytest.mark.parametrize("flags, recorded, fall, beats_noisy", [
    # Zhao's / OIDN's mix (0.16 L1 + 0.84 (1 - MS-SSIM))
    (["--ms-ssim-weight", "0.84", "--gradient-weight", "0"], {"ms_ssim_weight": 0.84}, 0.5, True),
    # squared error in transfer space
    (["--loss-norm", "l2"], {"loss_norm": "l2", "loss_space": "transfer"}, 0.8, True),
    # squared error in the metrics' display space: at this length the tiny net does not yet beat the
    # noisy input there, where the gamma weighs the dark synthetic pixels most
    (["--loss-norm", "l2", "--loss-space", "display"], {"loss_norm": "l2", "loss_space": "display"}, 0.8, False),
], ids=["ms-ssim", "l2", "l2-display"])
def test_loss_variants_train_and_are_recorded(dataset: Path, tmp_path: Path, flags: list[str],
                                              recorded: dict, fall: float, beats_noisy: bool) -> None:
    # Each loss learns (its value falls by the factor ``fall``; validation above the noisy input where
    # stated) and the choice is recorded in the checkpoint.
    run = tmp_path / "run"
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, val_every=20, progress=False, log_every=10)
    assert main(["--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "40",
                 "--lr", "0.003", *flags]) == 0
    log = _log(run)
    losses = [r["loss"] for r in log if r["type"] == "train"]
    assert all(0 < loss < 1 for loss in losses) and losses[-1] < fall * losses[0]
    val = [r for r in log if r["type"] == "val"][-1]
    if beats_noisy:
        assert val["per_spp"]["4"]["psnr"]["ours"] > val["per_spp"]["4"]["psnr"]["noisy"]
    header = read_checkpoint(run / "last.ckpt").header["train_config"]
    assert {key: header[key] for key in recorded} == recorded


@pytest.mark.parametrize("field, value, message", [
    ("loss_norm", "l3", "loss_norm must be one of l1, l2"),
    ("loss_space", "linear", "loss_space must be one of transfer, display"),
])
def test_unknown_loss_choice_in_a_config_file(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture,
                                              field: str, value: str, message: str) -> None:
    cfg = _config(tmp_path, model=TINY_MODEL, **{field: value})
    assert main(["--data", str(dataset), "--out", str(tmp_path / "r"), "--config", cfg]) == 1
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err


def test_resume_continues_exactly(dataset: Path, tmp_path: Path) -> None:
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, lr=0.01, lr_warmup=0, lr_cosine_steps=0, lr_decay_every=3,
                  log_every=2, ckpt_every=2, val_every=0, progress=False)
    straight, split = tmp_path / "straight", tmp_path / "split"
    assert main(["--data", str(dataset), "--out", str(straight), "--config", cfg, "--steps", "8"]) == 0
    assert main(["--data", str(dataset), "--out", str(split), "--config", cfg, "--steps", "5"]) == 0
    assert read_checkpoint(split / "last.ckpt").header["step"] == 5
    assert main(["--out", str(split), "--resume", "--steps", "8", "--no-progress"]) == 0
    a, b = read_checkpoint(straight / "last.ckpt"), read_checkpoint(split / "last.ckpt")
    assert a.header["step"] == b.header["step"] == 8
    for key, value in a.prefixed("model/").items():
        torch.testing.assert_close(b.tensors[f"model/{key}"], value, rtol=1e-6, atol=1e-7)
    for key, value in a.prefixed("optim/").items():
        torch.testing.assert_close(b.tensors[f"optim/{key}"], value, rtol=1e-6, atol=1e-7)
    log_a, log_b = _log(straight), _log(split)
    assert [r["step"] for r in log_b] == [2, 4, 5, 6, 8]  # step 5 = end of the first part
    assert [r["lr"] for r in log_b if r["step"] in (6, 8)] == pytest.approx([0.01 * 0.9, 0.01 * 0.9 ** 2])
    assert log_b[-1]["loss"] == pytest.approx(log_a[-1]["loss"], rel=1e-5)


def test_resume_drops_log_lines_after_checkpoint(dataset: Path, tmp_path: Path) -> None:
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, log_every=1, val_every=0, progress=False)
    run = tmp_path / "run"
    assert main(["--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "2"]) == 0
    with open(run / "log.jsonl", "a") as fh:  # written after the checkpoint, then the process died
        fh.write(json.dumps({"type": "train", "step": 3, "loss": 123.0}) + "\n")
    assert main(["--out", str(run), "--resume", "--steps", "4", "--no-progress"]) == 0
    log = _log(run)
    assert [r["step"] for r in log] == [1, 2, 3, 4] and all(r["loss"] != 123.0 for r in log)


def test_nan_losses_stop_training_without_poisoning(dataset: Path, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture) -> None:
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, val_every=0, ckpt_every=2, progress=False)
    run = tmp_path / "run"
    assert main(["--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "2"]) == 0
    before = read_checkpoint(run / "last.ckpt").prefixed("model/")
    real = training.step.denoising_loss
    monkeypatch.setattr(training.step, "denoising_loss", lambda out, ref, *a: real(out, ref, *a) * float("nan"))
    rc = main(["--out", str(run), "--resume", "--steps", "20", "--max-bad-steps", "3", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1
    assert "NaN/Inf for 3 steps in a row" in err[0] and "Traceback" not in err[0]
    after = read_checkpoint(run / "last.ckpt")  # saved at step 4, after two skipped steps
    assert after.header["step"] == 4 and after.header["extra"]["skipped_total"] == 2
    for key, value in before.items():  # skipped steps changed neither weights nor BatchNorm statistics
        torch.testing.assert_close(after.tensors[f"model/{key}"], value, rtol=0, atol=0)


@pytest.mark.parametrize("argv, message", [
    (["--data", "{missing}", "--out", "{tmp}/r"], "dataset.json: not found"),
    (["--out", "{tmp}/r"], "--data is required for a new run"),
    (["--out", "{tmp}/r", "--resume"], "last.ckpt: checkpoint not found"),
    (["--out", "{tmp}/r", "--resume", "--preset", "flat-s"], "--preset cannot be combined with --resume"),
    (["--out", "{tmp}/r", "--resume", "--detail-crops", "0.5"], "--detail-crops cannot be combined with --resume"),
    (["--data", "{data}", "--out", "{tmp}/r", "--detail-crops", "2"], "patch detail must be in [0, 1]"),
    (["--data", "{data}", "--out", "{data}/dataset.json"], "dataset.json: exists and is not a folder"),
    (["--data", "{data}", "--out", "{tmp}/r", "--steps", "0"], "steps must be a positive integer"),
    (["--data", "{data}", "--out", "{tmp}/r", "--log-loss-eps", "-1"], "log_loss_eps must be in [0, 1]"),
    (["--data", "{data}", "--out", "{tmp}/r", "--ms-ssim-weight", "2"], "ms_ssim_weight must be in [0, 1]"),
    (["--data", "{data}", "--out", "{tmp}/r", "--ms-ssim-weight", "0.5", "--patch", "8"],
     "needs patches of at least 11 px"),
    (["--data", "{data}", "--out", "{tmp}/r", "--config", "{tmp}/nope.json"], "nope.json: cannot read config"),
])
def test_cli_errors_one_line(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture,
                             argv: list[str], message: str) -> None:
    args = [a.format(tmp=tmp_path, data=dataset, missing=tmp_path / "missing") for a in argv]
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("train: error: ") and message in err[0], err


def test_cli_refuses_to_overwrite_a_run(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, val_every=0, progress=False)
    run = tmp_path / "run"
    assert main(["--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "1"]) == 0
    capsys.readouterr()
    assert main(["--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "1"]) == 1
    assert "already holds a run" in capsys.readouterr().err


def test_cli_usage_error_exit_2(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--out", "x", "--preset", "giant"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown model preset 'giant' (valid: flat-s, flat-m, flat-l, paper, unet-s" in err[0]


def test_aux_model_end_to_end(tmp_path: Path) -> None:
    data = write_synthetic_dataset(tmp_path / "ds", scenes=2, res=(32, 32), spp=(4,), val_scenes=(1,), aovs=True)
    cfg = _config(tmp_path, model={**TINY_MODEL, "aux_inputs": True, "transfer": "pu", "output": "direct"},
                  batch=4, log_every=2, val_every=2, progress=False)
    assert main(["--data", str(data), "--out", str(tmp_path / "run"), "--config", cfg, "--steps", "2"]) == 0
    _, config, _ = load_model(tmp_path / "run" / "best.ckpt")
    assert config.aux_inputs and config.in_channels == 15 and config.transfer == "pu"


@pytest.fixture(scope="module")
def camera_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("dsc"), scenes=2, res=(32, 32), spp=(4,), val_scenes=(1,),
                                   aovs=True, cameras=True)


@pytest.mark.parametrize("mode", ["stem", "noskip", "levels", "kernel"])
def test_each_aux_arm_trains_from_an_rgb_net_with_camera_normals_and_a_prefilter(
        camera_dataset: Path, tmp_path: Path, mode: str, capsys: pytest.CaptureFixture) -> None:
    """``--aux --aux-mode M --aux-normals camera --aux-prefilter bilateral --init-from RGB``: the run
    starts from the RGB net (its weights in place), trains and validates, its checkpoint records
    the options; a resume may not change them."""
    from model.architectures import build_model
    from model.checkpoint import save_checkpoint
    from model.config import ModelConfig

    rgb = ModelConfig(arch="dense_unet", levels=2, layers=1, growth=4, init_features=8, transfer="pu", kernel=3)
    torch.manual_seed(0)
    source = tmp_path / "rgb.ckpt"
    save_checkpoint(source, build_model(rgb), step=5)
    run = tmp_path / "run"
    rc = main(["--data", str(camera_dataset), "--out", str(run), "--arch", "dense_unet", "--levels", "2", "--layers",
               "1", "--growth", "4", "--width", "8", "--kernel", "3", "--transfer", "pu", "--aux", "--aux-mode", mode,
               "--aux-normals", "camera", "--aux-prefilter", "bilateral", "--init-from", str(source), "--steps", "2",
               "--batch", "4", "--patch", "32", "--lr", "1e-4", "--val-every", "2", "--no-oidn", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    model, config, meta = load_model(run / "best.ckpt")
    assert (config.aux_inputs, config.aux_mode, config.aux_normals, config.aux_prefilter) == \
        (True, mode, "camera", "bilateral")
    assert meta["train_config"]["model"]["aux_mode"] == mode and meta["train_config"]["init_from"] == str(source)
    assert [r["psnr"] is not None for r in _log(run) if r["type"] == "val"] == [True]
    capsys.readouterr()
    assert main(["--out", str(run), "--resume", "--aux-mode", "stem", "--steps", "3"]) == 1
    assert "--aux-mode cannot be combined with --resume" in capsys.readouterr().err


def test_resume_refuses_a_different_dataset(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, val_every=0, progress=False)
    run = tmp_path / "run"
    assert main(["--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "1"]) == 0
    other = write_synthetic_dataset(tmp_path / "other", scenes=1, spp=(8,), val_scenes=())
    capsys.readouterr()
    assert main(["--out", str(run), "--resume", "--data", str(other), "--steps", "2"]) == 1
    assert "dataset differs from the one this run was trained on (spp: [4, 16] -> [8])" in capsys.readouterr().err


def test_resume_refuses_a_dataset_that_grew_or_shrank(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The checkpoint records how many train/val scenes each dataset gave; a resumed run that would
    see other scenes stops (it would no longer be the run its command describes)."""
    data = write_synthetic_dataset(tmp_path / "ds", scenes=2, res=(32, 32), spp=(4,), val_scenes=(1,))
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, val_every=0, progress=False)
    run = tmp_path / "run"
    assert main(["--data", str(data), "--out", str(run), "--config", cfg, "--steps", "1"]) == 0
    assert read_checkpoint(run / "last.ckpt").header["data_config"]["scenes"] == {"train": 1, "val": 1}
    write_synthetic_dataset(data, scenes=4, res=(32, 32), spp=(4,), val_scenes=(1,))  # two more train scenes
    capsys.readouterr()
    assert main(["--out", str(run), "--resume", "--steps", "2"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "trained on 1 train / 1 val scenes, the dataset now gives 3 / 1" in err[0]


def test_aux_model_refuses_dataset_without_aux(dataset: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture) -> None:
    assert main(["--data", str(dataset), "--out", str(tmp_path / "run"), "--preset", "flat-s", "--aux"]) == 1
    assert "the model needs albedo/normal" in capsys.readouterr().err


def test_config_precedence_defaults_file_flags(tmp_path: Path) -> None:
    from training.cli import build_parser, config_from_args
    cfg = _config(tmp_path, model={"preset": "flat-s", "transfer": "pu"}, batch=16, lr=0.002)
    args = build_parser().parse_args(["--data", "d", "--out", "o", "--config", cfg, "--lr", "0.005",
                                      "--output", "direct", "--patch", "24"])
    config, resume = config_from_args(args)
    assert not resume and config.batch == 16 and config.lr == 0.005 and config.patch.size == 24
    assert (config.model.layers, config.model.growth, config.model.transfer, config.model.output) == \
        (10, 8, "pu", "direct")
    assert config.lr_decay == 0.9 and config.lr_decay_every == 10_000 and config.grad_clip is None


def test_cpu_budget_stops_the_run_validated_and_saved(tmp_path: Path, dataset: Path) -> None:
    """--cpu-minutes: the run stops once its optimisation used that much CPU, with a last log
    line, a validation and last.ckpt at the step it reached; resuming with a larger budget goes on."""
    from model.checkpoint import read_checkpoint

    out = tmp_path / "run"
    code = main(["--data", str(dataset), "--out", str(out), "--preset", "flat-s", "--steps", "100000",
                     "--batch", "2", "--patch", "16", "--cpu-minutes", "0.02", "--val-every", "1000",
                     "--log-every", "1000", "--no-progress", "--no-oidn", "--threads", "1"])
    assert code == 0
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    trains = [r for r in log if r["type"] == "train"]
    step = read_checkpoint(out / "last.ckpt").header["step"]
    assert 0 < step < 100000 and trains[-1]["step"] == step
    assert trains[-1]["cpu_s"] >= 0.02 * 60 and trains[-1]["cpu_s"] < 0.02 * 60 + 30
    assert log[-1]["type"] == "val" and log[-1]["step"] == step
    assert main(["--out", str(out), "--resume", "--cpu-minutes", "0.04", "--no-progress"]) == 0
    assert read_checkpoint(out / "last.ckpt").header["step"] > step


@pytest.fixture(scope="module")
def noisy_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("dsv"), scenes=3, res=(64, 64), spp=(2, 8),
                                   val_scenes=(2,), variance=True)


def test_end_to_end_multiscale_with_noise_input(noisy_dataset: Path, tmp_path: Path) -> None:
    """A tiny dense U-Net with noise input and a full-resolution head trains, validates with the
    variance images, resumes, and its checkpoint rebuilds the model; a noise model refuses data
    without variance."""
    run = tmp_path / "run"
    flags = ["--arch", "dense_unet", "--levels", "2", "--layers", "1", "--growth", "4", "--width", "8", "--head", "4",
             "--transfer", "pu", "--noise-input", "--patch", "32", "--batch", "4", "--lr", "1e-3",
             "--lr-cosine-steps", "8", "--log-every", "4", "--val-every", "4", "--no-progress", "--no-oidn"]
    assert main(["--data", str(noisy_dataset), "--out", str(run), "--steps", "4", *flags]) == 0
    assert main(["--out", str(run), "--resume", "--steps", "8", "--no-progress"]) == 0
    model, config, meta = load_model(run / "last.ckpt")
    assert config.arch == "dense_unet" and config.noise_input and config.head == 4 and meta["step"] == 8
    vals = [r for r in _log(run) if r["type"] == "val"]
    assert [r["step"] for r in vals] == [4, 8] and all(r["psnr"] is not None for r in vals)
    lrs = [r["lr"] for r in _log(run) if r["type"] == "train"]
    assert lrs[0] > lrs[1]  # cosine decay
    plain = write_synthetic_dataset(tmp_path / "plain", scenes=2, res=(64, 64), spp=(2,), val_scenes=())
    assert main(["--data", str(plain), "--out", str(tmp_path / "r2"), "--steps", "1", *flags]) == 1


def test_extra_data_trains_and_validates_on_both_datasets(noisy_dataset: Path, tmp_path: Path) -> None:
    """--extra-data: the pairs and validation images of both datasets, scene ids kept apart, the
    extra dataset's config recorded in the checkpoint; resuming keeps it."""
    other = write_synthetic_dataset(tmp_path / "other", scenes=2, res=(64, 64), spp=(4,), val_scenes=(0,),
                                    variance=True, seed=5)
    run = tmp_path / "run"
    flags = ["--arch", "dense_unet", "--levels", "1", "--layers", "1", "--growth", "4", "--width", "8",
             "--transfer", "pu", "--noise-input", "--patch", "32", "--batch", "2", "--log-every", "1",
             "--val-every", "2", "--no-progress", "--no-oidn"]
    assert main(["--data", str(noisy_dataset), "--extra-data", str(other), "--out", str(run), "--steps", "2",
                 *flags]) == 0
    vals = [r for r in _log(run) if r["type"] == "val"]
    assert vals[-1]["images"] == 2 + 1  # scene 2 of the first (spp 2, 8), scene 0 of the other (spp 4)
    meta = read_checkpoint(run / "last.ckpt").header
    assert meta["train_config"]["extra_data"] == [str(other)]
    assert meta["data_config"]["extra_data"][0]["path"] == str(other)
    assert meta["data_config"]["extra_data"][0]["scenes"] == {"train": 1, "val": 1}
    assert main(["--out", str(run), "--resume", "--steps", "3", "--no-progress"]) == 0
    from training.train import DATASET_ID_STRIDE, _Run
    from training.train_config import TrainConfig
    pairs = _Run(TrainConfig.from_dict({**meta["train_config"], "out": str(tmp_path / "r3")}), False).pairs
    assert {p.scene for p in pairs} == {0, 1, DATASET_ID_STRIDE + 1}


@pytest.mark.parametrize("limit, recorded, kept_spp, errors", [
    (["--max-spp", "4"], {"max_spp": 4, "min_spp": 0}, 2,  # scene 2 at 2 spp, not at 8
     [(["--max-spp", "1"], "no render at <= 1 spp")]),
    (["--min-spp", "4"], {"min_spp": 4, "max_spp": 0}, 8,
     [(["--min-spp", "16"], "no render at >= 16 spp"), (["--min-spp", "8", "--max-spp", "4"], "must not exceed max_spp")]),
])
def test_spp_limits_train_and_validate_on_the_renders_within(noisy_dataset: Path, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture, limit: list[str],
                                                             recorded: dict[str, int], kept_spp: int,
                                                             errors: list[tuple[list[str], str]]) -> None:
    """--max-spp / --min-spp: the pairs and validation images outside the limit are left out
    (converged pairs kept when asked); the choice is recorded; a limit that leaves no render, or
    --min-spp above --max-spp, is a one-line error."""
    run = tmp_path / "run"
    flags = ["--arch", "dense_unet", "--levels", "1", "--layers", "1", "--growth", "4", "--width", "8",
             "--transfer", "pu", "--patch", "32", "--batch", "2", "--log-every", "1", "--val-every", "2",
             "--no-progress", "--no-oidn", "--converged-pairs"]
    assert main(["--data", str(noisy_dataset), "--out", str(run), "--steps", "2", *limit, *flags]) == 0
    vals = [r for r in _log(run) if r["type"] == "val"]
    assert vals[-1]["images"] == 1 and set(vals[-1]["per_spp"]) == {str(kept_spp)}
    meta = read_checkpoint(run / "last.ckpt").header
    assert {k: meta["train_config"][k] for k in recorded} == recorded
    from training.dataset import CONVERGED_SPP
    from training.train import _Run
    from training.train_config import TrainConfig
    pairs = _Run(TrainConfig.from_dict({**meta["train_config"], "out": str(tmp_path / "r2")}), False).pairs
    assert sorted((p.scene, p.spp) for p in pairs) == [(0, CONVERGED_SPP), (0, kept_spp), (1, CONVERGED_SPP),
                                                        (1, kept_spp)]
    for bad, message in errors:
        capsys.readouterr()
        assert main(["--data", str(noisy_dataset), "--out", str(tmp_path / "r3"), "--steps", "1", *bad, *flags]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err


def test_a_dataset_without_a_validation_scene_validates_on_its_training_scenes(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Too few scenes to hold one out: the run validates on its training scenes, says so in one
    line at the start, and prints each validation's score (beside the noisy input's)."""
    data = write_synthetic_dataset(tmp_path / "ds", scenes=2, res=(32, 32), spp=(4, 16), val_scenes=())
    run = tmp_path / "r"
    assert main(["--data", str(data), "--out", str(run), "--patch", "28", "--steps", "2", "--batch", "2",
                 "--val-every", "1", "--preset", "flat-s", "--no-oidn", "--no-progress"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == ("train: validating every 1 steps on the 2 training scenes (4 images): the data holds no "
                      "scene out (split 'val'), so the score measures the fit to these scenes, not to others")
    vals = [r for r in _log(run) if r["type"] == "val"]
    assert [(r["step"], r["images"]) for r in vals] == [(1, 4), (2, 4)]
    for record, line in zip(vals, out[1:3]):
        assert line.startswith(f"train: step {record['step']}: validation PSNR {record['psnr']:.2f} dB on the "
                               f"training scenes (4 images; noisy {record['noisy_psnr']:.2f}, ")
    assert read_checkpoint(run / "last.ckpt").header["data_config"]["scenes"] == {"train": 2, "val": 0}
    assert (run / "best.ckpt").exists()


def test_a_crop_larger_than_the_images_is_refused_before_the_run_exists(
        dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Crops larger than the data's images: one line naming the largest crop that fits (a multiple
    of the network's alignment), and no run folder."""
    small = write_synthetic_dataset(tmp_path / "d30", scenes=2, res=(36, 30), spp=(4,), val_scenes=(1,))
    for flags, fits in ((["--preset", "flat-s"], 32), (["--arch", "dense_unet", "--levels", "1"], 28)):
        run = tmp_path / "runs" / "r"
        data = dataset if fits == 32 else small
        assert main(["--data", str(data), "--out", str(run), "--patch", "40", *flags]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        size = "32x32" if fits == 32 else "36x30"
        assert err == [f"train: error: {data}: its {size} images are smaller than the 40px training crops; give "
                       f"--patch {fits} or less"]
        assert not (tmp_path / "runs").exists()


def test_a_failed_start_leaves_nothing_behind(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A start that fails (bad data before the folder is made, or in its first step after) removes
    what it made: its files and the folders it created, never a folder that was there."""
    cfg = _config(tmp_path, model=TINY_MODEL, batch=2, val_every=0, progress=False)
    assert main(["--data", str(tmp_path / "missing"), "--out", str(tmp_path / "a" / "b"), "--config", cfg]) == 1
    assert "dataset.json: not found" in capsys.readouterr().err and not (tmp_path / "a").exists()
    flat = _config(tmp_path, model=TINY_MODEL, batch=2, val_every=0, progress=False,
                   patch={"size": 28, "min_unique": 10**6})  # no crop passes: the first step fails
    assert main(["--data", str(dataset), "--out", str(tmp_path / "a" / "b"), "--config", flat]) == 1
    assert "the training images are almost flat" in capsys.readouterr().err and not (tmp_path / "a").exists()
    kept = tmp_path / "mine"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    assert main(["--data", str(dataset), "--out", str(kept), "--config", flat]) == 1
    assert [p.name for p in kept.iterdir()] == ["notes.txt"] and (kept / "notes.txt").read_text() == "mine"


def test_ctrl_c_before_the_first_checkpoint_leaves_nothing_behind(dataset: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch,
                                                                   capsys: pytest.CaptureFixture) -> None:
    import training.train as train_module

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "train_step", interrupted)
    cfg = _config(tmp_path, model=TINY_MODEL, batch=2, val_every=0, progress=False)
    assert main(["--data", str(dataset), "--out", str(tmp_path / "a" / "b"), "--config", cfg]) == 130
    assert "resume with" not in capsys.readouterr().err and not (tmp_path / "a").exists()


def test_train_out_never_replaces_what_is_there(dataset: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture) -> None:
    """``train --out`` (a new run) refuses a file, a run's files without its last.ckpt, a recipe
    run and a dataset, each left as it was; a run with a last.ckpt is refused too (--resume
    continues it: test_cli_refuses_to_overwrite_a_run)."""
    cfg = _config(tmp_path, model=TINY_MODEL, batch=2, val_every=0, progress=False)
    cases = {"file": None, "partial": {"log.jsonl": "{}\n", "train_config.json": "{}"},
             "recipe": {"recipe.json": "{}"}, "data": {"dataset.json": "{}"}}
    messages = {"file": "exists and is not a folder",
                "partial": "holds a run's files without a last.ckpt to resume from (log.jsonl, train_config.json)",
                "recipe": "holds a recipe run (recipe.json), not a run to add to; choose another --out",
                "data": "holds a dataset (dataset.json), not a run to add to"}
    for name, files in cases.items():
        out = tmp_path / name
        if files is None:
            out.write_text("a file")
        else:
            out.mkdir()
            for file, text in files.items():
                (out / file).write_text(text)
        before = out.read_bytes() if files is None else {p.name: p.read_bytes() for p in out.iterdir()}
        assert main(["--data", str(dataset), "--out", str(out), "--config", cfg, "--steps", "1"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and messages[name] in err[0], err
        after = out.read_bytes() if files is None else {p.name: p.read_bytes() for p in out.iterdir()}
        assert after == before, name


def test_the_progress_bar_runs_to_the_limit_that_stops_the_run(monkeypatch: pytest.MonkeyPatch) -> None:
    """Under --minutes (or --cpu-minutes) the bar's total is the step the run is expected to stop
    at, from the pace of its steps so far, and its description names the limit; without a limit
    that comes first it stays the run's steps."""
    import types

    import training.train as train_module

    clock = [100.0]
    monkeypatch.setattr(train_module, "time", types.SimpleNamespace(monotonic=lambda: clock[0]))
    cpu = [0.0]
    config = types.SimpleNamespace(steps=20_000, cpu_budget_s=0.0)
    run = types.SimpleNamespace(step=0, config=config, cpu_used=lambda: cpu[0])

    class Bar:
        total, description, refreshed = 20_000, None, 0

        def set_description(self, desc: str, refresh: bool = True) -> None:
            self.description = desc

        def refresh(self) -> None:
            self.refreshed += 1

    bar = Bar()
    forecast = train_module._Forecast(run, deadline=100.0 + 120.0)  # --minutes 2
    run.step, clock[0], cpu[0] = 10, 110.0, 20.0  # 10 steps in 10 s
    forecast.show(bar)
    assert (bar.total, bar.description, bar.refreshed) == (120, "time limit", 1)
    run.step, clock[0] = 12, 110.5  # within a second of the last revision: left as it is
    forecast.show(bar)
    assert bar.total == 120
    run.step, clock[0] = 40, 160.0  # slower now: 40 steps in 60 s, 60 s left
    forecast.show(bar)
    assert bar.total == 80
    run.step, clock[0] = 80, 160.2  # the run reached the total and goes on: revised at once
    forecast.show(bar)
    assert bar.total == 160  # ceil(59.8 s left / 0.7525 s a step) = 80 more
    run.step = 150  # stopped by the limit here: the bar ends at the step reached
    forecast.finish(bar)
    assert bar.total == 150
    config.cpu_budget_s = 60.0  # 20 CPU-seconds left at 0.5 a step: the CPU budget comes first
    run.step, cpu[0] = 40, 30.0
    forecast = train_module._Forecast(run, deadline=None)
    run.step, clock[0], cpu[0] = 60, 170.0, 40.0
    forecast.show(bar)
    assert (bar.total, bar.description) == (60 + 40, "cpu budget")
    config.cpu_budget_s, config.steps = 0.0, 70  # no limit before the steps: the run's steps
    run.step, clock[0] = 61, 172.0
    forecast.show(bar)
    assert (bar.total, bar.description) == (70, "")


def test_out_is_created_with_its_parents_and_minutes_stop_a_run(dataset: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture) -> None:
    """--out in a fresh clone (runs/x, runs/ missing) is made like generate-dataset's; --minutes
    stops the sitting saved, and --resume goes on."""
    run = tmp_path / "runs" / "deeper" / "x"
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, val_every=0, progress=False)
    assert main(["--data", str(dataset), "--out", str(run), "--config", cfg, "--steps", "1000", "--minutes",
                 "0.000001"]) == 0
    assert "stopped by the time (resume with: train --out" in capsys.readouterr().out
    step = read_checkpoint(run / "last.ckpt").header["step"]
    assert 0 <= step < 1000
    assert main(["--out", str(run), "--resume", "--steps", str(step + 2), "--no-progress"]) == 0
    assert read_checkpoint(run / "last.ckpt").header["step"] == step + 2


def test_cuda_where_there_is_none_is_one_line(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    import model.device

    monkeypatch.setattr(model.device, "cuda_available", lambda: False)
    assert main(["--data", str(dataset), "--out", str(tmp_path / "r"), "--device", "cuda"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "torch sees no CUDA device here" in err[0]


def test_the_card_records_a_gaussian_dataset(tmp_path: Path) -> None:
    """A run on data rendered with another pixel filter records it in every checkpoint's card;
    datasets of different filters are not mixed."""
    from model.checkpoint import checkpoint_meta, pixel_filter

    gaussian = write_synthetic_dataset(tmp_path / "g", scenes=2, res=(32, 32), spp=(4,), val_scenes=(1,))
    config = json.loads((gaussian / "dataset.json").read_text())
    (gaussian / "dataset.json").write_text(json.dumps({**config, "filter": {"type": "gaussian", "stddev": 0.5}}))
    cfg = _config(tmp_path, model=TINY_MODEL, batch=2, val_every=1, progress=False, oidn=False)
    assert main(["--data", str(gaussian), "--out", str(tmp_path / "r"), "--config", cfg, "--steps", "1"]) == 0
    header = read_checkpoint(tmp_path / "r" / "best.ckpt").header
    assert pixel_filter(header) == {"type": "gaussian", "stddev": 0.5}
    assert checkpoint_meta(header)["hours"]["cpu"] > 0 and "recipe" not in checkpoint_meta(header)
    box = write_synthetic_dataset(tmp_path / "b", scenes=2, res=(32, 32), spp=(4,), val_scenes=(1,))
    assert main(["--data", str(gaussian), "--extra-data", str(box), "--out", str(tmp_path / "r2"), "--config", cfg,
                 "--steps", "1"]) == 1


def test_batches_from_worker_processes_train_the_same_run(dataset: Path, tmp_path: Path) -> None:
    """--workers N (what a GPU run uses): the batches come from forked processes, and the run is the
    one the prefetch thread gives."""
    cfg = _config(tmp_path, model=TINY_MODEL, batch=4, val_every=0, progress=False, threads=1)
    for name, workers in (("thread", "0"), ("processes", "2")):
        assert main(["--data", str(dataset), "--out", str(tmp_path / name), "--config", cfg, "--steps", "6",
                     "--workers", workers]) == 0
    a, b = (read_checkpoint(tmp_path / name / "last.ckpt") for name in ("thread", "processes"))
    assert b.header["train_config"]["workers"] == 2
    for key, value in a.prefixed("model/").items():
        torch.testing.assert_close(b.tensors[f"model/{key}"], value, rtol=0, atol=0)
