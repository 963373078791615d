"""The dataset's file-naming pattern: one writer, one parser."""
from __future__ import annotations

import pytest

from imaging.naming import ImageName, image_name, parse_image_name, scene_name


def test_names_follow_the_documented_pattern() -> None:
    assert image_name(42, 128) == "scene0042_0128spp.hdr.exr"
    assert image_name(42, None) == "scene0042_ref.hdr.exr"
    assert image_name(7, 4, "alb") == "scene0007_0004spp.alb.exr"
    assert scene_name(12345) == "scene12345"


@pytest.mark.parametrize("index,spp,kind", [(0, 1, "hdr"), (42, 128, "nrm"), (9999, None, "alb"),
                                            (12345, 4096, "hdr")])
def test_parse_inverts_image_name(index: int, spp: int | None, kind: str) -> None:
    assert parse_image_name(image_name(index, spp, kind)) == ImageName(index, spp, kind)


@pytest.mark.parametrize("bad", ["scene42_0128spp.hdr.exr", "scene0042_128spp.hdr.exr",
                                 "scene0042_ref.exr", "../scene0042_ref.hdr.exr", "scene0042_ref.hdr.png"])
def test_parse_rejects_other_names(bad: str) -> None:
    with pytest.raises(ValueError, match="does not follow the pattern"):
        parse_image_name(bad)


def test_image_name_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError):
        image_name(1, 0)
    with pytest.raises(ValueError):
        image_name(1, 4, "png")
