"""benchmarks/ensemble.py: members, their mean and each combination scored on the same images."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks.ensemble import MEAN, label, markdown_table, summarize, validation_rows
from training.synthetic import write_synthetic_dataset
from denoise.denoiser import Denoiser
from tests.test_benchmark_validation import _checkpoint


def test_identity_members_score_as_the_noisy_input_in_every_column(tmp_path: Path) -> None:
    """Untrained residual models return the render: so do their mean, every combination and the
    guard on them; a perturbed member differs."""
    data = write_synthetic_dataset(tmp_path / "d", scenes=3, res=(32, 24), spp=(4, 16), val_scenes=(1, 2),
                                   variance=True)
    members = {"a": Denoiser(_checkpoint(tmp_path / "a.ckpt")), "b": Denoiser(_checkpoint(tmp_path / "b.ckpt"))}
    settings = [(1, 0.0, 1.0), (3, 0.3, 2.0)]
    rows = list(validation_rows([data], members, settings, min_spp=4))
    assert len(rows) == 4 and {spp for spp, _ in rows} == {4, 16}
    for _, row in rows:
        for column in ("a", "b", MEAN, label(settings[0]), label(settings[1])):
            assert row[column] == pytest.approx(row["noisy"], abs=1e-3)
    summary = summarize(iter(rows))
    assert summary["per_spp"]["4"]["images"] == 2
    assert summary["mean"]["a"] == pytest.approx(np.mean([summary["per_spp"][s]["a"] for s in ("4", "16")]))
    assert "| **mean** |" in "\n".join(markdown_table(summary, "t"))
    members["b"] = Denoiser(_checkpoint(tmp_path / "c.ckpt", perturb=True))
    _, row = next(validation_rows([data], members, settings, min_spp=16))
    assert row["b"] != pytest.approx(row["noisy"], abs=1e-3)
