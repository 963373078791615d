"""The readers fuzzed, each with the small valid files it starts from and how a command reads them.

A :class:`Target` writes its seed files (made with the tests' own helpers: tiny EXRs as
``write_exr`` and the layouts of ``tests/test_exr_layers.py``, PFM and RGBE files as Mitsuba
writes them, the tiny checkpoint of ``tests/test_denoiser.py``, a scene with an include, a train
config, a synthetic dataset's ``dataset.json`` and manifest), mutates one of them
(:mod:`fuzz.mutate`) and hands the result to the command that reads it, in this process: the CLI
main itself (``denoise``), or, where the command would go on to render or train, the same
library calls it makes first under the command's own error handling
(:meth:`console.usage.OneLineParser.attempt`), so the outcome is what a user would see.
"""
from __future__ import annotations

import json
import random
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fuzz.mutate import json_bytes, mutate_bytes, mutate_json, safetensors_with_header

DATASET_FILES = ("dataset.json", "manifest.jsonl")
SCENE = """<scene version="3.0.0">
    <default name="spp" value="1"/>
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    <include filename="sensor.xml"/>
    <shape type="sphere"><point name="center" x="0" y="0" z="0"/><float name="radius" value="1"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.4, 0.3"/></bsdf></shape>
    <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
</scene>
"""
SENSOR = """<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="6"/></film>
    </sensor>
</scene>
"""


@dataclass(frozen=True)
class Seed:
    """A valid file: its name, its bytes, how many leading bytes are its header (``hot``; 0 for the
    whole file) and whether it is text."""

    name: str
    data: bytes
    hot: int = 0
    text: bool = False


@dataclass
class Target:
    """A reader: ``prog`` whose one-line errors it gives, ``make_seeds(folder)`` its seed files
    (every file the reader needs; the ones in ``mutable``, or all, are mutated), ``run(folder,
    context, name)`` the command on the folder holding the mutated file ``name`` (its exit code)."""

    name: str
    prog: str
    make_seeds: Callable[[Path], list[Seed]]
    run: Callable[[Path, "Context", str], int]
    mutable: tuple[str, ...] = ()
    structured: Callable[[Seed, random.Random], bytes] | None = None
    seeds: list[Seed] = field(default_factory=list)

    def prepare(self, folder: Path) -> None:
        """Make the seed files in ``folder`` (created)."""
        folder.mkdir(parents=True, exist_ok=True)
        self.seeds = self.make_seeds(folder)

    def mutate(self, rnd: random.Random) -> Seed:
        """One of the seeds, mutated (a structure-aware mutation half the time where there is one)."""
        candidates = [s for s in self.seeds if not self.mutable or s.name in self.mutable]
        seed = rnd.choice(candidates)
        if self.structured is not None and rnd.random() < 0.5:
            data = self.structured(seed, rnd)
        else:
            others = tuple(s.data for s in self.seeds if s is not seed)
            data = mutate_bytes(seed.data, rnd, seed.hot, seed.text, others)
        return Seed(seed.name, data, seed.hot, seed.text)

    def lay_out(self, folder: Path, mutated: Seed) -> Path:
        """Write every seed file into ``folder``, the mutated one in place of its original."""
        for seed in (*self.seeds, mutated):
            (folder / seed.name).parent.mkdir(parents=True, exist_ok=True)
            (folder / seed.name).write_bytes(mutated.data if seed.name == mutated.name else seed.data)
        return folder / mutated.name


@dataclass
class Context:
    """What every target's command needs beside the fuzzed file (made once): a tiny checkpoint,
    a tiny input image, a synthetic dataset."""

    root: Path
    checkpoint: Path
    image: Path
    dataset: Path

    @classmethod
    def create(cls, root: Path) -> Context:
        from imaging.exr import write_exr
        from tests.test_denoiser import write_tiny_checkpoint
        from training.synthetic import write_synthetic_dataset

        root.mkdir(parents=True, exist_ok=True)
        image = root / "in.exr"
        write_exr(image, np.random.default_rng(0).random((6, 8, 3)).astype(np.float32))
        return cls(root, write_tiny_checkpoint(root / "tiny.ckpt"), image,
                   write_synthetic_dataset(root / "dataset", scenes=2, res=(8, 8), spp=(4,), val_scenes=(1,)))


# ----------------------------------------------------------------------------- seeds
def _rng() -> np.random.Generator:
    return np.random.default_rng(7)


def _image(h: int = 6, w: int = 8) -> np.ndarray:
    return (_rng().random((h, w, 3)) * 4).astype(np.float32)


def _exr_seed(path: Path) -> Seed:
    from imaging.exr_header import read_exr_header

    end = read_exr_header(path).tables_end  # None (a compression the header check cannot size): the whole file
    return Seed(path.name, path.read_bytes(), 0 if end is None else end + 16)


def exr_seeds(folder: Path) -> list[Seed]:
    from imaging.exr import write_exr

    img = _image()
    write_exr(folder / "plain.exr", img, metadata={"spp": 16})
    write_exr(folder / "half.exr", img, layers={"albedo": img / 4, "variance": img / 16}, half=True)
    return [_exr_seed(folder / n) for n in ("plain.exr", "half.exr")]


def _planes(prefix: str, suffixes: str, dtype: type = np.float32) -> dict[str, np.ndarray]:
    sep = "." if prefix else ""
    return {f"{prefix}{sep}{s}": _rng().random((6, 8)).astype(dtype) for s in suffixes}


def exr_multipart_seeds(folder: Path) -> list[Seed]:
    import OpenEXR

    parts = [OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION, "spp": 32}, _planes("", "RGBA", np.float16),
                          name="color"),
             OpenEXR.Part({"compression": OpenEXR.PIZ_COMPRESSION}, _planes("", "RGB", np.float16), name="albedo"),
             OpenEXR.Part({}, _planes("", "XYZ"), name="normal"),
             OpenEXR.Part({"compression": OpenEXR.NO_COMPRESSION}, _planes("variance", "RGB"), name="variance")]
    with OpenEXR.File(parts) as f:
        f.write(str(folder / "parts.exr"))
    tiles = OpenEXR.TileDescription()
    tiles.xSize, tiles.ySize = 4, 4
    with OpenEXR.File({"type": OpenEXR.tiledimage, "tiles": tiles}, _planes("", "RGB")) as f:
        f.write(str(folder / "tiled.exr"))
    return [_exr_seed(folder / n) for n in ("parts.exr", "tiled.exr")]


def exr_layer_seeds(folder: Path) -> list[Seed]:
    import OpenEXR

    blender = {**_planes("ViewLayer.Combined", "RGBA", np.float16), **_planes("ViewLayer.Emit", "RGB"),
               **_planes("ViewLayer.DiffCol", "RGB"), **_planes("ViewLayer.Denoising Albedo", "RGB", np.float16),
               **_planes("ViewLayer.Denoising Normal", "XYZ", np.float16), **_planes("ViewLayer.Depth", "Z")}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, blender) as f:
        f.write(str(folder / "blender.exr"))
    aov = {**_planes("", "RGB"), **_planes("my_image", "RGBA"), **_planes("albedo", "RGB"), **_planes("nn", "XYZ")}
    with OpenEXR.File({"compression": OpenEXR.RLE_COMPRESSION}, aov) as f:
        f.write(str(folder / "aov.exr"))
    return [_exr_seed(folder / n) for n in ("blender.exr", "aov.exr")]


def pfm_seeds(folder: Path) -> list[Seed]:
    from imaging.bitmap_io import read_bitmap_header, write_bitmap

    write_bitmap(folder / "rgb.pfm", _image())
    grey = _image()[..., 0]
    (folder / "grey.pfm").write_bytes(b"Pf\n8 6\n-1.0\n" + grey[::-1].astype("<f4").tobytes())
    (folder / "big.pfm").write_bytes(b"PF\n8 6\n2.0\n" + _image()[::-1].astype(">f4").tobytes())
    return [Seed(n, (folder / n).read_bytes(), read_bitmap_header(folder / n).data_offset + 8)
            for n in ("rgb.pfm", "grey.pfm", "big.pfm")]


def hdr_seeds(folder: Path) -> list[Seed]:
    from imaging.bitmap_io import read_bitmap_header, write_bitmap

    write_bitmap(folder / "rle.hdr", _image(9, 16))  # 8..32767 pixels wide: run-length encoded
    write_bitmap(folder / "flat.hdr", _image(3, 4))
    return [Seed(n, (folder / n).read_bytes(), read_bitmap_header(folder / n).data_offset + 16)
            for n in ("rle.hdr", "flat.hdr")]


def checkpoint_seeds(folder: Path) -> list[Seed]:
    import torch

    from model.architectures import build_model
    from model.checkpoint import save_checkpoint
    from model.config import ModelConfig
    from tests.test_denoiser import write_tiny_checkpoint

    write_tiny_checkpoint(folder / "tiny.ckpt")
    torch.manual_seed(0)
    unet = build_model(ModelConfig(arch="dense_unet", levels=1, layers=1, growth=4, init_features=8, transfer="pu"))
    optimizer = torch.optim.Adam(unet.parameters())
    unet(torch.rand(1, 3, 8, 8)).mean().backward()
    optimizer.step()
    save_checkpoint(folder / "unet.ckpt", unet, step=1, optimizer=optimizer)
    seeds = []
    for name in ("tiny.ckpt", "unet.ckpt"):
        data = (folder / name).read_bytes()
        seeds.append(Seed(name, data, 8 + int.from_bytes(data[:8], "little")))
    return seeds


def mutate_checkpoint_header(seed: Seed, rnd: random.Random) -> bytes:
    """The safetensors header mutated as JSON: our checkpoint header (model config, optimiser, step)
    two times in three, else the tensors' entries (dtype, shape, offsets)."""
    header = json.loads(seed.data[8:seed.hot])
    if rnd.random() < 2 / 3:
        ours = json.loads(header["__metadata__"]["denoiser_checkpoint"])
        header["__metadata__"]["denoiser_checkpoint"] = json_bytes(mutate_json(ours, rnd), rnd).decode()
    else:
        header = mutate_json(header, rnd)
    try:
        return safetensors_with_header(seed.data, header)
    except (TypeError, ValueError, RecursionError):
        return seed.data[:8] + json_bytes(header, rnd) + seed.data[seed.hot:]


def resume_seeds_from(dataset: Path) -> Callable[[Path], list[Seed]]:
    """A run's last.ckpt after one step of training on the context's dataset (its header's data
    and out paths replaced by placeholders: resuming names them)."""
    def make(folder: Path) -> list[Seed]:
        from training.cli import build_parser, config_from_args
        from training.train import train

        shutil.rmtree(folder / "made", ignore_errors=True)
        args = build_parser().parse_args(["--data", str(dataset), "--out", str(folder / "made"), "--layers", "2",
                                          "--growth", "4", "--width", "8",
                                          "--steps", "1", "--batch", "2", "--patch", "8", "--val-every", "0",
                                          "--no-progress", "--no-oidn", "--threads", "1"])
        train(config_from_args(args)[0])
        data = (folder / "made" / "last.ckpt").read_bytes()
        header = json.loads(data[8:8 + int.from_bytes(data[:8], "little")])
        ours = json.loads(header["__metadata__"]["denoiser_checkpoint"])
        ours["train_config"].update(data="DATA", out="OUT")
        header["__metadata__"]["denoiser_checkpoint"] = json.dumps(ours)
        data = safetensors_with_header(data, header)
        return [Seed("last.ckpt", data, 8 + int.from_bytes(data[:8], "little"))]
    return make


def scene_seeds(folder: Path) -> list[Seed]:
    return [Seed("scene.xml", SCENE.encode(), text=True), Seed("sensor.xml", SENSOR.encode(), text=True)]


def train_config_seeds(folder: Path) -> list[Seed]:
    from model.config import PRESETS
    from training.train_config import TrainConfig

    full = TrainConfig(data="DATA", out="OUT", model=PRESETS["flat-s"], steps=10, batch=2).to_dict()
    full.pop("data")
    full.pop("out")
    small = {"model": {"preset": "unet-s", "levels": 2}, "steps": 5, "lr": 0.001}
    return [Seed("full.json", json.dumps(full, indent=1).encode(), text=True),
            Seed("small.json", json.dumps(small).encode(), text=True)]


def dataset_seeds_from(dataset: Path) -> Callable[[Path], list[Seed]]:
    """A synthetic dataset's files: its config and manifest (mutated) and its images."""
    def make(folder: Path) -> list[Seed]:
        images = [Seed(str(p.relative_to(dataset)), p.read_bytes()) for p in sorted((dataset / "images").iterdir())]
        return [*(Seed(n, (dataset / n).read_bytes(), text=True) for n in DATASET_FILES), *images]
    return make


def mutate_json_seed(seed: Seed, rnd: random.Random) -> bytes:
    """A JSON file (or each JSON line of a .jsonl file) mutated as JSON."""
    if seed.name.endswith(".jsonl"):
        lines = seed.data.decode().splitlines()
        i = rnd.randrange(len(lines))
        lines[i] = json_bytes(mutate_json(json.loads(lines[i]), rnd), rnd).decode().replace("\n", " ")
        return "\n".join(lines).encode() + b"\n"
    return json_bytes(mutate_json(json.loads(seed.data), rnd), rnd)


# ----------------------------------------------------------------------------- commands
def denoise_image(folder: Path, ctx: Context, name: str) -> int:
    from pipeline.cli import denoise_main

    return denoise_main([str(folder / name), str(folder / "out.exr"), "--model", str(ctx.checkpoint)])


def reference_image(folder: Path, ctx: Context, name: str) -> int:
    """render-and-denoise's and training's EXR reader (:func:`imaging.exr.read_exr`), as it reads a
    --reference before rendering."""
    from pipeline.cli import render_parser
    from pipeline.evaluation import RenderSettings, read_reference

    settings = RenderSettings(scene="unused.xml", reference=str(folder / name), max_memory_mb=64)
    return render_parser().attempt(lambda: read_reference(settings))[1]


def denoise_with_model(folder: Path, ctx: Context, name: str) -> int:
    from pipeline.cli import denoise_main

    return denoise_main(["--model", str(folder / name), str(ctx.image), str(folder / "out.exr")])


def resume_training(folder: Path, ctx: Context, name: str) -> int:
    """train --resume up to its first step: the run's config from last.ckpt, the data, the network
    and the optimiser's state restored from it."""
    from training.cli import build_parser
    from training.train import _Run, resume_config

    def start() -> None:
        _Run(resume_config(folder, {"data": str(ctx.dataset), "steps": 2}), resume=True)

    return build_parser().attempt(start)[1]


def load_scene_file(folder: Path, ctx: Context, name: str) -> int:
    """render-and-denoise's scene loading (parse, inline includes, fix the film, Mitsuba's loader)."""
    from pipeline.cli import render_parser
    from pipeline.evaluation import RenderSettings

    settings = RenderSettings(scene=str(folder / "scene.xml"), resolution=(8, 6))
    return render_parser().attempt(settings.load)[1]


def read_train_config(folder: Path, ctx: Context, name: str) -> int:
    """train's reading of --config (and its checks of the model it describes), up to training."""
    from model.shapes import check_fits_in_memory
    from training.cli import build_parser, config_from_args

    parser = build_parser()
    args = parser.parse_args(["--config", str(folder / name), "--data", str(ctx.dataset), "--out",
                              str(folder / "run")])
    return parser.attempt(lambda: check_fits_in_memory(config_from_args(args)[0].model))[1]


def read_dataset(folder: Path, ctx: Context, name: str) -> int:
    """train's reading of a dataset: dataset.json, the manifest, the images it lists."""
    from model.transfer import get_transfer
    from training.cli import build_parser
    from training.dataset import load_training_pairs, load_val_images, read_dataset_config, read_manifest

    def read() -> None:
        read_dataset_config(folder)
        records = read_manifest(folder)
        load_training_pairs(folder, [r for r in records if r.split == "train"], get_transfer("pu"), False)
        load_val_images(folder, [r for r in records if r.split == "val"], False, False)

    return build_parser().attempt(read)[1]


TARGET_NAMES = ("exr", "exr-blocks", "exr-multipart", "exr-layers", "pfm", "hdr", "checkpoint", "checkpoint-resume",
                "scene-xml", "train-config", "dataset")


def targets(ctx: Context) -> dict[str, Target]:
    """Every fuzzed reader by name (:data:`TARGET_NAMES`)."""
    found = [
        Target("exr", "denoise", exr_seeds, denoise_image),
        Target("exr-blocks", "render-and-denoise", exr_seeds, reference_image),
        Target("exr-multipart", "denoise", exr_multipart_seeds, denoise_image),
        Target("exr-layers", "denoise", exr_layer_seeds, denoise_image),
        Target("pfm", "denoise", pfm_seeds, denoise_image),
        Target("hdr", "denoise", hdr_seeds, denoise_image),
        Target("checkpoint", "denoise", checkpoint_seeds, denoise_with_model, structured=mutate_checkpoint_header),
        Target("checkpoint-resume", "train", resume_seeds_from(ctx.dataset), resume_training,
               structured=mutate_checkpoint_header),
        Target("scene-xml", "render-and-denoise", scene_seeds, load_scene_file),
        Target("train-config", "train", train_config_seeds, read_train_config, structured=mutate_json_seed),
        Target("dataset", "train", dataset_seeds_from(ctx.dataset), read_dataset, mutable=DATASET_FILES,
               structured=mutate_json_seed),
    ]
    assert tuple(t.name for t in found) == TARGET_NAMES
    return {t.name: t for t in found}
