"""Checkpoints: save -> load gives identical outputs; bad files give clear errors; no pickle."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import safetensors.torch
import torch

from imaging.errors import CheckpointError
from model.architectures import build_model
from model.checkpoint import (code_version, compact_optimizer, load_model, read_checkpoint, restore_optimizer,
                              replace_meta, restore_rng, save_checkpoint, strip_optimizer)
from model.config import ModelConfig
from training.loss import denoising_loss

CONFIG = ModelConfig(layers=3, growth=4, init_features=8, transfer="pu", output="direct")


def _trained(steps: int = 2) -> tuple[torch.nn.Module, torch.optim.Adam]:
    torch.manual_seed(0)
    model = build_model(CONFIG)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    x, y = torch.rand(4, 3, 12, 12), torch.rand(4, 3, 12, 12)
    for _ in range(steps):
        opt.zero_grad()
        denoising_loss(model(x), y).backward()
        opt.step()
    return model, opt


def test_save_load_identical_outputs(tmp_path: Path) -> None:
    model, opt = _trained()
    path = tmp_path / "m.ckpt"
    save_checkpoint(path, model, step=7, optimizer=opt, train_config={"lr": 0.01},
                    data_config={"spp": [4, 16]}, extra={"best_psnr": 30.5})
    loaded, config, meta = load_model(path)
    assert config == CONFIG and loaded.config == CONFIG
    assert meta["step"] == 7 and meta["train_config"] == {"lr": 0.01} and meta["data_config"] == {"spp": [4, 16]}
    assert meta["extra"]["best_psnr"] == 30.5 and not loaded.training
    x = torch.rand(2, 3, 16, 16)
    model.eval()
    with torch.no_grad():
        torch.testing.assert_close(loaded(x), model(x), rtol=0, atol=0)


def test_optimizer_and_rng_restored(tmp_path: Path) -> None:
    model, opt = _trained()
    torch.manual_seed(123)
    path = tmp_path / "m.ckpt"
    save_checkpoint(path, model, step=2, optimizer=opt)
    expected_draw = torch.rand(3)
    ckpt = read_checkpoint(path)
    fresh = torch.optim.Adam(build_model(CONFIG).parameters(), lr=0.5)
    restore_optimizer(ckpt, fresh)
    saved, restored = opt.state_dict()["state"], fresh.state_dict()["state"]
    assert sorted(saved) == sorted(restored)
    for index, state in saved.items():
        for key in ("exp_avg", "exp_avg_sq", "step"):
            torch.testing.assert_close(restored[index][key], state[key], rtol=0, atol=0)
    assert fresh.param_groups[0]["lr"] == pytest.approx(1e-3)
    torch.manual_seed(999)
    restore_rng(ckpt)
    torch.testing.assert_close(torch.rand(3), expected_draw, rtol=0, atol=0)


def test_strip_optimizer_keeps_weights_and_header(tmp_path: Path) -> None:
    """A shipped copy: every model and RNG tensor and the header as written (code version, configs,
    step, extra), the optimiser's tensors and header entry gone; a missing source is a clear error."""
    model, opt = _trained()
    src, dst = tmp_path / "last.ckpt", tmp_path / "shipped.ckpt"
    save_checkpoint(src, model, step=5, optimizer=opt, train_config={"lr": 0.01}, extra={"best_psnr": 31.0})
    strip_optimizer(src, dst)
    before, after = read_checkpoint(src), read_checkpoint(dst)
    assert before.prefixed("optim/") and not after.prefixed("optim/")
    assert set(after.tensors) == {k for k in before.tensors if not k.startswith("optim/")}
    for key, tensor in after.tensors.items():
        torch.testing.assert_close(tensor, before.tensors[key], rtol=0, atol=0)
    assert after.header == {**before.header, "optimizer": None} and before.header["optimizer"] is not None
    assert dst.stat().st_size < src.stat().st_size
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        strip_optimizer(tmp_path / "nope.ckpt", tmp_path / "out.ckpt")
    assert not (tmp_path / "out.ckpt").exists()


def test_replace_meta_gives_a_file_its_card_record_and_keeps_its_weights(tmp_path: Path) -> None:
    """Every tensor bit for bit and every other header field as written; only ``meta`` is new."""
    model, _ = _trained()
    path = tmp_path / "old.ckpt"
    save_checkpoint(path, model, step=7, train_config={"lr": 0.01}, extra={"cpu_s": 60.0})
    before = read_checkpoint(path)
    meta = {"recipe": {"name": "r", "sha256": "0" * 64, "stage": "main"}, "hours": {"cpu": 0.5, "gpu": 0.0}}
    replace_meta(path, meta)
    after = read_checkpoint(path)
    assert set(after.tensors) == set(before.tensors)
    for key, tensor in after.tensors.items():
        assert tensor.dtype == before.tensors[key].dtype and torch.equal(tensor, before.tensors[key]), key
    assert after.header == {**before.header, "meta": meta} and "meta" not in before.header
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        replace_meta(tmp_path / "nope.ckpt", meta)


def _continue(model: torch.nn.Module, opt: torch.optim.Adam, steps: int) -> None:
    torch.manual_seed(5)
    x, y = torch.rand(4, 3, 12, 12), torch.rand(4, 3, 12, 12)
    for _ in range(steps):
        opt.zero_grad()
        denoising_loss(model(x), y).backward()
        opt.step()


def test_compact_optimizer_resumes_close_to_the_exact_state(tmp_path: Path) -> None:
    """Moments in bfloat16: restored as float32 within bfloat16's rounding (2^-8 relative), step,
    weights, RNG and the rest of the header unchanged, the file smaller; three more steps from it
    land within a small fraction of what those steps moved the weights. A file without optimiser
    state is a clear error and writes nothing."""
    model, opt = _trained(3)
    src, dst = tmp_path / "last.ckpt", tmp_path / "compact.ckpt"
    save_checkpoint(src, model, step=3, optimizer=opt, train_config={"lr": 1e-3}, extra={"best_psnr": 30.0})
    compact_optimizer(src, dst)
    before, after = read_checkpoint(src), read_checkpoint(dst)
    assert after.header == {**before.header, "optimizer": {**before.header["optimizer"], "moments": "bfloat16"}}
    assert dst.stat().st_size < src.stat().st_size
    for key, tensor in before.tensors.items():
        if key.startswith("optim/") and not key.endswith("/step"):
            assert after.tensors[key].dtype == torch.bfloat16
        else:
            torch.testing.assert_close(after.tensors[key], tensor, rtol=0, atol=0)
    exact, rounded = build_model(CONFIG), build_model(CONFIG)
    exact.load_state_dict(before.prefixed("model/"))
    rounded.load_state_dict(after.prefixed("model/"))
    exact_opt = torch.optim.Adam(exact.parameters(), lr=1e-3)
    rounded_opt = torch.optim.Adam(rounded.parameters(), lr=1e-3)
    restore_optimizer(before, exact_opt)
    restore_optimizer(after, rounded_opt)
    for index, state in exact_opt.state_dict()["state"].items():
        restored = rounded_opt.state_dict()["state"][index]
        assert restored["exp_avg"].dtype == torch.float32
        torch.testing.assert_close(restored["step"], state["step"], rtol=0, atol=0)
        for key in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(restored[key], state[key], rtol=2 ** -8, atol=1e-30)
    start = [p.detach().clone() for p in exact.parameters()]
    _continue(exact, exact_opt, 3)
    _continue(rounded, rounded_opt, 3)
    with torch.no_grad():
        moved = sum(float((p - s).abs().sum()) for p, s in zip(exact.parameters(), start))
        apart = sum(float((p - q).abs().sum()) for p, q in zip(exact.parameters(), rounded.parameters()))
    assert moved > 0 and apart < 0.01 * moved, (apart, moved)
    strip_optimizer(src, tmp_path / "bare.ckpt")
    with pytest.raises(CheckpointError, match="no optimiser state"):
        compact_optimizer(tmp_path / "bare.ckpt", tmp_path / "out.ckpt")
    assert not (tmp_path / "out.ckpt").exists()


def test_file_is_plain_safetensors(tmp_path: Path) -> None:
    model, _ = _trained(0)
    save_checkpoint(tmp_path / "m.ckpt", model, step=0)
    tensors = safetensors.torch.load_file(str(tmp_path / "m.ckpt"))  # no pickle anywhere
    assert any(k.startswith("model/") for k in tensors) and "rng/torch" in tensors


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        load_model(tmp_path / "nope.ckpt")


def test_truncated(tmp_path: Path) -> None:
    model, opt = _trained(1)
    path = tmp_path / "m.ckpt"
    save_checkpoint(path, model, step=1, optimizer=opt)
    data = path.read_bytes()
    for cut in (10, len(data) // 2, len(data) - 1):
        path.write_bytes(data[:cut])
        with pytest.raises(CheckpointError, match="truncated or not a safetensors checkpoint"):
            load_model(path)


def test_foreign_files(tmp_path: Path) -> None:
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"PK\x03\x04 this is a zip, or a pickle, or anything else" * 4)
    with pytest.raises(CheckpointError, match="truncated or not a safetensors checkpoint"):
        load_model(junk)
    other = tmp_path / "other.safetensors"
    safetensors.torch.save_file({"w": torch.zeros(3)}, str(other), metadata={"framework": "x"})
    with pytest.raises(CheckpointError, match="not a denoiser checkpoint"):
        load_model(other)


def _rewrite(path: Path, header_changes: dict | None = None, drop: str | None = None,
             replace: dict | None = None) -> None:
    with open(path, "rb") as fh:
        data = fh.read()
    tensors = safetensors.torch.load(data)
    ckpt = read_checkpoint(path)
    header = {**ckpt.header, **(header_changes or {})}
    if drop:
        tensors.pop(drop)
    tensors.update(replace or {})
    safetensors.torch.save_file(tensors, str(path), metadata={"denoiser_checkpoint": json.dumps(header)})


def test_config_weight_mismatch(tmp_path: Path) -> None:
    model, _ = _trained(0)
    path = tmp_path / "m.ckpt"
    save_checkpoint(path, model, step=0)
    _rewrite(path, header_changes={"model_config": {**CONFIG.to_dict(), "growth": 5}})
    with pytest.raises(CheckpointError, match="has shape .* the model config needs"):
        load_model(path)
    save_checkpoint(path, model, step=0)
    _rewrite(path, header_changes={"model_config": {**CONFIG.to_dict(), "layers": 4}})
    with pytest.raises(CheckpointError, match="weights do not match the model config"):
        load_model(path)
    save_checkpoint(path, model, step=0)
    _rewrite(path, header_changes={"model_config": {**CONFIG.to_dict(), "arch": "transformer"}})
    with pytest.raises(CheckpointError, match="bad model config in checkpoint"):
        load_model(path)
    save_checkpoint(path, model, step=0)
    _rewrite(path, header_changes={"format_version": 99})
    with pytest.raises(CheckpointError, match="format version 99 is not supported"):
        load_model(path)


def test_refuses_nan_weights(tmp_path: Path) -> None:
    model, _ = _trained(0)
    with torch.no_grad():
        model.head[0].weight[0, 0, 0, 0] = float("nan")
    with pytest.raises(CheckpointError, match="refusing to save non-finite weights"):
        save_checkpoint(tmp_path / "m.ckpt", model, step=0)
    assert not (tmp_path / "m.ckpt").exists() and list(tmp_path.iterdir()) == []


def test_restored_adam_moments_follow_channels_last_params(tmp_path: Path) -> None:
    model, opt = _trained()
    save_checkpoint(tmp_path / "m.ckpt", model, step=2, optimizer=opt)
    fresh = build_model(CONFIG).to(memory_format=torch.channels_last)
    fused = torch.optim.Adam(fresh.parameters(), lr=1e-3, fused=True)
    restore_optimizer(read_checkpoint(tmp_path / "m.ckpt"), fused)
    for param in fresh.parameters():
        assert fused.state[param]["exp_avg"].stride() == param.stride()


def test_a_checkpoint_records_the_code_that_wrote_it(tmp_path: Path) -> None:
    path = tmp_path / "m.ckpt"
    save_checkpoint(path, build_model(ModelConfig(layers=2, growth=4, init_features=8)), step=3)
    code = read_checkpoint(path).header["code"]
    assert code == code_version() and len(code["model_sources_sha256"]) == 64
    assert code["torch"] == torch.__version__
    assert code["git_commit"] is None or len(code["git_commit"]) == 40



SHIPPED = sorted((Path(__file__).resolve().parents[1] / "model" / "weights").glob("*.ckpt"))


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_checkpoints_load_and_carry_their_training_record(path: Path) -> None:
    # Every shipped checkpoint rebuilds its model from the file alone, with finite weights, and its
    # run's log and training config are kept in experiments/training/NAME/; one trained on low spp
    # records its range.
    model, config, meta = load_model(path)
    assert all(torch.isfinite(p).all() for p in model.parameters())
    record = path.parents[2] / "experiments" / "training" / path.stem
    assert (record / "log.jsonl").is_file()
    train_config = json.loads((record / "train_config.json").read_text())
    if path.stem.endswith("-lowspp"):
        assert meta["train_config"]["max_spp"] == train_config["max_spp"] == 16


def test_the_card_meta_and_the_pixel_filter_it_records(tmp_path: Path) -> None:
    """``meta`` is written as given; the pixel filter comes from it, else from the data's record
    (a name or a dict), else it is a box (every checkpoint made before the record existed)."""
    from model.checkpoint import checkpoint_meta, pixel_filter

    path = tmp_path / "m.ckpt"
    gaussian = {"type": "gaussian", "stddev": 0.5}
    save_checkpoint(path, build_model(ModelConfig(layers=2, growth=4, init_features=8)), step=1,
                    meta={"pixel_filter": gaussian, "hours": {"cpu": 1.5, "gpu": 0.0}})
    header = read_checkpoint(path).header
    assert checkpoint_meta(header)["hours"] == {"cpu": 1.5, "gpu": 0.0} and pixel_filter(header) == gaussian
    assert pixel_filter({"data_config": {"filter": "box"}}) == {"type": "box"}
    assert pixel_filter({"data_config": {"filter": {"type": "tent"}}}) == {"type": "tent"}
    assert pixel_filter({}) == {"type": "box"} and checkpoint_meta({}) == {}


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    model, opt = _trained(1)
    save_checkpoint(tmp_path / "m.ckpt", model, step=1, optimizer=opt)
    return tmp_path / "m.ckpt"


@pytest.mark.parametrize("changes, message", [
    ({"growth": 4096}, r"weights do not match the model config \(it implies at least 1,811,939,328 parameters, "
                       r"7,247,757,312 bytes; the file has [0-9,]+ bytes\)"),
    ({"layers": 4096}, r"weights do not match the model config \(it implies at least 49,152 weight tensors, the "
                       r"file holds 48\)"),
    ({"init_features": 9}, r"weight head.0.weight has shape \(8, 9, 7, 7\) F32, the model config needs "
                           r"\(9, 9, 7, 7\) F32"),
    ({"arch": "dense_unet", "levels": 6, "layers": 4000}, r"weights do not match the model config \(it implies at "
                                                          r"least 624,000 weight tensors"),
])
def test_headers_that_lie_about_the_network_are_refused_before_it_is_built(
        saved: Path, monkeypatch: pytest.MonkeyPatch, changes: dict, message: str) -> None:
    """The header's config is checked against the stored tensors' names, shapes and dtypes (counted
    or built on the meta device), never by building the network it describes."""
    import model.checkpoint

    _rewrite(saved, header_changes={"model_config": {**CONFIG.to_dict(), **changes}})
    monkeypatch.setattr(model.checkpoint, "build_model", lambda config: pytest.fail("network built"))
    with pytest.raises(CheckpointError, match=f"m.ckpt: {message}"):
        load_model(saved)


@pytest.mark.parametrize("replace, message", [
    ({"model/head.0.weight": torch.zeros(8, 9, 7, 7, dtype=torch.float64)},
     r"weight head.0.weight has shape \(8, 9, 7, 7\) F64, the model config needs \(8, 9, 7, 7\) F32"),
    ({"model/extra.weight": torch.zeros(3)}, r"weights do not match the model config \(missing: -; unexpected: "
                                             r"extra.weight\)"),
    ({"junk": torch.zeros(2**10)}, "unexpected tensor 'junk'"),
    ({"optim/999/exp_avg": torch.zeros(3)}, "unexpected tensor 'optim/999/exp_avg'"),
    ({"optim/0/exp_avg": torch.zeros(2**16)}, r"optimiser tensor optim/0/exp_avg has shape \(65536,\) F32, its "
                                              r"parameter \(8, 9, 7, 7\)"),
    ({"optim/0/secret": torch.zeros(8, 9, 7, 7)}, "optimiser tensor optim/0/secret has shape"),
    ({"rng/torch": torch.zeros(2, 2)}, r"tensor rng/torch has shape \(2, 2\) F32, expected 1-D U8"),
    ({"rng/torch": torch.zeros(2, 2, dtype=torch.uint8)}, r"tensor rng/torch has shape \(2, 2\) U8"),
    ({"rng/torch": torch.zeros(5, dtype=torch.float32)}, r"tensor rng/torch has shape \(5,\) F32"),
    ({"optim/24/exp_avg": torch.zeros(3)}, "unexpected tensor 'optim/24/exp_avg'"),  # indices 0..23: 24 parameters
])
def test_tensors_beside_the_weights_are_checked(saved: Path, replace: dict, message: str) -> None:
    _rewrite(saved, replace=replace)
    with pytest.raises(CheckpointError, match=f"m.ckpt: {message}"):
        read_checkpoint(saved)


@pytest.mark.parametrize("text, message", [
    ("[" * 100000 + "]" * 100000, "corrupt checkpoint header"),
    ('{"format": "mc-densenet-denoiser-checkpoint", "format_version": 1, "step": 0}', "bad model config in checkpoint"),
    ('{"format": "mc-densenet-denoiser-checkpoint", "format_version": 1}', r"corrupt checkpoint header \(step None\)"),
    ("not json", "corrupt checkpoint header"),
    ("[1, 2]", "corrupt checkpoint header"),
])
def test_header_json_that_breaks_parsers(saved: Path, text: str, message: str) -> None:
    tensors = safetensors.torch.load_file(str(saved))
    safetensors.torch.save_file(tensors, str(saved), metadata={"denoiser_checkpoint": text})
    with pytest.raises(CheckpointError, match=f"m.ckpt: {message}"):
        read_checkpoint(saved)


@pytest.mark.parametrize("changes, message", [
    ({"step": -1}, "step -1"), ({"step": "7"}, "step '7'"), ({"train_config": 1.5}, "train_config of type float"),
    ({"extra": []}, "extra of type list"), ({"optimizer": {"type": "Adam", "param_groups": [1]}},
                                             "optimizer param_groups not a list of objects"),
    ({"train_config": {"max_spp": [8]}}, r"train_config max_spp \[8\]"),
])
def test_header_fields_of_the_wrong_type(saved: Path, changes: dict, message: str) -> None:
    """What inference and training read from the header has the type the writer gives it."""
    _rewrite(saved, header_changes=changes)
    with pytest.raises(CheckpointError, match=f"m.ckpt: corrupt checkpoint header \\({message}"):
        read_checkpoint(saved)


def test_there_are_as_many_parameters_as_the_optimiser_indices_assume() -> None:
    assert len(list(build_model(CONFIG).parameters())) == 24


@pytest.mark.parametrize("group, message", [
    ({"params": ["a"]}, "corrupt optimiser parameter group"),
    ({"params": [0], "betas": "x"}, "corrupt optimiser parameter group"),
    ({"params": [0], "betas": [0.9, "x"]}, "corrupt optimiser parameter group"),
    ({"params": [0], "lr": "fast"}, "corrupt optimiser parameter group"),
])
def test_optimiser_groups_of_the_wrong_shape(saved: Path, group: dict, message: str) -> None:
    """Adam's hyper-parameters are numbers, flags or null (a string would fail only at the next step)."""
    ckpt = read_checkpoint(saved)
    groups = [{**ckpt.header["optimizer"]["param_groups"][0], **group}]
    _rewrite(saved, header_changes={"optimizer": {**ckpt.header["optimizer"], "param_groups": groups}})
    fresh = torch.optim.Adam(build_model(CONFIG).parameters())
    with pytest.raises(CheckpointError, match=f"m.ckpt: {message}"):
        restore_optimizer(read_checkpoint(saved), fresh)


def test_no_optimiser_state_to_resume_from(saved: Path, tmp_path: Path) -> None:
    strip_optimizer(saved, tmp_path / "stripped.ckpt")
    fresh = torch.optim.Adam(build_model(CONFIG).parameters())
    with pytest.raises(CheckpointError, match="stripped.ckpt: has no Adam optimiser state to resume from"):
        restore_optimizer(read_checkpoint(tmp_path / "stripped.ckpt"), fresh)
