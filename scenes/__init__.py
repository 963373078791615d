"""Procedural training scenes: families of Mitsuba scene dicts, and their XML export."""
from scenes.registry import FAMILIES, generate
from scenes.spec import GeneratedScene
from scenes.xml_export import scene_to_xml, write_scene

__all__ = ["FAMILIES", "GeneratedScene", "generate", "scene_to_xml", "write_scene"]
