"""What differs between the Blender versions the extension supports (4.2 LTS, 4.5 LTS, 5.0, 5.1+).

Every version check of the add-on lives here; the CLI, the scene builder and the tests have theirs
in `hybridgi_cli/blender_compat.py` (an installed extension ships without that package).
"""

from __future__ import annotations

import bpy

#: (major, minor, patch) of the running Blender.
VERSION = tuple(bpy.app.version)

#: Blender 5.0 renamed four of Cycles' passes; HybridGI writes the names its Blender's Cycles uses,
#: so the EXRs of both engines compare layer by layer.
_PASS_NAMES_BEFORE_5_0 = {
    "Diffuse Direct": "DiffDir",
    "Diffuse Indirect": "DiffInd",
    "Diffuse Color": "DiffCol",
    "Ambient Occlusion": "AO",
}


def pass_name(name: str) -> str:
    """This Blender's name of the pass Blender 5.0 calls `name`."""
    return name if VERSION >= (5, 0, 0) else _PASS_NAMES_BEFORE_5_0.get(name, name)


def point_color_shader():
    """The builtin shader for points with a colour each (`pos`, `color`; size from point_size_set).
    Blender 4.2 has no POINT_FLAT_COLOR; its FLAT_COLOR draws points at the state's size."""
    import gpu  # noqa: PLC0415

    try:
        return gpu.shader.from_builtin("POINT_FLAT_COLOR")
    except ValueError:  # the names it accepts are an enum of that version's builtins
        return gpu.shader.from_builtin("FLAT_COLOR")


def geometry_edited_objects(depsgraph) -> frozenset:
    """Names of the objects whose geometry this depsgraph update changed (`is_updated_geometry`),
    inside view_update / depsgraph handlers.

    Blender 5.3 also flags the geometry of an object when one of its materials is edited; its data
    (mesh) is then in the same updates without the flag, while mesh and modifier edits flag both.
    """
    updates = list(depsgraph.updates)
    flagged = [u.id for u in updates if isinstance(u.id, bpy.types.Object) and u.is_updated_geometry]
    if VERSION < (5, 3, 0) or not flagged:
        return frozenset(obj.name for obj in flagged)
    unchanged_data = {(type(u.id), u.id.name) for u in updates
                      if not isinstance(u.id, bpy.types.Object) and not u.is_updated_geometry}
    return frozenset(obj.name for obj in flagged
                     if obj.data is None or (type(obj.data), obj.data.name) not in unchanged_data)
