"""Blender's notices of change, read in one place: depsgraph updates classified once for the
viewport and the frame handlers, what is animated, and the evaluated boxes of moved objects.

`sync.py` reads the scene's content into a snapshot; this module reads what Blender says changed,
so that the add-on's other modules (viewport, animation handlers, final renders) read no scene
data themselves. The exact change (moved, deformed, appeared...) is the core's snapshot diff
(`hybridgi_core.changes`); these notices only decide when a new snapshot, or which part of one,
is worth its cost. Main thread only: everything here reads `bpy`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import bpy
import numpy as np

from . import compat

#: Object types whose evaluated geometry may become triangles (the sync converts the mesh
#: instances they evaluate to; lamps and cameras never do).
GEOMETRY_TYPES = frozenset({"MESH", "CURVE", "CURVES", "SURFACE", "META", "FONT", "POINTCLOUD", "VOLUME",
                            "GREASEPENCIL"})
#: Geometry-nodes inputs that make a node tree's output change with the frame by itself.
TIME_NODES = frozenset({"GeometryNodeInputSceneTime", "GeometryNodeSimulationInput"})


# --- depsgraph updates -------------------------------------------------------------------------


@dataclass
class DepsgraphUpdates:
    """What one set of `depsgraph.updates` asks for.

    full : only a whole new snapshot expresses it (geometry data edited, instancers, objects added,
        deleted, hidden or shown, a material slot changed)
    moved : plain object name -> (4, 4) float64 world matrix, for objects only moved
    moved_ids : plain object name -> `object_id` of the object moved: a rename sends no update,
        so a name may have passed to another object since the last full snapshot
    boxes : object name -> world (lo, hi) box of every geometry object moved or edited
    lights, world, materials : lamps / the world / materials changed; material_names : which
        materials to read again (None = all: an image or a node group changed)
    relink : keyframes, collections or scene settings changed: what is animated may differ
    """

    full: bool = False
    moved: dict = field(default_factory=dict)
    moved_ids: dict = field(default_factory=dict)
    boxes: dict = field(default_factory=dict)
    lights: bool = False
    world: bool = False
    materials: bool = False
    material_names: set | None = field(default_factory=set)
    relink: bool = False

    @property
    def shading(self) -> bool:
        return self.lights or self.world or self.materials

    @property
    def any(self) -> bool:
        return self.full or bool(self.moved) or bool(self.boxes) or self.shading or self.relink


def classify_updates(depsgraph, structure_key=None) -> DepsgraphUpdates:
    """Read `depsgraph.updates` (only valid inside view_update / depsgraph handlers).

    structure_key : `scene_structure` of the last full snapshot; when given, a collection or scene
        update that changed the instances asks for a full snapshot.
    """
    c = DepsgraphUpdates()
    shading_only = False
    structure = False
    node_trees = False
    geometry_edited = compat.geometry_edited_objects(depsgraph)
    for update in depsgraph.updates:
        id_ = update.id
        if isinstance(id_, bpy.types.Object):
            if id_.type == "LIGHT":
                c.lights = True
            elif id_.type in GEOMETRY_TYPES:
                if id_.name in geometry_edited or update.is_updated_transform:
                    box = world_box(id_)
                    if box is not None:
                        c.boxes[id_.name] = box
                if id_.name in geometry_edited or id_.is_instancer:
                    c.full = True
                elif update.is_updated_transform:
                    c.moved[id_.name] = np.array(id_.matrix_world, np.float64)
                    c.moved_ids[id_.name] = object_id(id_)
                elif update.is_updated_shading:
                    shading_only = True  # a material slot changed, or a material edit (below)
            elif update.is_updated_transform and id_.is_instancer:
                c.full = True  # a collection instance moved: its instances are not plain objects
        elif isinstance(id_, bpy.types.Light):
            c.lights = True
        elif isinstance(id_, bpy.types.World):
            c.world = True
        elif isinstance(id_, bpy.types.Material):
            c.materials = True
            if c.material_names is not None:
                c.material_names.add(id_.name)
        elif isinstance(id_, bpy.types.Image):
            c.materials, c.material_names = True, None
            c.world = True  # an environment texture
        elif isinstance(id_, bpy.types.NodeTree):
            node_trees = True  # a material's or world's own tree comes with that ID's update
        elif isinstance(id_, bpy.types.Action):
            c.relink = True  # keyframes added or removed: what is animated may differ
        elif isinstance(id_, (bpy.types.Scene, bpy.types.Collection)):
            structure = c.relink = True
        elif isinstance(id_, bpy.types.ID) and update.is_updated_geometry and not isinstance(id_, bpy.types.Camera):
            c.full = True  # mesh, curve, text... data edited
    if node_trees and not (c.materials or c.world):
        c.materials, c.material_names, c.world = True, None, True  # a node group: any user may change
    if shading_only and not c.materials:
        c.full = True
    if structure and structure_key is not None and not c.full and scene_structure(depsgraph) != structure_key:
        c.full = True  # objects added, deleted, hidden or shown
    return c


def scene_structure(depsgraph) -> tuple:
    """What a full snapshot depends on besides data edits: the instances and their visibility."""
    return tuple(
        (inst.object.name, inst.object.type, inst.is_instance, inst.show_self,
         inst.parent.name if inst.is_instance and inst.parent is not None else "")
        for inst in depsgraph.object_instances
    )


def object_id(obj) -> int | None:
    """The object's identity for this Blender session, whatever its name (the original's
    `session_uid`: an evaluated copy's is 0); None where Blender has none."""
    return getattr(getattr(obj, "original", obj), "session_uid", None)


def plain_object_ids(depsgraph) -> dict[str, int | None]:
    """Name -> `object_id` of every plain (non-instanced) geometry object."""
    return {
        inst.object.name: object_id(inst.object)
        for inst in depsgraph.object_instances
        if not inst.is_instance and inst.object.type in GEOMETRY_TYPES
    }


def plain_object_matrices(depsgraph) -> dict[str, np.ndarray]:
    """Name -> (4, 4) float64 world matrix of every plain (non-instanced) geometry object: what a
    later move of one of them is applied relative to."""
    return {
        inst.object.name: np.array(inst.matrix_world, np.float64)
        for inst in depsgraph.object_instances
        if not inst.is_instance and inst.object.type in GEOMETRY_TYPES
    }


# --- what is animated --------------------------------------------------------------------------


def world_animated(world) -> bool:
    """Whether the world or its node tree has keyframes, drivers or NLA strips."""
    return world is not None and (has_animation(world) or has_animation(getattr(world, "node_tree", None)))


def has_animation(data) -> bool:
    anim = getattr(data, "animation_data", None)
    if anim is None:
        return False
    return anim.action is not None or len(anim.drivers) > 0 or len(anim.nla_tracks) > 0


def _animated_nodes(tree, seen: set) -> bool:
    """Whether a geometry-node tree (or a group inside it) reads the time or simulates."""
    if tree is None or tree.name_full in seen:
        return False
    seen.add(tree.name_full)
    if has_animation(tree):
        return True
    for node in tree.nodes:
        if node.bl_idname in TIME_NODES:
            return True
        if node.bl_idname == "GeometryNodeGroup" and _animated_nodes(node.node_tree, seen):
            return True
    return False


def _references(obj) -> Iterable:
    """Objects whose motion moves or deforms `obj`: parent, modifier and constraint targets."""
    if obj.parent is not None:
        yield obj.parent
    for mod in obj.modifiers:
        for attr in ("object", "target", "origin", "offset_object", "mirror_object", "auxiliary_target"):
            other = getattr(mod, attr, None)
            if isinstance(other, bpy.types.Object):
                yield other
    for con in obj.constraints:
        target = getattr(con, "target", None)
        if isinstance(target, bpy.types.Object):
            yield target
        for sub in getattr(con, "targets", ()):  # the Armature constraint
            if isinstance(getattr(sub, "target", None), bpy.types.Object):
                yield sub.target


def _self_animated(obj) -> bool:
    if has_animation(obj):
        return True
    data = obj.data
    if data is not None:
        if has_animation(data):  # lamp energy, curve bevel, ...
            return True
        keys = getattr(data, "shape_keys", None)
        if keys is not None and has_animation(keys):
            return True
    return any(mod.type == "NODES" and _animated_nodes(mod.node_group, set()) for mod in obj.modifiers)


def animated_object_names(objects: Iterable) -> frozenset[str]:
    """Names of the objects that move or deform over the animation (main thread).

    An object is animated when it, its data or its shape keys have keyframes, drivers or NLA
    strips, when a geometry-nodes modifier reads the scene time or simulates, or when something
    it follows (parent, armature or other modifier object, constraint target) is animated. What
    this misses (a Python handler moving objects) the session's diff still catches: the object
    becomes dynamic after its first move, at the cost of one ray-scene rebuild.
    """
    objects = list(objects)
    state: dict[str, bool] = {}

    def visit(obj) -> bool:
        name = obj.name_full
        if name in state:
            return state[name]
        state[name] = False  # a dependency cycle counts as not animated
        result = _self_animated(obj) or any(visit(other) for other in _references(obj))
        state[name] = result
        return result

    return frozenset(obj.name for obj in objects if visit(obj))


def world_box(obj) -> tuple[np.ndarray, np.ndarray] | None:
    """World-space (lo, hi) float32 of an (evaluated) object's bounding box; None without geometry."""
    if obj.type not in GEOMETRY_TYPES:
        return None
    corners = np.array([tuple(c) for c in obj.bound_box], np.float64)
    m = np.array(obj.matrix_world, np.float64)
    world = corners @ m[:3, :3].T + m[:3, 3]
    return world.min(axis=0).astype(np.float32), world.max(axis=0).astype(np.float32)


def animated_boxes(scene, depsgraph, names: frozenset[str]) -> tuple[dict, bool]:
    """({name: evaluated world box} of the animated geometry objects named, whether an animated
    lamp or the world may have changed the light) at the current frame."""
    boxes, lights = {}, world_animated(scene.world)
    for name in names:
        obj = scene.objects.get(name)
        if obj is None:
            continue
        if obj.type == "LIGHT":
            lights = True
            continue
        box = world_box(obj.evaluated_get(depsgraph))
        if box is not None:
            boxes[name] = box
    return boxes, lights
