"""Dataset reading: config, manifest, images into RAM in transfer space; clear errors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from imaging.errors import DatasetError
from imaging.exr import read_exr
from training.dataset import CONVERGED_SPP, load_training_pairs, load_val_images, read_dataset_config, read_manifest
from training.synthetic import write_synthetic_dataset
from model.transfer import get_transfer


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("ds"), scenes=3, res=(32, 24), spp=(4, 16),
                                   val_scenes=(2,), aovs=True)


def test_manifest_and_config(dataset: Path) -> None:
    config = read_dataset_config(dataset)
    assert config["spp"] == [4, 16] and config["res"] == [32, 24]
    records = read_manifest(dataset)
    assert [(r.index, r.split) for r in records] == [(0, "train"), (1, "train"), (2, "val")]
    assert records[0].spp == (4, 16) and records[0].aovs == ("alb", "nrm")


def test_training_pairs_in_transfer_space(dataset: Path) -> None:
    transfer = get_transfer("log")
    records = [r for r in read_manifest(dataset) if r.split == "train"]
    pairs = load_training_pairs(dataset, records, transfer, aux=True)
    assert [(p.scene, p.spp) for p in pairs] == [(0, 4), (0, 16), (1, 4), (1, 16)]
    assert pairs[0].noisy.shape == (24, 32, 9) and pairs[0].ref.shape == (24, 32, 3)
    linear = read_exr(dataset / "images" / "scene0001_0016spp.hdr.exr").rgb
    expected = transfer.forward(torch.from_numpy(linear)).numpy()
    np.testing.assert_allclose(pairs[3].noisy[..., :3], expected, rtol=1e-6)
    plain = load_training_pairs(dataset, records, transfer, aux=False)
    assert plain[0].noisy.shape == (24, 32, 3)


def test_converged_pairs_feed_the_reference_itself(dataset: Path) -> None:
    transfer = get_transfer("pu")
    records = [r for r in read_manifest(dataset) if r.split == "train"]
    pairs = load_training_pairs(dataset, records, transfer, aux=True, converged=True)
    assert [(p.scene, p.spp) for p in pairs] == [(0, 4), (0, 16), (0, CONVERGED_SPP), (1, 4), (1, 16),
                                                (1, CONVERGED_SPP)]
    clean, noisy16 = pairs[5], pairs[4]
    np.testing.assert_array_equal(clean.noisy[..., :3], clean.ref)
    np.testing.assert_array_equal(clean.noisy[..., 3:], noisy16.noisy[..., 3:])  # aux of the highest spp
    assert not np.array_equal(noisy16.noisy[..., :3], noisy16.ref)
    plain = load_training_pairs(dataset, records, transfer, aux=False, converged=True)
    assert plain[2].noisy.shape == (24, 32, 3) and np.array_equal(plain[2].noisy, plain[2].ref)


def test_val_images_linear(dataset: Path) -> None:
    records = [r for r in read_manifest(dataset) if r.split == "val"]
    images = load_val_images(dataset, records, aux=False)
    assert [(i.scene, i.spp) for i in images] == [(2, 4), (2, 16)]
    np.testing.assert_array_equal(images[0].ref, read_exr(dataset / "images" / "scene0002_ref.hdr.exr").rgb)
    assert images[0].aux is None


def test_missing_aux_buffers(tmp_path: Path) -> None:
    root = write_synthetic_dataset(tmp_path, scenes=1, val_scenes=())
    with pytest.raises(DatasetError, match="needs aux inputs but the dataset has no alb/nrm"):
        load_training_pairs(root, read_manifest(root), get_transfer("log"), aux=True)


def test_missing_image(tmp_path: Path) -> None:
    root = write_synthetic_dataset(tmp_path, scenes=1, val_scenes=())
    (root / "images" / "scene0000_0016spp.hdr.exr").unlink()
    with pytest.raises(DatasetError, match="scene0000_0016spp.hdr.exr: file not found"):
        load_training_pairs(root, read_manifest(root), get_transfer("log"), aux=False)


def test_paths_never_come_from_manifest(tmp_path: Path) -> None:
    root = write_synthetic_dataset(tmp_path, scenes=1, val_scenes=())
    line = json.loads((root / "manifest.jsonl").read_text())
    line["path"] = "/etc/passwd"
    line["images"] = ["../../outside.exr"]
    (root / "manifest.jsonl").write_text(json.dumps(line) + "\n")
    pairs = load_training_pairs(root, read_manifest(root), get_transfer("log"), aux=False)
    assert len(pairs) == 2


@pytest.mark.parametrize("content, message", [
    (None, "dataset.json: not found"),
    ("{not json", "dataset.json: cannot read"),
    ('{"version": 2, "spp": [4]}', "unsupported dataset version 2"),
    ('{"version": 1, "spp": []}', "'spp' must be a non-empty list"),
])
def test_bad_dataset_json(tmp_path: Path, content: str | None, message: str) -> None:
    if content is not None:
        (tmp_path / "dataset.json").write_text(content)
    with pytest.raises(DatasetError, match=message):
        read_dataset_config(tmp_path)


def test_bad_manifest(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="manifest.jsonl: not found"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.jsonl").write_text('{"index": 0, "split": "train", "spp": [4]}\n{"index": 1}\n')
    with pytest.raises(DatasetError, match="manifest.jsonl:2: malformed manifest line"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.jsonl").write_text('{"index": 0, "split": "test", "spp": [4]}\n')
    with pytest.raises(DatasetError, match="bad index 0 or split 'test'"):
        read_manifest(tmp_path)


def test_camera_normals_are_turned_into_each_scene_s_camera_frame(tmp_path: Path) -> None:
    """``normals="camera"``: each scene's normals times the rotation of the sensor in its file
    (the synthetic normal (0, 0.6, 0.8) everywhere; tolerance 1e-6); albedo and radiance as they were."""
    from rendering.camera import world_to_camera
    from tests.test_camera import look_at
    from training.synthetic import camera_origin

    data = write_synthetic_dataset(tmp_path / "ds", scenes=2, res=(8, 8), spp=(4,), val_scenes=(1,), aovs=True,
                                   cameras=True)
    records = read_manifest(data)
    transfer = get_transfer("pu")
    world = load_training_pairs(data, records[:1], transfer, aux=True)
    pairs = load_training_pairs(data, records[:1], transfer, aux=True, normals="camera", converged=True)
    images = load_val_images(data, records[1:], aux=True, normals="camera")
    for index, got in ((0, pairs[0].noisy[..., 6:9]), (0, pairs[1].noisy[..., 6:9]), (1, images[0].aux[..., 3:])):
        want = world_to_camera(look_at(list(camera_origin(index)), [0, 0, 0], [0, 1, 0])) @ [0.0, 0.6, 0.8]
        np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=1e-6)
    np.testing.assert_array_equal(pairs[0].noisy[..., :6], world[0].noisy[..., :6])
    assert not np.allclose(pairs[0].noisy[..., 6:], world[0].noisy[..., 6:], atol=0.1)


def test_camera_normals_without_the_scene_file_are_one_error(tmp_path: Path) -> None:
    data = write_synthetic_dataset(tmp_path / "ds", scenes=1, res=(8, 8), spp=(4,), val_scenes=(), aovs=True)
    with pytest.raises(DatasetError, match=r"scene 0: normals in camera space need the scene's file, .*scene\.xml: "
                                           "not found"):
        load_training_pairs(data, read_manifest(data), get_transfer("pu"), aux=True, normals="camera")
