"""What differs between the Blender versions the extension supports (4.2 LTS, 4.5 LTS, 5.0, 5.1+).

Every version check of the add-on lives here; the CLI, the scene builder and the tests have theirs
in `hybridgi_cli/blender_compat.py` (an installed extension ships without that package). Importing
this module does not import bpy (the worker's modules must stay importable without it).
"""

from __future__ import annotations

import functools

#: Blender 5.0 renamed four of Cycles' passes; HybridGI writes the names its Blender's Cycles uses,
#: so the EXRs of both engines compare layer by layer.
_PASS_NAMES_BEFORE_5_0 = {
    "Diffuse Direct": "DiffDir",
    "Diffuse Indirect": "DiffInd",
    "Diffuse Color": "DiffCol",
    "Ambient Occlusion": "AO",
    "Glossy Direct": "GlossDir",
    "Glossy Indirect": "GlossInd",
    "Glossy Color": "GlossCol",
}


@functools.cache
def version() -> tuple[int, int, int]:
    """(major, minor, patch) of the running Blender."""
    import bpy  # noqa: PLC0415

    return tuple(bpy.app.version)


def pass_name(name: str) -> str:
    """This Blender's name of the pass Blender 5.0 calls `name`."""
    return name if version() >= (5, 0, 0) else _PASS_NAMES_BEFORE_5_0.get(name, name)


def point_color_shader():
    """The builtin shader for points with a colour each (`pos`, `color`; size from point_size_set).
    Blender 4.2 has no POINT_FLAT_COLOR; its FLAT_COLOR draws points at the state's size."""
    import gpu  # noqa: PLC0415

    try:
        return gpu.shader.from_builtin("POINT_FLAT_COLOR")
    except ValueError:  # the names it accepts are an enum of that version's builtins
        return gpu.shader.from_builtin("FLAT_COLOR")


def light_options(light) -> tuple[bool, float, bool]:
    """(use_temperature, exposure, normalize) of a Blender light. Blender 4.2's lights have none of
    the three: no blackbody tint, exposure 0, area lights always normalized."""
    return (bool(getattr(light, "use_temperature", False)), float(getattr(light, "exposure", 0.0)),
            bool(getattr(light, "normalize", True)))


def light_casts_shadow(light) -> bool:
    """A light's "Shadow" checkbox: `use_shadow` since Blender 4.0 (before it Cycles kept its own
    `light.cycles.cast_shadow`, read where `use_shadow` is missing)."""
    if hasattr(light, "use_shadow"):
        return bool(light.use_shadow)
    return bool(getattr(getattr(light, "cycles", None), "cast_shadow", True))


def light_is_portal(light) -> bool:
    """An area light marked as a Portal (Cycles: it guides the sky's samples and emits nothing):
    `light.cycles.is_portal` in 4.2-5.0; a newer Blender's own `is_portal` where it has one."""
    if hasattr(light, "is_portal"):
        return bool(light.is_portal)
    return bool(getattr(getattr(light, "cycles", None), "is_portal", False))


def soft_falloff(light) -> bool:
    """A POINT/SPOT light's "Soft Falloff" (Cycles emits from a sphere when it is off). Blender 4.2
    has it (added in 4.1, Cycles commit 6ddb3f99b "Lights: Option to use old point light falloff");
    the fallback is its default on new lights, True."""
    return bool(getattr(light, "use_soft_falloff", True))


def geometry_edited_objects(depsgraph) -> frozenset:
    """Names of the objects whose geometry this depsgraph update changed (`is_updated_geometry`),
    inside view_update / depsgraph handlers.

    Blender 5.3 also flags the geometry of an object when one of its materials is edited; its data
    (mesh) is then in the same updates without the flag, while mesh and modifier edits flag both.
    """
    import bpy  # noqa: PLC0415

    updates = list(depsgraph.updates)
    flagged = [u.id for u in updates if isinstance(u.id, bpy.types.Object) and u.is_updated_geometry]
    if version() < (5, 3, 0) or not flagged:
        return frozenset(obj.name for obj in flagged)
    unchanged_data = {(type(u.id), u.id.name) for u in updates
                      if not isinstance(u.id, bpy.types.Object) and not u.is_updated_geometry}
    return frozenset(obj.name for obj in flagged
                     if obj.data is None or (type(obj.data), obj.data.name) not in unchanged_data)


def set_file_format(settings, file_format: str) -> None:
    """`ImageFormatSettings.file_format = file_format`. Blender 5.0 added `media_type`, which must
    name the kind of file before a format of that kind can be chosen."""
    if version() >= (5, 0, 0):
        settings.media_type = {"OPEN_EXR_MULTILAYER": "MULTI_LAYER_IMAGE", "FFMPEG": "VIDEO"}.get(file_format, "IMAGE")
    settings.file_format = file_format
