"""The example scene shipped as ``scenes/examples/demo.xml`` (used by ``make demo``).

A Cornell box with a glass sphere (a caustic on the floor, light refracted onto the ceiling), a
rough gold block (glossy) and a brick back wall (a generated texture, written as
``scenes/examples/textures/bricks.exr``): at 16 spp it shows what a denoiser does with fireflies,
texture and glossy highlights. ``make demo`` renders it at 256x256 and compares with the shipped
4096-spp reference ``scenes/examples/demo_reference.exr`` (rendering one would take minutes).
Regenerate the files with ``python -m scenes.demo`` (``--reference``: the reference too); tests
check the shipped XML still matches :func:`demo_scene` and the reference the scene.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scenes import camera, lights, materials, textures
from scenes.rooms import room, wall
from scenes.shapes import sphere, transformed
from scenes.spec import GeneratedScene
from scenes.transforms import compose, rotate, scale, translate
from scenes.xml_export import write_scene

EXAMPLES_DIR = Path(__file__).resolve().parent / "examples"
DEMO_NAME = "demo.xml"
REFERENCE_NAME = "demo_reference.exr"
# The shipped files by absolute path, wherever the package is installed (the README's snippet uses it)
DEMO_SCENE = EXAMPLES_DIR / DEMO_NAME
DEMO_REFERENCE = EXAMPLES_DIR / REFERENCE_NAME
DEMO_RESOLUTION = (256, 256)  # make demo's --res
REFERENCE_SPP = 4096
REFERENCE_SEED = 1_000_003  # not a seed render-and-denoise uses for its noisy render
BRICKS = "textures/bricks.exr"
TEXTURE_SEED = 7


def demo_scene() -> GeneratedScene:
    """The fixed demo scene (family ``demo``, seed 0): 2x2x2 box, ceiling light of 17 W/m^2 sr."""
    w = h = d = 2.0
    white, red, green = [0.73, 0.71, 0.68], [0.63, 0.065, 0.05], [0.14, 0.45, 0.091]
    scene: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": 8}}
    scene["sensor"] = camera.perspective((0.0, 1.0, 4.2), (0.0, 0.95, 0.0), 39.0)
    bricks = textures.brick_image(np.random.default_rng(TEXTURE_SEED), 128)
    walls = {"floor": materials.diffuse(white), "ceiling": materials.diffuse(white),
             "back": materials.diffuse(textures.bitmap(BRICKS, 1.0)),
             "left": materials.diffuse(red), "right": materials.diffuse(green)}
    scene.update(room(w, h, d, walls))
    panel = wall("ceiling", w, h, d).panel(-0.25, 0.25, -0.2, 0.2, offset=1e-3)
    scene["light"] = transformed("rectangle", panel, materials.diffuse([0.7, 0.7, 0.7]),
                                 lights.area([17.0, 12.0, 4.0]))
    scene["glass_sphere"] = sphere((-0.38, 0.35, 0.3), 0.35,
                                   {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.000277})
    block = compose(translate((0.4, 0.45, -0.3)), rotate((0, 1, 0), 25.0), scale((0.28, 0.45, 0.28)))
    scene["gold_block"] = transformed("cube", block, {"type": "roughconductor", "material": "Au",
                                                      "distribution": "ggx", "alpha": 0.15})
    return GeneratedScene("demo", 0, scene, {BRICKS: bricks})


def write_demo(folder: Path = EXAMPLES_DIR) -> Path:
    """Write ``demo.xml`` and its texture into ``folder``; return the XML path."""
    return write_scene(demo_scene(), folder, DEMO_NAME)


def write_demo_reference(folder: Path = EXAMPLES_DIR, spp: int = REFERENCE_SPP) -> Path:
    """Render ``folder/demo.xml`` at :data:`DEMO_RESOLUTION` and ``spp`` samples per pixel into
    ``folder/demo_reference.exr`` (float16, its settings in the header); return the path."""
    from importlib import metadata

    from imaging.exr import write_exr
    from rendering.render import render

    result = render(folder / DEMO_NAME, spp, seed=REFERENCE_SEED, resolution=DEMO_RESOLUTION)
    path = folder / REFERENCE_NAME
    write_exr(path, result.rgb, half=True,
              metadata={"scene": DEMO_NAME, "spp": spp, "seed": REFERENCE_SEED,
                        "mitsuba": metadata.version("mitsuba"), "variant": result.variant,
                        "command": f"python -m scenes.demo --reference (spp {spp})"})
    return path


if __name__ == "__main__":
    import sys

    print(write_demo())
    if "--reference" in sys.argv[1:]:
        print(write_demo_reference())
