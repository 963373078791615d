"""Serialise a Mitsuba 3 scene dict to Mitsuba XML, and write a generated scene to a folder.

Mitsuba 3.9 loads dicts but cannot write them back, so this is our own serializer for the value
kinds our generators use:

- nested plugin dicts (``{'type': 'diffuse', ...}``): the XML tag comes from Mitsuba's plugin
  registry; top-level plugins get ``id=<key>``, nested ones ``name=<key>``;
- ``{'type': 'rgb', 'value': v}`` -> ``<rgb>``; ``{'type': 'ref', 'id': i}`` -> ``<ref>``;
- bool -> ``<boolean>``, int -> ``<integer>``, float -> ``<float>`` written with ``repr`` so it
  parses back to the identical value, str -> ``<string>``;
- 3-sequences of numbers -> ``<point>`` (for position-like names) or ``<vector>``;
- ``drjit.scalar.Matrix4f`` or ``mi.ScalarTransform4f`` -> ``<transform><matrix .../></transform>``
  (row-major, 16 values).

The first film's width/height and the first sampler's sample count become the ``$resx``,
``$resy`` and ``$spp`` parameters (with their values as ``<default>``), as in our eval scenes.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import write_bytes_atomic, write_text_atomic
from rendering.backend import select_variant
from imaging.exr import write_exr
from scenes.spec import GeneratedScene, check_asset_name

_TAGS = {
    "Scene": "scene", "Sensor": "sensor", "Film": "film", "Emitter": "emitter",
    "Sampler": "sampler", "Shape": "shape", "Texture": "texture", "Volume": "volume",
    "Medium": "medium", "BSDF": "bsdf", "Integrator": "integrator",
    "PhaseFunction": "phase", "ReconstructionFilter": "rfilter",
}
_POINT_NAMES = {"position", "center", "origin", "target", "p0", "p1"}
RESOLUTION_PARAMS = ("resx", "resy")
SPP_PARAM = "spp"


def plugin_tag(plugin_type: str) -> str:
    """XML tag of a Mitsuba plugin type, e.g. ``'roughplastic'`` -> ``'bsdf'``."""
    select_variant()  # Mitsuba/Dr.Jit load libLLVM on import: choose it first
    import mitsuba as mi

    kind = mi.PluginManager.instance().plugin_type(plugin_type)
    tag = _TAGS.get(kind.name)
    if tag is None:
        raise ValueError(f"unknown Mitsuba plugin type {plugin_type!r}")
    return tag


def format_float(x: float) -> str:
    """Shortest text that parses back to exactly ``x``."""
    x = float(x)
    if not np.isfinite(x):
        raise ValueError(f"cannot write the non-finite float {x!r} to a scene file")
    return repr(x)


def _matrix_values(value: Any) -> list[float] | None:
    """Row-major entries of a 4x4 Dr.Jit matrix or of a transform's ``matrix``, else None."""
    if isinstance(value, (int, float, str, bool, Mapping, np.generic)):
        return None
    select_variant()
    import drjit as dr

    matrix_types = (dr.scalar.Matrix4f, dr.scalar.Matrix4f64)
    matrix = value if isinstance(value, matrix_types) else getattr(value, "matrix", None)
    if isinstance(matrix, matrix_types):  # mi.ScalarTransform4f has .matrix
        return np.array(matrix, dtype=np.float64).ravel().tolist()
    return None


def _is_triple(value: Any) -> bool:
    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, (Sequence, np.ndarray)):
        return False
    return len(value) == 3 and all(isinstance(v, (int, float, np.number)) and not isinstance(v, bool)
                                   for v in value)


def _add_value(parent: ET.Element, key: str, value: Any, path: str) -> None:
    attrs = {"name": key}
    if isinstance(value, Mapping):
        _add_plugin(parent, key, value, path, top_level=False)
    elif isinstance(value, (bool, np.bool_)):
        ET.SubElement(parent, "boolean", attrs, value="true" if value else "false")
    elif isinstance(value, (int, np.integer)):
        ET.SubElement(parent, "integer", attrs, value=str(int(value)))
    elif isinstance(value, (float, np.floating)):
        ET.SubElement(parent, "float", attrs, value=format_float(value))
    elif isinstance(value, str):
        ET.SubElement(parent, "string", attrs, value=value)
    elif (matrix := _matrix_values(value)) is not None:
        transform = ET.SubElement(parent, "transform", attrs)
        ET.SubElement(transform, "matrix", value=" ".join(format_float(v) for v in matrix))
    elif _is_triple(value):
        tag = "point" if key in _POINT_NAMES else "vector"
        ET.SubElement(parent, tag, attrs, value=", ".join(format_float(v) for v in value))
    else:
        raise TypeError(f"{path}: cannot write a value of type {type(value).__name__} to XML")


def _add_plugin(parent: ET.Element, key: str, node: Mapping[str, Any], path: str,
                top_level: bool) -> None:
    kind = node.get("type")
    if not isinstance(kind, str):
        raise ValueError(f"{path}: nested dict without a string 'type'")
    attrs = {"id": key} if top_level else {"name": key}
    if kind == "rgb":
        value = node.get("value")
        values = [value] if isinstance(value, (int, float, np.number)) else list(value)
        ET.SubElement(parent, "rgb", {"name": key},
                      value=", ".join(format_float(v) for v in values))
        return
    if kind == "ref":
        ref_attrs = {"id": str(node["id"])} if top_level else {"name": key, "id": str(node["id"])}
        ET.SubElement(parent, "ref", ref_attrs)
        return
    elem = ET.SubElement(parent, plugin_tag(kind), {"type": kind, **attrs})
    for child_key, child in node.items():
        if child_key != "type":
            _add_value(elem, child_key, child, f"{path}.{child_key}")


def _parametrize(root: ET.Element) -> dict[str, str]:
    """Turn the first film's size and first sampler's count into $resx/$resy/$spp."""
    defaults: dict[str, str] = {}
    film = next(root.iter("film"), None)
    if film is not None:
        for prop, param in zip(("width", "height"), RESOLUTION_PARAMS):
            elem = next((c for c in film if c.get("name") == prop), None)
            if elem is not None:
                defaults[param] = elem.get("value", "")
                elem.set("value", f"${param}")
    sampler = next(root.iter("sampler"), None)
    if sampler is not None:
        elem = next((c for c in sampler if c.get("name") == "sample_count"), None)
        if elem is not None:
            defaults[SPP_PARAM] = elem.get("value", "")
            elem.set("value", f"${SPP_PARAM}")
    return defaults


def scene_to_xml(scene: Mapping[str, Any]) -> str:
    """Mitsuba XML text for a scene dict (``type`` must be ``'scene'``)."""
    if scene.get("type") != "scene":
        raise ValueError(f"expected a dict with type 'scene', got type {scene.get('type')!r}")
    root = ET.Element("scene", version="3.0.0")
    for key, value in scene.items():
        if key == "type":
            continue
        if isinstance(value, Mapping):
            _add_plugin(root, key, value, key, top_level=True)
        else:
            _add_value(root, key, value, key)
    defaults = _parametrize(root)
    for i, (name, value) in enumerate(defaults.items()):
        root.insert(i, ET.Element("default", name=name, value=value))
    ET.indent(root, space="    ")
    return ET.tostring(root, encoding="unicode") + "\n"


def write_assets(gen: GeneratedScene, folder: Path) -> None:
    """Write every asset of ``gen`` under ``folder`` (arrays as float32 EXR, bytes as is)."""
    for name, content in gen.assets.items():
        check_asset_name(name)
        target = folder / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, np.ndarray):
            write_exr(target, content)
        else:
            write_bytes_atomic(target, content)


def write_scene(gen: GeneratedScene, folder: str | Path, name: str = "scene.xml") -> Path:
    """Write ``folder/name`` (Mitsuba XML) and every asset under ``folder``; return the XML path.

    Assets are written first and the XML last, each atomically, so a present scene file means a
    complete scene.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    xml = scene_to_xml(gen.scene)
    write_assets(gen, folder)
    path = folder / name
    write_text_atomic(path, xml)
    return path
