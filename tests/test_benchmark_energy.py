"""benchmarks/energy.py: every setting scored on the same images, summarised with its worst case."""
from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.energy import NONE, label, markdown, parse_settings, summarize, validation_rows
from training.synthetic import write_synthetic_dataset
from denoise.denoiser import Denoiser
from denoise.energy import EnergySettings
from tests.test_benchmark_validation import _checkpoint


def test_an_identity_model_leaves_nothing_to_correct(tmp_path: Path) -> None:
    """An untrained residual model returns the render: its local means are the render's, so every
    setting scores as the uncorrected output, which scores as the render; a perturbed model's
    output is corrected, and the table counts images made worse."""
    data = write_synthetic_dataset(tmp_path / "d", scenes=3, res=(32, 24), spp=(4, 16), val_scenes=(1, 2),
                                   variance=True)
    settings = [EnergySettings(), EnergySettings(clamp=4.0, radius=1, significance=0.0)]
    labels = [label(s) for s in settings]
    identity = Denoiser(_checkpoint(tmp_path / "a.ckpt"), energy=None)
    rows = list(validation_rows([data], identity, settings))
    assert len(rows) == 4 and {spp for spp, _ in rows} == {4, 16}
    for _, row in rows:
        assert row[NONE] == pytest.approx(row["noisy"], abs=1e-3)
        assert all(row[name] == pytest.approx(row[NONE], abs=1e-4) for name in labels)
        assert row["kept none"] == pytest.approx(row["kept default"], rel=1e-4)
    summary = summarize(iter(rows), labels)
    assert summary["per_spp"]["4"]["images"] == 2 and summary["per_spp"]["4"][f"worse {labels[1]}"] == 0
    assert "| 16 | 2 |" in "\n".join(markdown(summary, "t", labels))
    perturbed = Denoiser(_checkpoint(tmp_path / "b.ckpt", perturb=True), energy=None)
    _, row = next(validation_rows([data], perturbed, settings))
    assert row[labels[1]] != pytest.approx(row[NONE], abs=1e-4)


def test_settings_are_parsed_and_checked() -> None:
    assert parse_settings("16:2:4,8:1:0") == [EnergySettings(), EnergySettings(clamp=8.0, radius=1, significance=0.0)]
    for bad in ("16:2", "x:2:4", "0:2:4", "16:-1:4"):
        with pytest.raises(ValueError):
            parse_settings(bad)
