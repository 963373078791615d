"""benchmarks/inference.py's model entries: registry names, presets with random weights, specs, spp."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.inference import _checkpoint, _macs, _preset_overrides, call, denoiser_macs, ratios
from imaging.errors import ConfigError
from denoise.denoiser import Denoiser
from model.config import PRESETS

UNET = next(name for name, config in PRESETS.items() if config.multiscale)  # an architecture preset


def test_registry_names_and_files_are_passed_on_presets_get_random_weights(tmp_path: Path) -> None:
    assert _checkpoint("high", tmp_path) == "high" and not list(tmp_path.iterdir())  # real weights
    path = _checkpoint(UNET, tmp_path)
    assert path == str(tmp_path / f"{UNET}.ckpt") and Path(path).is_file()
    den = Denoiser(f"{path}+{path}:-16")
    out = den.denoise_array(np.ones((8, 8, 3), np.float32), spp=4)
    assert out.models == (UNET, UNET)


def test_a_preset_with_field_overrides_is_the_candidate_it_names(tmp_path: Path) -> None:
    path = _checkpoint("unet-s:kernel=5:growth=6", tmp_path)
    config = Denoiser(path).members[0].config
    assert (config.kernel, config.growth, config.layers) == (5, 6, PRESETS["unet-s"].layers)
    assert _preset_overrides("high") is None and _preset_overrides("unet-s") == ("unet-s", {})
    for bad in ("unet-s:kernel=five", "unet-s:kernel", "unet-s:no_such_field=1"):
        with pytest.raises(ConfigError):
            _checkpoint(bad, tmp_path)


def test_out_names_the_json_written(tmp_path: Path, monkeypatch) -> None:
    """``--out`` keeps the committed results file as it is (a quick timing must not overwrite it)."""
    import benchmarks.inference as inference

    monkeypatch.setattr(inference, "oidn_available", lambda: False)
    out = tmp_path / "timing.json"
    before = inference.RESULTS.read_bytes() if inference.RESULTS.exists() else None
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["inference", "--quick", "--models", "unet-s:kernel=5", "--spp", "4",
                                      "--out", str(out)])
    inference.main()
    assert json.loads(out.read_text())["models"] and "unet-s:kernel=5" in out.read_text()
    assert (inference.RESULTS.read_bytes() if inference.RESULTS.exists() else None) == before
    for bad in (tmp_path, tmp_path / "no" / "such.json"):  # refused before anything is measured
        monkeypatch.setattr(sys, "argv", ["inference", "--quick", "--out", str(bad)])
        with pytest.raises(SystemExit, match="give a file in an existing folder"):
            inference.main()


def test_macs_count_only_the_networks_that_run_at_the_spp(tmp_path: Path) -> None:
    path = _checkpoint(UNET, tmp_path)
    both = Denoiser(f"{path}+{path}:17-")
    one = _macs(both.members[0].config)
    assert denoiser_macs(both, 4) == one and denoiser_macs(both, 64) == 2 * one


def test_a_call_at_unknown_spp_has_no_variance_and_ratios_are_per_process_medians(tmp_path: Path) -> None:
    den = Denoiser("fast")
    img = np.full((16, 16, 3), 0.5, np.float32)
    assert call(den, img, img * 0.01, "unknown").guard_weight is None
    assert call(den, img, img * 0.01, 4).guard_weight is not None
    sizes = {"8x8": {"oidn": {"process_s_per_mp": [1.0, 2.0, 4.0]},
                     "fast|4": {"process_s_per_mp": [0.5, 1.0, 8.0]}}}
    assert ratios(sizes) == {"8x8": {"fast": {"4": 0.5}}}


def test_each_timed_call_follows_an_untimed_call_of_the_same_variant(monkeypatch) -> None:
    """Whatever ran before (OIDN's threads and buffers) must not be billed to the next variant."""
    import benchmarks.inference as inference

    log: list[str] = []
    clock = iter(range(1000))
    monkeypatch.setattr(inference, "call", lambda den, img, var, spp: log.append(f"{den}|{spp}"))
    monkeypatch.setattr(inference, "oidn_available", lambda: True)
    monkeypatch.setattr(inference, "oidn_denoise", lambda img: log.append("oidn"))
    monkeypatch.setattr(inference.time, "perf_counter", lambda: log.append("clock") or float(next(clock)))
    result = inference.measure_size(8, 8, {"a": "A", "b": "B"}, repeat=2, spps=[4])
    clocks = [i for i, entry in enumerate(log) if entry == "clock"]
    starts = clocks[::2]  # each timing reads the clock before and after its call
    assert all(log[i + 2] == "clock" for i in starts)
    assert sorted(log[i + 1] for i in starts) == ["A|4"] * 2 + ["B|4"] * 2 + ["oidn"] * 2  # the timed calls
    assert all(log[i - 1] == log[i + 1] for i in starts)  # each right after an untimed call of its own
    assert set(result) == {"a|4", "b|4", "oidn"} and all(len(r["runs"]) == 2 for r in result.values())
