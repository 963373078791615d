"""The scene families by name, and ``generate(family, seed)``.

``FAMILIES`` holds every family; ``DEFAULT_FAMILIES`` names those a dataset uses unless told
otherwise (the original nine, in their original order: datasets generated with the default stay
reproducible as families are added).
"""
from __future__ import annotations

from collections.abc import Callable

from scenes.families import (
    caustics,
    cornell_box,
    env_objects,
    indoor_room,
    material_preview,
    media,
    small_emitters,
    terrain,
    textured_surfaces,
    veach_mis,
)
from scenes.spec import GeneratedScene

FAMILIES: dict[str, Callable[[int], GeneratedScene]] = {
    "cornell_box": cornell_box.generate,
    "material_preview": material_preview.generate,
    "indoor_room": indoor_room.generate,
    "env_objects": env_objects.generate,
    "caustics": caustics.generate,
    "small_emitters": small_emitters.generate,
    "textured_surfaces": textured_surfaces.generate,
    "terrain": terrain.generate,
    "veach_mis": veach_mis.generate,
    "media": media.generate,
}
DEFAULT_FAMILIES: tuple[str, ...] = (
    "cornell_box", "material_preview", "indoor_room", "env_objects", "caustics", "small_emitters",
    "textured_surfaces", "terrain", "veach_mis",
)
MAX_SEED = 2**63 - 1


def generate(family: str, seed: int) -> GeneratedScene:
    """The scene of ``family`` for ``seed`` (an integer in [0, 2^63)); same seed, same scene.

    Raises ValueError for an unknown family (naming the known ones) or a bad seed.
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r} (known: {', '.join(sorted(FAMILIES))})")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed must be an integer in [0, 2^63), got {seed!r}")
    return FAMILIES[family](seed)
