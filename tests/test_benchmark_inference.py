"""benchmarks/inference.py's model entries: presets, files, ensembles and the shipped default."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.inference import SPP, _checkpoint, _macs, denoiser_macs
from denoise.denoiser import DEFAULT_MODEL, WEIGHTS_DIR, Denoiser, ensemble_members, shipped_members
from denoise.ensemble import SEPARATOR


def test_default_is_the_shipped_ensemble_with_its_spp_ranges(tmp_path: Path) -> None:
    spec = str(_checkpoint("default", tmp_path))
    members = ensemble_members(spec)
    assert members == shipped_members(SEPARATOR.join(DEFAULT_MODEL))
    assert members[0] == f"{WEIGHTS_DIR / 'fast'}.ckpt:17-" and members[-1] == f"{WEIGHTS_DIR / 'u-high'}.ckpt:17-"
    assert not list(tmp_path.iterdir())  # real weights: nothing written


def test_a_preset_ensemble_gets_random_weights_and_keeps_a_range(tmp_path: Path) -> None:
    spec = str(_checkpoint("fast+u-fast:-16", tmp_path))
    assert ensemble_members(spec) == [str(tmp_path / "fast.ckpt"), f"{tmp_path / 'u-fast.ckpt'}:-16"]
    den = Denoiser(spec)
    out = den.denoise_array(np.ones((8, 8, 3), np.float32), spp=SPP)
    assert out.models == ("fast", "u-fast")  # the benchmark's spp runs the low-spp member


def test_an_ensembles_macs_count_only_the_members_that_run_at_the_benchmarks_spp(tmp_path: Path) -> None:
    both = Denoiser(str(_checkpoint("fast+u-fast", tmp_path)))
    fast_only = Denoiser(str(_checkpoint("fast+u-fast:17-", tmp_path)))
    fast, u_fast = (_macs(m.config) for m in both.members)
    assert denoiser_macs(both) == fast + u_fast
    assert denoiser_macs(fast_only) == fast  # u-fast runs from 17 spp only, the benchmark calls at SPP
