"""Random Mitsuba BSDF dicts: diffuse, (rough)plastic, (rough)conductor, (rough)dielectric.

Reflectances are linear RGB in [0, 0.9] (or a texture dict in that range); roughness ``alpha`` is
the microfacet width (0.01 near-specular .. 0.6 very rough); ``int_ior`` is a real index of
refraction (1.3 .. 1.9).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from scenes.colors import random_albedo, rgb
from scenes.sampling import log_uniform

CONDUCTORS = ("Au", "Ag", "Al", "Cu", "Cr", "Hg", "W")
MICROFACETS = ("ggx", "beckmann")
KINDS = ("diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "dielectric",
         "roughdielectric")
BSDF = dict[str, Any]
Reflectance = list[float] | Mapping[str, Any]


def _reflectance(value: Reflectance) -> Any:
    return rgb(value) if isinstance(value, list) else dict(value)


def diffuse(reflectance: Reflectance) -> BSDF:
    """Lambertian BSDF with an RGB or texture reflectance."""
    return {"type": "diffuse", "reflectance": _reflectance(reflectance)}


def twosided(bsdf: BSDF) -> BSDF:
    """Make a one-sided BSDF (diffuse, plastic, conductor) shade both faces alike."""
    return {"type": "twosided", "bsdf": bsdf}


def plastic(rng: np.random.Generator, reflectance: Reflectance | None = None) -> BSDF:
    """Smooth plastic: diffuse base under a specular dielectric coating."""
    return {"type": "plastic",
            "diffuse_reflectance": _reflectance(reflectance or random_albedo(rng)),
            "int_ior": float(rng.uniform(1.4, 1.7))}


def roughplastic(rng: np.random.Generator, reflectance: Reflectance | None = None) -> BSDF:
    """Rough plastic with a GGX/Beckmann coating of alpha in [0.03, 0.5]."""
    return {"type": "roughplastic",
            "distribution": str(rng.choice(MICROFACETS)),
            "alpha": log_uniform(rng, 0.03, 0.5),
            "diffuse_reflectance": _reflectance(reflectance or random_albedo(rng)),
            "int_ior": float(rng.uniform(1.4, 1.7))}


def conductor(rng: np.random.Generator) -> BSDF:
    """Smooth metal with measured optical constants (gold, silver, copper, ...)."""
    return {"type": "conductor", "material": str(rng.choice(CONDUCTORS))}


def roughconductor(rng: np.random.Generator, alpha_range: tuple[float, float] = (0.02, 0.5)) -> BSDF:
    """Rough metal: measured constants, alpha log-uniform in ``alpha_range``."""
    return {"type": "roughconductor",
            "material": str(rng.choice(CONDUCTORS)),
            "distribution": str(rng.choice(MICROFACETS)),
            "alpha": log_uniform(rng, *alpha_range)}


def dielectric(rng: np.random.Generator) -> BSDF:
    """Smooth glass-like interface, interior IOR in [1.3, 1.9] against air."""
    return {"type": "dielectric", "int_ior": float(rng.uniform(1.3, 1.9)), "ext_ior": 1.000277}


def roughdielectric(rng: np.random.Generator) -> BSDF:
    """Frosted glass: IOR in [1.3, 1.9], GGX/Beckmann alpha in [0.03, 0.4]."""
    return {"type": "roughdielectric",
            "distribution": str(rng.choice(MICROFACETS)),
            "alpha": log_uniform(rng, 0.03, 0.4),
            "int_ior": float(rng.uniform(1.3, 1.9)), "ext_ior": 1.000277}


def random_bsdf(rng: np.random.Generator, weights: Mapping[str, float] | None = None,
                reflectance: Reflectance | None = None) -> BSDF:
    """A BSDF of a kind drawn from ``weights`` (kind -> relative weight; default: uniform).

    ``reflectance`` (RGB list or texture dict) is used by the diffuse and plastic kinds.
    """
    weights = dict(weights or {k: 1.0 for k in KINDS})
    unknown = set(weights) - set(KINDS)
    if unknown:
        raise ValueError(f"unknown BSDF kind(s) {sorted(unknown)} (known: {', '.join(KINDS)})")
    kinds = list(weights)
    p = np.array([weights[k] for k in kinds], dtype=np.float64)
    kind = kinds[int(rng.choice(len(kinds), p=p / p.sum()))]
    if kind == "diffuse":
        return diffuse(reflectance or random_albedo(rng))
    if kind == "plastic":
        return plastic(rng, reflectance)
    if kind == "roughplastic":
        return roughplastic(rng, reflectance)
    if kind == "conductor":
        return conductor(rng)
    if kind == "roughconductor":
        return roughconductor(rng)
    if kind == "dielectric":
        return dielectric(rng)
    return roughdielectric(rng)


def null() -> BSDF:
    """An invisible, index-matched boundary: it only marks where a shape's medium begins."""
    return {"type": "null"}
