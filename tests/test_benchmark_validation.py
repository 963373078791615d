"""benchmarks/validation.py: several checkpoints scored on the same held-out images."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from benchmarks.validation import build_parser, main, markdown, model_specs, score
from imaging.errors import DatasetError
from model.architectures import build_model
from model.checkpoint import save_checkpoint
from model.config import ModelConfig
from training.synthetic import write_synthetic_dataset

IDENTITY = ModelConfig(layers=2, growth=4, init_features=8, transfer="pu", output="residual")


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("val")
    first = write_synthetic_dataset(root / "a", scenes=4, res=(32, 24), spp=(2, 8), val_scenes=(1, 3))
    second = write_synthetic_dataset(root / "b", scenes=2, res=(32, 24), spp=(2, 8), val_scenes=(1,), seed=5)
    return first, second


def _checkpoint(path: Path, config: ModelConfig = IDENTITY, perturb: bool = False) -> Path:
    torch.manual_seed(0)
    model = build_model(config)  # residual: the last conv starts at zero, so the model is the identity
    if perturb:
        with torch.no_grad():
            for p in model.parameters():
                p.add_(0.05 * torch.randn_like(p))
    save_checkpoint(path, model, step=3)
    return path


def test_the_untrained_residual_model_scores_as_the_noisy_input_on_every_val_image(
        data: tuple[Path, Path], tmp_path: Path) -> None:
    models = {"identity": _checkpoint(tmp_path / "id.ckpt"), "other": _checkpoint(tmp_path / "o.ckpt", perturb=True)}
    result = score(models, [data[0]], max_scenes=None, oidn=False)
    assert result["images"] == 4 and result["scenes"] == 2 and result["spp"] == [2, 8]
    noisy = result["baselines"]["noisy"]
    for spp in ("2", "8"):
        assert result["models"]["identity"]["per_spp"][spp]["psnr"] == pytest.approx(noisy["per_spp"][spp]["psnr"],
                                                                                     abs=1e-3)
        assert result["models"]["other"]["per_spp"][spp]["psnr"] != pytest.approx(noisy["per_spp"][spp]["psnr"],
                                                                                  abs=1e-3)
    assert result["models"]["identity"]["psnr"] == pytest.approx(noisy["psnr"], abs=1e-3)
    assert result["baselines"]["oidn"]["psnr"] is None and result["models"]["identity"]["step"] == 3


def test_max_scenes_and_a_second_dataset_choose_the_images(data: tuple[Path, Path], tmp_path: Path) -> None:
    models = {"identity": _checkpoint(tmp_path / "id.ckpt")}
    assert score(models, [data[0]], max_scenes=2, oidn=False)["scenes"] == 1  # scene 3 is past the limit
    both = score(models, list(data), max_scenes=None, oidn=False)
    assert both["scenes"] == 3 and both["images"] == 6  # scene 1 of each dataset stays distinct


def test_models_with_albedo_normal_inputs_are_refused(data: tuple[Path, Path], tmp_path: Path) -> None:
    aux = _checkpoint(tmp_path / "aux.ckpt", ModelConfig(layers=2, growth=4, init_features=8, aux_inputs=True))
    with pytest.raises(ValueError, match="albedo/normal"):
        score({"aux": aux}, [data[0]], max_scenes=None, oidn=False)


def test_the_command_writes_json_and_table_and_fails_in_one_line(data: tuple[Path, Path], tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    ckpt = _checkpoint(tmp_path / "id.ckpt")
    assert main(["--data", str(data[0]), "--models", f"mine={ckpt},{ckpt}", "--no-oidn",
                 "--out", str(tmp_path / "r")]) == 0
    result = json.loads((tmp_path / "r" / "validation.json").read_text())
    assert result["command"].startswith("python -m benchmarks.validation --data") and result["images"] == 4
    assert list(result["models"]) == ["mine", str(ckpt)]
    table = (tmp_path / "r" / "validation.md").read_text().splitlines()
    assert table[2].startswith(f"| spp | noisy | mine | {ckpt} | OIDN | mine - OIDN |")
    assert table[-1].startswith("| **mean** |")
    capsys.readouterr()
    assert main(["--data", str(tmp_path / "missing"), "--models", str(ckpt)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "manifest.jsonl: not found" in err[0]


def test_the_default_models_are_the_default_entrys_checkpoints() -> None:
    specs = model_specs(build_parser().parse_args(["--data", "d"]).models)
    assert list(specs) == ["flat-s-allspp", "flat-s-lowspp", "unet-m-k5-lowspp", "unet-l-allspp", "unet-m-k5-lowspp-b"]
    assert all(path.is_file() for path in specs.values()), specs


def test_min_ceiling_keeps_the_scenes_whose_reference_is_clean_enough(tmp_path: Path) -> None:
    root = write_synthetic_dataset(tmp_path / "c", scenes=4, res=(32, 24), spp=(2, 8), val_scenes=(1, 3))
    manifest = root / "manifest.jsonl"
    ceilings = {1: 45.0, 3: 30.0}  # scene 0 and 2 are training scenes
    lines = [json.loads(line) for line in manifest.read_text().splitlines() if line.strip()]
    manifest.write_text("".join(json.dumps({**r, "ref_noise": {"psnr_ceiling_db": ceilings.get(r["index"], 50.0)}})
                                + "\n" for r in lines))
    models = {"identity": _checkpoint(tmp_path / "id.ckpt")}
    assert score(models, [root], max_scenes=None, oidn=False, min_ceiling_db=40)["scenes"] == 1
    assert score(models, [root], max_scenes=None, oidn=False, min_ceiling_db=30)["scenes"] == 2
    with pytest.raises(DatasetError, match="no 'val' scenes whose reference's noise ceiling is at least 46 dB"):
        score(models, [root], max_scenes=None, oidn=False, min_ceiling_db=46)


def test_the_train_split_scores_the_scenes_the_networks_trained_on(data: tuple[Path, Path], tmp_path: Path) -> None:
    models = {"identity": _checkpoint(tmp_path / "id.ckpt")}
    train = score(models, [data[0]], max_scenes=None, oidn=False, split="train")
    held_out = score(models, [data[0]], max_scenes=None, oidn=False)
    assert train["split"] == "train" and train["scenes"] == 2 and train["images"] == 4  # scenes 0 and 2
    assert train["baselines"]["noisy"]["psnr"] != pytest.approx(held_out["baselines"]["noisy"]["psnr"], abs=1e-3)
    assert "4 images of 2 training scenes" in markdown({**train, "command": "c", "date": "d"})
    with pytest.raises(ValueError, match="split must be one of val, train"):
        score(models, [data[0]], max_scenes=None, oidn=False, split="test")
