"""The scoreboard's set-up call (benchmarks/evaluate.py): every kind of model takes it."""
from __future__ import annotations

from pathlib import Path

from benchmarks.evaluate import warm_up
from denoise.denoiser import Denoiser
from model.config import ModelConfig
from tests.test_denoiser import write_tiny_checkpoint


def test_a_model_with_albedo_and_normal_inputs_is_warmed_up_with_buffers(tmp_path: Path) -> None:
    """The first call before the timed scenes gives a model that needs albedo and normals flat
    buffers of its own (without them the scoreboard stopped at once: "needs albedo and normals")."""
    aux = Denoiser(write_tiny_checkpoint(tmp_path / "aux.ckpt", ModelConfig(layers=2, growth=4, init_features=8,
                                                                             aux_inputs=True)))
    assert aux.needs_aovs
    warm_up(aux)
    camera = Denoiser(write_tiny_checkpoint(tmp_path / "camera.ckpt", ModelConfig(
        layers=2, growth=4, init_features=8, aux_inputs=True, aux_normals="camera")))
    warm_up(camera)  # it needs the camera's rotation too ("takes normals in the camera's frame")
    warm_up(Denoiser(write_tiny_checkpoint(tmp_path / "rgb.ckpt")))
