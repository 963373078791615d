"""Growing a trained DenseNet deeper: the grown model computes the source's output, then learns."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from imaging.errors import ConfigError
from imaging.hashing import file_sha256
from model.architectures import build_model
from model.checkpoint import load_model, save_checkpoint
from training.cli import main
from model.config import ModelConfig
from model.grow import grow_model
from training.synthetic import write_synthetic_dataset

SMALL = ModelConfig(layers=2, growth=4, init_features=8, transfer="pu")


def _trained_like(config: ModelConfig, seed: int) -> torch.nn.Module:
    """A model with random non-trivial weights and BN statistics (as if trained)."""
    torch.manual_seed(seed)
    model = build_model(config)
    with torch.no_grad():
        for name, tensor in model.state_dict().items():
            if tensor.is_floating_point():
                if name.endswith("running_var"):
                    tensor.uniform_(0.5, 2.0)
                else:
                    tensor.normal_(0.0, 0.3)
    return model.eval()


def test_grown_model_computes_the_source_output(rng) -> None:
    source = _trained_like(SMALL, seed=1)
    target = build_model(ModelConfig(layers=5, growth=4, init_features=8, transfer="pu"))
    before_new = target.body.layers[4].body[2].weight.clone()
    grow_model(target, source)
    target.eval()
    x = torch.from_numpy(rng.uniform(0, 1, (2, 3, 19, 23)).astype("float32"))
    with torch.no_grad():
        expected, got = source(x), target(x)
    assert torch.allclose(got, expected, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(source(x), x)  # the source is no identity: the check means something
    assert torch.equal(target.body.layers[4].body[2].weight, before_new)  # new layers keep He init
    assert float(target.tail[-1].weight.detach()[:, source.body.out_channels:].abs().max()) == 0.0


def test_new_layers_receive_gradient(rng) -> None:
    source = _trained_like(SMALL, seed=2)
    target = build_model(ModelConfig(layers=3, growth=4, init_features=8, transfer="pu"))
    grow_model(target, source)
    target.train()
    x = torch.from_numpy(rng.uniform(0, 1, (4, 3, 16, 16)).astype("float32"))
    target(x).square().mean().backward()
    assert float(target.tail[-1].weight.grad[:, source.body.out_channels:].abs().max()) > 0


def test_a_shrunk_model_is_the_source_without_its_last_layers(rng) -> None:
    source = _trained_like(ModelConfig(layers=5, growth=4, init_features=8, transfer="pu"), seed=4)
    target = build_model(SMALL)  # 2 layers
    grow_model(target, source)
    target.eval()
    x = torch.from_numpy(rng.uniform(0, 1, (2, 3, 19, 23)).astype("float32"))
    c_dst = target.body.out_channels
    with torch.no_grad():
        assert not torch.allclose(target(x), source(x), atol=1e-3)  # the dropped layers mattered
        source.tail[-1].weight[:, c_dst:] = 0.0  # what the source computes without them
        assert torch.allclose(target(x), source(x), rtol=1e-5, atol=1e-6)
    assert torch.equal(target.body.layers[1].body[2].weight, source.body.layers[1].body[2].weight)


@pytest.mark.parametrize("change", [{"growth": 5}, {"init_features": 9}, {"transfer": "log"},
                                    {"output": "direct"}, {"arch": "plaincnn"}])
def test_incompatible_models_are_refused(change: dict) -> None:
    source = build_model(SMALL)
    fields = {**SMALL.to_dict(), "layers": 4, **change}
    with pytest.raises(ConfigError, match="grow"):
        grow_model(build_model(ModelConfig(**fields)), source)
    if "arch" not in change:  # the same differences are refused for a shallower target
        with pytest.raises(ConfigError, match="shrink|grow"):
            grow_model(build_model(ModelConfig(**{**fields, "layers": 1})), _trained_like(
                ModelConfig(**{**SMALL.to_dict(), "layers": 3}), seed=5))


def test_train_init_from_starts_at_the_source(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    data = write_synthetic_dataset(tmp_path / "ds", scenes=2, res=(32, 32), spp=(4, 16), val_scenes=(1,))
    source = tmp_path / "source.ckpt"
    save_checkpoint(source, _trained_like(SMALL, seed=3), step=7)
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"model": {**SMALL.to_dict(), "layers": 4}}))
    run = tmp_path / "run"
    rc = main(["--data", str(data), "--out", str(run), "--config", str(config), "--init-from", str(source),
               "--steps", "2", "--batch", "4", "--patch", "28", "--lr", "1e-4", "--lr-cosine-steps", "0",
               "--lr-decay", "0.5", "--lr-decay-every", "1", "--lr-warmup", "2",
               "--val-every", "0", "--log-every", "1", "--converged-pairs", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    model, cfg, meta = load_model(run / "last.ckpt")
    assert cfg.layers == 4 and meta["train_config"]["init_from"] == str(source)
    assert meta["train_config"]["converged_pairs"] is True
    assert meta["extra"]["init_from"] == {"path": str(source), "sha256": file_sha256(source)}
    lrs = [json.loads(line)["lr"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert lrs == pytest.approx([1e-4 / 2, 5e-5])  # warm-up: step 0 at half the LR
    src = load_model(source)[0]
    # two small steps from the source: the copied head moved a little, not back to a random init
    delta = (model.head[0].weight - src.head[0].weight).detach().abs().max()
    assert 0 < float(delta) < 0.01


def test_train_init_from_an_incompatible_checkpoint_is_one_line(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture) -> None:
    data = write_synthetic_dataset(tmp_path / "ds", scenes=1, res=(32, 32), spp=(4,), val_scenes=())
    source = tmp_path / "source.ckpt"
    save_checkpoint(source, build_model(SMALL), step=1)
    rc = main(["--data", str(data), "--out", str(tmp_path / "run"), "--preset", "flat-s",
               "--init-from", str(source), "--steps", "1", "--patch", "28", "--val-every", "0", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and len(err.strip().splitlines()) == 1 and "cannot grow" in err and str(source) in err


def test_same_config_is_a_warm_start_for_any_architecture() -> None:
    import dataclasses

    from tests.test_model_unet import TINY, trained_like

    source = trained_like(dataclasses.replace(TINY, noise_input=True))
    target = build_model(source.config)
    grow_model(target, source)
    x = torch.rand(1, source.config.image_channels, 20, 24)
    with torch.no_grad():
        assert torch.equal(target.eval()(x), source(x))
    with pytest.raises(ConfigError, match="only densenet"):
        grow_model(build_model(dataclasses.replace(source.config, layers=2)), source)


@pytest.mark.parametrize("extra", [{"head": 4}, {"kernel": 5}], ids=["head", "predicted-filter"])
def test_a_multiscale_net_grows_a_head_or_filter_that_starts_at_zero_and_learns(extra: dict) -> None:
    import dataclasses

    from tests.test_model_unet import TINY, trained_like

    source = trained_like(TINY)
    target = build_model(dataclasses.replace(TINY, **extra))
    grow_model(target, source)
    x = torch.rand(1, 3, 20, 24)
    with torch.no_grad():
        assert torch.equal(target.eval()(x), source(x))  # the head's last conv / the coefficients' conv is zero
    target.train()(x).square().mean().backward()
    new = target.head[2] if "head" in extra else target.kernel
    assert new.weight.grad.abs().sum() > 0  # and it learns from the first step
    with pytest.raises(ConfigError, match="only densenet"):  # a head or filter is never dropped
        grow_model(build_model(TINY), target)
