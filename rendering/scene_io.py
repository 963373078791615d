"""Turn a scene file or dict into Mitsuba XML/dict ready for denoiser-grade rendering.

Every render that feeds the denoiser or serves as its reference gets a known pixel filter and a
float32 film, whatever the scene says: a *box* by default, because Mitsuba's default gaussian filter
correlates neighbouring pixels' noise, which a box-trained denoiser then cannot remove. A dataset
made for a studio's own filter names it (``pixel_filter``, :func:`pixel_filter_spec`), and its
renders and references then use that filter. Scene files often keep the film in an ``<include>``d
file, so includes are inlined first and every film is rewritten.
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from imaging.errors import SceneError

# AOV names we know how to render, mapped to Mitsuba's aov-integrator type and channel suffixes.
AOV_TYPES: dict[str, tuple[str, tuple[str, str, str]]] = {
    "albedo": ("albedo", ("R", "G", "B")),
    "sh_normal": ("sh_normal", ("X", "Y", "Z")),
}
SENSOR_TYPES = {"perspective", "thinlens", "orthographic", "telecentric", "radiancemeter",
                "irradiancemeter", "batch", "fisheye"}
_PARAM_RE = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
# Mitsuba 3's pixel filters with their parameters' defaults (mitsuba.readthedocs.io, "Reconstruction
# filters"), and the class name each loads as. Mitsuba 3 has no Blackman-Harris filter.
PIXEL_FILTERS: dict[str, dict[str, float]] = {
    "box": {}, "tent": {}, "gaussian": {"stddev": 0.5}, "mitchell": {"B": 1 / 3, "C": 1 / 3},
    "catmullrom": {}, "lanczos": {"lobes": 3},
}
FILTER_CLASSES = {"box": "BoxFilter", "tent": "TentFilter", "gaussian": "GaussianFilter",
                  "mitchell": "MitchellNetravaliFilter", "catmullrom": "CatmullRomFilter",
                  "lanczos": "LanczosSincFilter"}
_INTEGER_FILTER_PARAMS = {"lobes"}
BOX = {"type": "box"}


def pixel_filter_spec(value: str | Mapping[str, Any] | None) -> dict[str, Any]:
    """The canonical pixel filter {"type": NAME, PARAM: value, ...} (every parameter present, its
    default filled in) of ``value``: None or "box"; a name ("gaussian"); "NAME:PARAM=V,..."
    ("gaussian:stddev=0.3"); or such a dict. Raises :class:`SceneError` naming the valid filters
    or parameters."""
    if value is None:
        return dict(BOX)
    if isinstance(value, str):
        name, _, params = value.partition(":")
        given: dict[str, Any] = {}
        for item in filter(None, (p.strip() for p in params.split(","))):
            key, eq, number = item.partition("=")
            try:
                given[key.strip()] = float(number) if eq else None
            except ValueError:
                given[key.strip()] = None
            if given[key.strip()] is None:
                raise SceneError(f"pixel filter {value!r}: expected NAME or NAME:PARAM=NUMBER,..., got {item!r}")
        value = {"type": name.strip(), **given}
    if not isinstance(value, Mapping) or value.get("type") not in PIXEL_FILTERS:
        name = value.get("type") if isinstance(value, Mapping) else value
        raise SceneError(f"unknown pixel filter {name!r} (valid: {', '.join(PIXEL_FILTERS)})")
    kind = value["type"]
    defaults = PIXEL_FILTERS[kind]
    unknown = sorted(set(value) - {"type"} - set(defaults))
    if unknown:
        raise SceneError(f"pixel filter {kind!r} has no parameter {unknown[0]!r} "
                         f"(it takes: {', '.join(defaults) or 'none'})")
    spec: dict[str, Any] = {"type": kind}
    for key, default in defaults.items():
        number = value.get(key, default)
        if isinstance(number, bool) or not isinstance(number, (int, float)) or not number > 0:
            raise SceneError(f"pixel filter {kind!r}: {key} must be a number > 0, got {number!r}")
        spec[key] = int(number) if key in _INTEGER_FILTER_PARAMS else float(number)
    return spec


def _filter_xml(spec: Mapping[str, Any]) -> ET.Element:
    element = ET.Element("rfilter", {"type": spec["type"]})
    for key, value in spec.items():
        if key != "type":
            tag = "integer" if key in _INTEGER_FILTER_PARAMS else "float"
            ET.SubElement(element, tag, {"name": key, "value": str(value)})
    return element


@dataclass
class PreparedScene:
    """A scene description ready for ``mi.load_string``/``mi.load_dict``.

    ``xml`` is set for file scenes (with ``search_paths`` for the file resolver and ``params`` for
    ``$name`` substitution), ``scene_dict`` for dict scenes. ``source`` names it in messages;
    ``pixel_filter`` is the filter its films were given (:func:`pixel_filter_spec`).
    """

    source: str
    xml: str | None = None
    scene_dict: dict[str, Any] | None = None
    search_paths: list[Path] = field(default_factory=list)
    params: dict[str, str] = field(default_factory=dict)
    pixel_filter: dict[str, Any] = field(default_factory=lambda: dict(BOX))


def check_aovs(aovs: Sequence[str]) -> None:
    """Raise :class:`SceneError` for an AOV name not in :data:`AOV_TYPES`."""
    unknown = [a for a in aovs if a not in AOV_TYPES]
    if unknown:
        raise SceneError(f"unknown AOV {unknown[0]!r} (known: {', '.join(AOV_TYPES)})")


def aov_spec(aovs: Sequence[str]) -> str:
    """The aov integrator's ``aovs`` string, e.g. ``albedo:albedo,sh_normal:sh_normal``."""
    return ",".join(f"{name}:{AOV_TYPES[name][0]}" for name in aovs)


# ----------------------------------------------------------------------------- XML scenes
def _parse(path: Path, source: str) -> ET.Element:
    if not path.exists():
        raise SceneError(f"{path}: file not found" + ("" if source == str(path) else f" (from {source})"))
    if path.is_dir():
        raise SceneError(f"{path}: is a directory, not a scene file")
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"{path}: malformed XML ({exc})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: cannot read ({exc})") from None


def _inline_includes(root: ET.Element, base: Path, scene_dir: Path, seen: tuple[Path, ...]) -> None:
    for parent in list(root.iter()):
        for idx, child in reversed(list(enumerate(list(parent)))):
            if child.tag != "include":
                continue
            name = child.get("filename", "")
            target = next((p for p in (base / name, scene_dir / name) if p.exists()), base / name)
            target = target.resolve()
            if target in seen:
                raise SceneError(f"{seen[-1]}: include cycle through {target}")
            included = _parse(target, str(seen[-1]))
            _inline_includes(included, target.parent, scene_dir, seen + (target,))
            parent.remove(child)
            for offset, grandchild in enumerate(list(included)):
                parent.insert(idx + offset, grandchild)


def _remove_property(elem: ET.Element, name: str) -> None:
    for child in list(elem):
        if child.get("name") == name:
            elem.remove(child)


def _set_property(elem: ET.Element, tag: str, name: str, value: str) -> None:
    _remove_property(elem, name)
    ET.SubElement(elem, tag, {"name": name, "value": value})


def _fix_film(film: ET.Element, resolution: tuple[int, int] | None, pixel_filter: Mapping[str, Any]) -> None:
    for child in list(film):
        if child.tag == "rfilter":
            film.remove(child)
    film.append(_filter_xml(pixel_filter))
    _set_property(film, "string", "component_format", "float32")
    _set_property(film, "string", "pixel_format", "rgb")
    if resolution is not None:
        for crop in ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"):
            _remove_property(film, crop)
        _set_property(film, "integer", "width", str(resolution[0]))
        _set_property(film, "integer", "height", str(resolution[1]))


def _fix_sensors(root: ET.Element, resolution: tuple[int, int] | None, source: str,
                 pixel_filter: Mapping[str, Any]) -> None:
    sensors = [e for e in root.iter("sensor")]
    if not sensors:
        raise SceneError(f"{source}: the scene has no <sensor> (a camera is required)")
    for sensor in sensors:
        films = [c for c in sensor if c.tag == "film"]
        if not films:
            films = [ET.SubElement(sensor, "film", {"type": "hdrfilm"})]
        for film in films:
            _fix_film(film, resolution, pixel_filter)


def _wrap_integrator_xml(root: ET.Element, aovs: Sequence[str]) -> None:
    if not aovs:
        return
    inner = next((c for c in root if c.tag == "integrator"), None)
    position = list(root).index(inner) if inner is not None else 0
    if inner is None:
        inner = ET.Element("integrator", {"type": "path"})
    else:
        root.remove(inner)
    wrapper = ET.Element("integrator", {"type": "aov"})
    ET.SubElement(wrapper, "string", {"name": "aovs", "value": aov_spec(aovs)})
    wrapper.append(inner)
    root.insert(position, wrapper)


def declared_params(xml: str) -> set[str]:
    """Names of the ``$name`` parameters an XML scene uses."""
    return set(_PARAM_RE.findall(xml))


def prepare_xml(
    path: str | Path,
    resolution: tuple[int, int] | None = None,
    aovs: Sequence[str] = (),
    params: Mapping[str, Any] | None = None,
    pixel_filter: str | Mapping[str, Any] | None = None,
) -> PreparedScene:
    """Read ``path``, inline its includes, force the pixel filter (a box unless ``pixel_filter``
    names another, :func:`pixel_filter_spec`) + float32 film on every sensor.

    ``resolution`` is (width, height) in pixels; ``aovs`` names extra buffers (see AOV_TYPES);
    ``params`` fills ``$name`` parameters, each of which the scene must use.
    """
    check_aovs(aovs)
    spec = pixel_filter_spec(pixel_filter)
    path = Path(path)
    root = _parse(path, str(path))
    if root.tag != "scene":
        raise SceneError(f"{path}: root element is <{root.tag}>, expected <scene>")
    scene_dir = path.resolve().parent
    _inline_includes(root, scene_dir, scene_dir, (path.resolve(),))
    _fix_sensors(root, resolution, str(path), spec)
    _wrap_integrator_xml(root, aovs)
    xml = ET.tostring(root, encoding="unicode")
    known = declared_params(xml) | {d.get("name", "") for d in root.iter("default")}
    params = {k: str(v) for k, v in (params or {}).items()}
    for name in params:
        if name not in known:
            raise SceneError(f"{path}: --param {name!r} is not a parameter of this scene "
                             f"(it declares: {', '.join(sorted(known)) or 'none'})")
    search = sorted({scene_dir} | {p.parent for p in scene_dir.rglob('*.xml')}, key=str)[:16]
    return PreparedScene(source=str(path), xml=xml, search_paths=search, params=params, pixel_filter=spec)


# ----------------------------------------------------------------------------- dict scenes
def _fixed_film(film: dict[str, Any] | None, resolution: tuple[int, int] | None,
               pixel_filter: Mapping[str, Any]) -> dict[str, Any]:
    film = dict(film or {"type": "hdrfilm"})
    film["rfilter"] = dict(pixel_filter)
    film["component_format"] = "float32"
    film["pixel_format"] = "rgb"
    if resolution is not None:
        for crop in ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"):
            film.pop(crop, None)
        film["width"], film["height"] = int(resolution[0]), int(resolution[1])
    return film


def _copy_dicts(value: Any) -> Any:
    """Copy the nested dicts (and lists) of a scene dict; plugin objects/transforms are shared."""
    if isinstance(value, Mapping):
        return {k: _copy_dicts(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy_dicts(v) for v in value]
    return value


def prepare_dict(
    scene: Mapping[str, Any],
    resolution: tuple[int, int] | None = None,
    aovs: Sequence[str] = (),
    source: str = "<dict scene>",
    base_dir: str | Path | None = None,
    pixel_filter: str | Mapping[str, Any] | None = None,
) -> PreparedScene:
    """Copy a Mitsuba scene dict with the pixel filter (a box unless ``pixel_filter`` names another)
    + float32 film on every sensor (and AOVs).

    Relative asset file names in the dict resolve against ``base_dir`` when given.
    """
    check_aovs(aovs)
    spec = pixel_filter_spec(pixel_filter)
    d = _copy_dicts(scene)
    sensors = [k for k, v in d.items() if isinstance(v, dict) and v.get("type") in SENSOR_TYPES]
    if not sensors:
        raise SceneError(f"{source}: the scene has no sensor (a camera is required)")
    for key in sensors:
        d[key] = dict(d[key])
        film_key = next((k for k, v in d[key].items() if isinstance(v, dict)
                         and v.get("type") in ("hdrfilm", "film")), "film")
        d[key][film_key] = _fixed_film(d[key].get(film_key), resolution, spec)
    if aovs:
        inner_key = "integrator" if "integrator" in d else None
        inner = d.pop(inner_key) if inner_key else {"type": "path"}
        d["integrator"] = {"type": "aov", "aovs": aov_spec(aovs), "inner": inner}
    search = [Path(base_dir).resolve()] if base_dir is not None else []
    return PreparedScene(source=source, scene_dict=d, search_paths=search, pixel_filter=spec)
