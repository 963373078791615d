"""The dataset's one file-naming pattern, written and parsed here only.

Images: ``scene{NNNN}_{SSSS}spp.{kind}.exr`` for a noisy render at SSSS samples per pixel and
``scene{NNNN}_ref.{kind}.exr`` for the reference, where kind is ``hdr`` (RGB radiance), ``alb``
(albedo), ``nrm`` (shading normal) or ``var`` (per-pixel variance of the noisy image's mean,
estimated from two halves of its samples). Example: ``scene0042_0128spp.hdr.exr``,
``scene0042_ref.hdr.exr``. Scene folders are ``scene{NNNN}``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

KINDS = ("hdr", "alb", "nrm", "var")
_NAME_RE = re.compile(r"^scene(?P<index>\d{4,})_(?:(?P<spp>\d{4,})spp|ref)\.(?P<kind>hdr|alb|nrm|var)\.exr$")


@dataclass(frozen=True)
class ImageName:
    """A parsed image name: scene index, spp (None for the reference) and buffer kind."""

    index: int
    spp: int | None
    kind: str

    @property
    def is_reference(self) -> bool:
        return self.spp is None


def scene_name(index: int) -> str:
    """Folder/prefix name of scene ``index``: ``scene0042``."""
    if index < 0:
        raise ValueError(f"scene index must be >= 0, got {index}")
    return f"scene{index:04d}"


def image_name(index: int, spp: int | None, kind: str = "hdr") -> str:
    """File name of an image; ``spp=None`` names the reference."""
    if kind not in KINDS:
        raise ValueError(f"unknown image kind {kind!r} (known: {', '.join(KINDS)})")
    if spp is not None and spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    middle = "ref" if spp is None else f"{spp:04d}spp"
    return f"{scene_name(index)}_{middle}.{kind}.exr"


def parse_image_name(name: str) -> ImageName:
    """Inverse of :func:`image_name`; raises ValueError for a name that does not follow it."""
    m = _NAME_RE.match(name)
    if m is None:
        raise ValueError(f"{name!r} does not follow the pattern scene0042_0128spp.hdr.exr / scene0042_ref.hdr.exr")
    spp = m.group("spp")
    return ImageName(int(m.group("index")), int(spp) if spp else None, m.group("kind"))
