"""Multi-layer / multi-part EXRs written by OpenEXR as other renderers lay them out: layers found,
the colour layer picked (or the ambiguity named), and written back with everything else intact."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from imaging.errors import ExrError
from imaging.exr_layers import (ALBEDO_WORDS, NORMAL_WORDS, find_aux_layer, pick_color_layer,
                                 read_exr_file, replace_layer, write_exr_file)

H, W = 12, 16


def planes(rng: np.random.Generator, prefix: str, suffixes: str, dtype: type = np.float32) -> dict:
    sep = "." if prefix else ""
    return {f"{prefix}{sep}{s}": rng.random((H, W)).astype(dtype) for s in suffixes}


def blender(rng: np.random.Generator, dtype: type = np.float16) -> dict:
    """Blender's single-part multilayer layout (view layer 'ViewLayer', denoising data on)."""
    return {**planes(rng, "ViewLayer.Combined", "RGBA", dtype),
            **planes(rng, "ViewLayer.Denoising Albedo", "RGB", dtype),
            **planes(rng, "ViewLayer.Denoising Normal", "XYZ", dtype),
            **planes(rng, "ViewLayer.Depth", "Z", np.float32)}


def mitsuba_aov(rng: np.random.Generator) -> dict:
    """Mitsuba's aov integrator film: bare R,G,B, the inner integrator's image, then the AOVs."""
    return {**planes(rng, "", "RGB"), **planes(rng, "my_image", "RGBA"),
            **planes(rng, "albedo", "RGB"), **planes(rng, "nn", "XYZ")}


def multipart(rng: np.random.Generator, path: Path) -> None:
    parts = [OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION, "spp": 32, "renderer": "other"},
                          planes(rng, "", "RGBA", np.float16), name="color"),
             OpenEXR.Part({}, planes(rng, "", "RGB", np.float16), name="albedo"),
             OpenEXR.Part({}, planes(rng, "", "XYZ"), name="normal"),
             OpenEXR.Part({}, planes(rng, "variance", "RGB"), name="variance")]
    OpenEXR.File(parts).write(str(path))


def test_blender_layers_and_colour_pick(tmp_path: Path, rng: np.random.Generator) -> None:
    channels = blender(rng)
    # a copy: the binding turns the arrays of the dict it is given into Channel objects
    OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION}, dict(channels)).write(str(tmp_path / "b.exr"))
    exr = read_exr_file(tmp_path / "b.exr")
    assert set(exr.layers) == {"ViewLayer.Combined", "ViewLayer.Denoising Albedo",
                               "ViewLayer.Denoising Normal", "ViewLayer.Depth"}
    color = pick_color_layer(exr)
    assert color.name == "ViewLayer.Combined" and color.alpha == "ViewLayer.Combined.A"
    assert exr.is_half(color)
    expected = np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"], -1).astype(np.float32)
    assert np.array_equal(exr.image(color), expected)
    albedo = find_aux_layer(exr, ALBEDO_WORDS, color, ("rgb",))
    normal = find_aux_layer(exr, NORMAL_WORDS, color, ("rgb", "xyz"))
    assert albedo.name == "ViewLayer.Denoising Albedo" and normal.name == "ViewLayer.Denoising Normal"


def test_a_named_colour_layer_wins_over_other_passes(tmp_path: Path, rng: np.random.Generator) -> None:
    """Blender with render passes: ViewLayer.Combined beside the Emit and DiffCol passes (colour
    layers by their channels, no colour by their names) is the one picked; without it, the passes
    are ambiguous."""
    channels = {**planes(rng, "ViewLayer.Combined", "RGBA", np.float16), **planes(rng, "ViewLayer.Emit", "RGB"),
                **planes(rng, "ViewLayer.DiffCol", "RGB")}
    OpenEXR.File({}, dict(channels)).write(str(tmp_path / "passes.exr"))
    assert pick_color_layer(read_exr_file(tmp_path / "passes.exr")).name == "ViewLayer.Combined"
    passes = {k: v for k, v in channels.items() if "Combined" not in k}
    OpenEXR.File({}, dict(passes)).write(str(tmp_path / "only.exr"))
    with pytest.raises(ExrError, match=r"several colour layers \('ViewLayer.DiffCol', 'ViewLayer.Emit'\)"):
        pick_color_layer(read_exr_file(tmp_path / "only.exr"))


def test_mitsuba_aov_film_picks_the_bare_rgb(tmp_path: Path, rng: np.random.Generator) -> None:
    OpenEXR.File({}, mitsuba_aov(rng)).write(str(tmp_path / "m.exr"))
    exr = read_exr_file(tmp_path / "m.exr")
    assert pick_color_layer(exr).name == ""
    assert pick_color_layer(exr, "my_image").name == "my_image"
    assert find_aux_layer(exr, NORMAL_WORDS, exr.layers[""], ("xyz",)).name == "nn"


def test_multipart_layers_named_by_part(tmp_path: Path, rng: np.random.Generator) -> None:
    multipart(rng, tmp_path / "p.exr")
    exr = read_exr_file(tmp_path / "p.exr")
    assert {"color", "albedo", "normal", "variance"} <= set(exr.layers)
    color = pick_color_layer(exr)
    assert (color.name, color.part) == ("color", 0)
    assert exr.metadata(0)["spp"] == 32


@pytest.mark.parametrize("channels, needles", [
    ({**planes(np.random.default_rng(0), "ViewLayer.Combined", "RGB"),
      **planes(np.random.default_rng(1), "Other.Combined", "RGB")},
     ["several colour layers", "'ViewLayer.Combined'", "'Other.Combined'", "--layer"]),
    ({**planes(np.random.default_rng(0), "diffuse", "RGB"), **planes(np.random.default_rng(1), "glossy", "RGB")},
     ["several colour layers", "'diffuse'", "'glossy'"]),
    (planes(np.random.default_rng(0), "", "Y"), ["has no R/G/B channels", "Y"]),
])
def test_ambiguous_or_missing_colour_is_one_clear_line(tmp_path: Path, channels: dict,
                                                       needles: list[str]) -> None:
    OpenEXR.File({}, channels).write(str(tmp_path / "a.exr"))
    with pytest.raises(ExrError) as exc:
        pick_color_layer(read_exr_file(tmp_path / "a.exr"))
    message = str(exc.value)
    assert "\n" not in message and "a.exr" in message
    for needle in needles:
        assert needle in message, message


def test_unknown_layer_lists_the_colour_layers(tmp_path: Path, rng: np.random.Generator) -> None:
    OpenEXR.File({}, blender(rng)).write(str(tmp_path / "b.exr"))
    with pytest.raises(ExrError, match=r"no R,G,B layer named 'nope' .*'ViewLayer.Combined'"):
        pick_color_layer(read_exr_file(tmp_path / "b.exr"), "nope")


@pytest.mark.parametrize("layout", ["blender", "mitsuba", "multipart", "tiled"])
def test_replace_layer_round_trip_keeps_everything_else(tmp_path: Path, rng: np.random.Generator,
                                                        layout: str) -> None:
    src = tmp_path / "in.exr"
    if layout == "multipart":
        multipart(rng, src)
    else:
        header: dict = {"compression": OpenEXR.ZIP_COMPRESSION, "owner": "someone", "spp": 64}
        if layout == "tiled":
            tiles = OpenEXR.TileDescription()
            tiles.xSize, tiles.ySize, tiles.mode = 8, 8, OpenEXR.ONE_LEVEL
            header.update(type=OpenEXR.tiledimage, tiles=tiles)
        OpenEXR.File(header, blender(rng) if layout == "blender" else mitsuba_aov(rng)).write(str(src))
    exr = read_exr_file(src)
    color = pick_color_layer(exr)
    new = (rng.random((H, W, 3)) * 70000).astype(np.float32)  # beyond float16's range too
    write_exr_file(tmp_path / "out.exr", replace_layer(exr, color, new, {"denoised_by": "tiny.ckpt"}))
    back = read_exr_file(tmp_path / "out.exr")
    assert len(back.parts) == len(exr.parts)
    for before, after in zip(exr.parts, back.parts):
        assert before.name == after.name and set(before.channels) == set(after.channels)
        for name, pixels in before.channels.items():
            assert after.channels[name].dtype == pixels.dtype, name
            if name not in color.channels:
                assert np.array_equal(after.channels[name], pixels), name
        for key in ("compression", "type", "owner", "spp", "renderer"):
            assert after.header.get(key) == before.header.get(key), key
    assert back.parts[color.part].header["denoised_by"] == "tiny.ckpt"
    got = back.image(back.layers[color.name])
    if exr.is_half(color):
        assert np.allclose(got, np.minimum(new, 65504), rtol=1e-3) and np.isfinite(got).all()
    else:
        assert np.array_equal(got, new)


def test_truncated_files_and_missing_folders_are_refused(tmp_path: Path, rng: np.random.Generator) -> None:
    OpenEXR.File({}, planes(rng, "", "RGB")).write(str(tmp_path / "ok.exr"))
    data = (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(ExrError, match="cut.exr: truncated or corrupt"):
        read_exr_file(tmp_path / "cut.exr")
    multipart(rng, tmp_path / "parts.exr")  # its last part cut short
    data = (tmp_path / "parts.exr").read_bytes()
    (tmp_path / "cut_parts.exr").write_bytes(data[: len(data) - 200])
    with pytest.raises(ExrError, match="cut_parts.exr: truncated or corrupt"):
        read_exr_file(tmp_path / "cut_parts.exr")
    with pytest.raises(ExrError, match="output folder does not exist"):
        write_exr_file(tmp_path / "no" / "o.exr", read_exr_file(tmp_path / "ok.exr"))


def whole_file_bytes(path: Path, exr) -> bytes:
    """``exr`` as OpenEXR.File writes it from whole planes (the writer before the row blocks)."""
    header = {k: v for k, v in exr.parts[0].header.items() if k not in ("channels", "chunkCount", "name")}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in exr.parts[0].channels.items()}) as f:
        f.write(str(path))
    return path.read_bytes()


@pytest.mark.parametrize("layout", ["blender", "mitsuba", "window"])
@pytest.mark.parametrize("max_bytes", [1, 3000, 64 * 2**20])
def test_one_part_scanline_files_are_written_in_row_blocks(tmp_path: Path, rng: np.random.Generator,
                                                          layout: str, max_bytes: int) -> None:
    header: dict = {"compression": OpenEXR.ZIP_COMPRESSION, "owner": "someone", "spp": 64, "exposure": 0.25}
    channels = blender(rng) if layout == "blender" else mitsuba_aov(rng)
    if layout == "window":  # a data window away from the origin, inside a larger display window
        header.update(dataWindow=(np.array([3, 5], np.int32), np.array([3 + W - 1, 5 + H - 1], np.int32)),
                      displayWindow=(np.array([0, 0], np.int32), np.array([99, 99], np.int32)))
    channels["id"] = rng.integers(0, 2**32, (H, W), dtype=np.uint32)
    OpenEXR.File(header, dict(channels)).write(str(tmp_path / "in.exr"))
    exr = read_exr_file(tmp_path / "in.exr")
    color = pick_color_layer(exr)
    out = replace_layer(exr, color, (rng.random((H, W, 3)) * 70000).astype(np.float32), {"denoised_by": "x"})
    write_exr_file(tmp_path / "out.exr", out, max_bytes=max_bytes)
    assert (tmp_path / "out.exr").read_bytes() == whole_file_bytes(tmp_path / "whole.exr", out)
    write_exr_file(tmp_path / "same.exr", exr, max_bytes=max_bytes)
    assert (tmp_path / "same.exr").read_bytes() == (tmp_path / "in.exr").read_bytes()


def test_replaced_layer_is_converted_when_written(tmp_path: Path, rng: np.random.Generator) -> None:
    """replace_layer keeps a reference to the result; writing a 512x512 file converts it a block
    of rows at a time (whole planes of the colour layer alone: 3 MB)."""
    import tracemalloc

    from imaging.exr_layers import ImagePlane

    OpenEXR.File({}, {c: np.zeros((512, 512), np.float16) for c in "RGB"}).write(str(tmp_path / "in.exr"))
    exr = read_exr_file(tmp_path / "in.exr")
    image = rng.random((512, 512, 3), dtype=np.float32) * 1e5
    max_bytes = 128 * 2**10
    tracemalloc.start()
    try:
        out = replace_layer(exr, pick_color_layer(exr), image)
        write_exr_file(tmp_path / "out.exr", out, max_bytes=max_bytes)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < max_bytes + 64 * 2**10
    plane = out.parts[0].channels["G"]
    assert isinstance(plane, ImagePlane) and plane.dtype == np.float16 and plane.shape == (512, 512)
    back = read_exr_file(tmp_path / "out.exr").parts[0].channels["G"]
    assert back.dtype == np.float16 and np.array_equal(back, np.asarray(plane))
    assert np.array_equal(back, np.minimum(image[:, :, 1], 65504).astype(np.float16))


def test_the_bare_rgb_wins_over_a_named_colour_layer(tmp_path: Path, rng: np.random.Generator) -> None:
    OpenEXR.File({}, {**planes(rng, "", "RGB"), **planes(rng, "color", "RGB")}).write(str(tmp_path / "b.exr"))
    assert pick_color_layer(read_exr_file(tmp_path / "b.exr")).name == ""


def test_aux_layers_beside_the_chosen_colour_layer(tmp_path: Path, rng: np.random.Generator) -> None:
    """Two view layers, each with its denoising albedo: the albedo of the picked view layer; with
    two albedos beside it, none."""
    channels = {**planes(rng, "A.Combined", "RGB"), **planes(rng, "A.Denoising Albedo", "RGB"),
                **planes(rng, "B.Combined", "RGB"), **planes(rng, "B.Denoising Albedo", "RGB")}
    OpenEXR.File({}, dict(channels)).write(str(tmp_path / "two.exr"))
    exr = read_exr_file(tmp_path / "two.exr")
    for view in ("A", "B"):
        color = pick_color_layer(exr, f"{view}.Combined")
        assert find_aux_layer(exr, ALBEDO_WORDS, color, ("rgb",)).name == f"{view}.Denoising Albedo"
    OpenEXR.File({}, {**channels, **planes(rng, "A.albedo", "RGB")}).write(str(tmp_path / "three.exr"))
    exr = read_exr_file(tmp_path / "three.exr")
    assert find_aux_layer(exr, ALBEDO_WORDS, pick_color_layer(exr, "A.Combined"), ("rgb",)) is None
    assert find_aux_layer(exr, ALBEDO_WORDS, pick_color_layer(exr, "B.Combined"), ("rgb",)).name == \
        "B.Denoising Albedo"


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_a_taken_layer_is_held_once_and_written_back_as_read(tmp_path: Path, rng: np.random.Generator,
                                                            dtype: type) -> None:
    """ExrFile.take_image: the layer's float32 pixels, which then also stand for its channels in the
    file (views, no second copy); the file written back holds the channels it was read with."""
    channels = {**planes(rng, "", "RGB", dtype), **planes(rng, "variance", "Y", dtype)}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, dict(channels)).write(str(tmp_path / "in.exr"))
    exr = read_exr_file(tmp_path / "in.exr")
    rgb = exr.take_image(exr.layers[""])
    var = exr.take_image(exr.layers["variance"], 3)
    assert rgb.dtype == var.dtype == np.float32 and rgb.shape == var.shape == (H, W, 3)
    assert np.array_equal(var[:, :, 2], channels["variance.Y"].astype(np.float32))
    held = exr.parts[0].channels
    assert all(held[c].image is rgb for c in "RGB") and held["variance.Y"].image is var
    assert exr.is_half(exr.layers[""]) == (dtype == np.float16)
    write_exr_file(tmp_path / "out.exr", exr)
    back = read_exr_file(tmp_path / "out.exr").parts[0].channels
    for name, pixels in channels.items():
        assert back[name].dtype == pixels.dtype and np.array_equal(back[name], pixels), name
