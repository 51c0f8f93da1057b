"""Frame changes and edits -> named cache events for the live GI sessions that want them.

A live session is a `GISession` that outlives one frame: the viewport's, or an incremental final
render's. Its owner registers it here under a key; two handlers then note, cheaply, what changed:

| handler | what it notes |
|---|---|
| `frame_change_post` | the animated objects' world boxes (moved or deformed), animated lamps/world |
| `depsgraph_update_post` | edited objects' world boxes, lamp/world/material edits, other edits |

and ask the owner to refresh (its `refresh` callback, e.g. a redraw). No handler builds a
snapshot: the owner takes the events (`take_events`) when it next syncs on its own schedule, and
`GISession.sync` computes the exact diff itself. The events tell the owner whether a re-sync is
worth its cost, and `apply_events` lets it mark the cells around the noted boxes urgent before
that sync (the cache's `on_geometry_changed`: quadratic fall-off over the indirect range).

Main thread for everything that reads `bpy` (`animated_object_names`, the handlers). The registry
itself is guarded by a lock, so an owner's worker thread may take events.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Hashable, Iterable
from dataclasses import dataclass, field

import bpy
import numpy as np
from bpy.app.handlers import persistent

log = logging.getLogger(__name__)

#: Geometry-nodes inputs that make a node tree's output change with the frame by itself.
TIME_NODES = frozenset({"GeometryNodeInputSceneTime", "GeometryNodeSimulationInput"})


@dataclass
class CacheEvents:
    """What changed since the owner last took its events.

    frame : the latest frame the scene changed to (None: no frame change)
    moved : names of objects that moved or deformed
    swept : per moved object, the world (lo, hi) float32 (3,) box around every place the
        handlers saw it since the events were last taken (bounded however long nobody takes them)
    lights : a lamp, the world or a material changed (the cache's `on_lights_changed`)
    edited : some other edit (objects added or removed, settings): re-sync to find out
    """

    frame: int | None = None
    moved: set[str] = field(default_factory=set)
    swept: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    lights: bool = False
    edited: bool = False

    @property
    def dirty(self) -> bool:
        """Whether anything changed that a sync could see."""
        return self.frame is not None or bool(self.moved) or self.lights or self.edited

    @property
    def boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The swept boxes, as `IrradianceCache.on_geometry_changed` takes them."""
        return list(self.swept.values())

    def note_moved(self, name: str, box: tuple[np.ndarray, np.ndarray]) -> None:
        self.moved.add(name)
        old = self.swept.get(name)
        self.swept[name] = box if old is None else (np.minimum(old[0], box[0]), np.maximum(old[1], box[1]))


@dataclass
class LiveSession:
    session: object  # hybridgi_core.session.GISession
    scene: str | None  # name_full of the scene whose handlers feed it; None: every scene
    refresh: Callable[[], None] | None
    on_drop: Callable[[], None] | None
    events: CacheEvents = field(default_factory=CacheEvents)
    #: Animated object names of `scene`, cached between frames; None = recompute on next use.
    animated: frozenset[str] | None = None


_lock = threading.Lock()
_live: dict[Hashable, LiveSession] = {}


# --- registry ----------------------------------------------------------------------------------


def register_session(key: Hashable, session, scene: str | None = None,
                     refresh: Callable[[], None] | None = None,
                     on_drop: Callable[[], None] | None = None) -> None:
    """Feed `session` the events of `scene` (a scene's name_full; None for all) from now on.

    refresh : called on the main thread after events arrive (e.g. the viewport's `tag_redraw`);
        a ReferenceError from it (its Blender owner was freed) unregisters the session.
    on_drop : called when the registry lets go of the session (`unregister_session`, a file load,
        the add-on's unregister): the owner closes what it owns there. Re-registering a key
        replaces the old entry without calling its on_drop.
    """
    with _lock:
        _live[key] = LiveSession(session, scene, refresh, on_drop)


def unregister_session(key: Hashable):
    """Stop feeding the session under `key`; returns it (None if none), after its on_drop."""
    with _lock:
        entry = _live.pop(key, None)
    if entry is None:
        return None
    if entry.on_drop is not None:
        entry.on_drop()
    return entry.session


def live_session(key: Hashable):
    """The session registered under `key`, or None."""
    with _lock:
        entry = _live.get(key)
    return None if entry is None else entry.session


def take_events(key: Hashable) -> CacheEvents:
    """The events noted for `key` since the last call (empty if none or not registered)."""
    with _lock:
        entry = _live.get(key)
        if entry is None:
            return CacheEvents()
        events, entry.events = entry.events, CacheEvents()
    return events


def apply_events(session, events: CacheEvents) -> np.ndarray:
    """Mark the cells around the events' boxes urgent in the session's cache (numpy only, any
    thread that owns the session). Returns the touched flat cells (int64)."""
    system = getattr(session, "system", None)
    if system is None or not events.boxes:
        return np.zeros(0, np.int64)
    return system.cache.on_geometry_changed(events.boxes)


def reset() -> None:
    """Drop every live session (calling each on_drop): the file they belong to is going away."""
    for key in list(_live):
        unregister_session(key)


def render_job_key(scene_name: str) -> tuple[str, str]:
    """Registry key of the incremental final-render job of a scene (see pipeline.py)."""
    return ("render", scene_name)


# --- what is animated (main thread: reads bpy data) ---------------------------------------------


def _has_animation(data) -> bool:
    anim = getattr(data, "animation_data", None)
    if anim is None:
        return False
    return anim.action is not None or len(anim.drivers) > 0 or len(anim.nla_tracks) > 0


def _animated_nodes(tree, seen: set) -> bool:
    """Whether a geometry-node tree (or a group inside it) reads the time or simulates."""
    if tree is None or tree.name_full in seen:
        return False
    seen.add(tree.name_full)
    if _has_animation(tree):
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
    if _has_animation(obj):
        return True
    data = obj.data
    if data is not None:
        if _has_animation(data):  # lamp energy, curve bevel, ...
            return True
        keys = getattr(data, "shape_keys", None)
        if keys is not None and _has_animation(keys):
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


def _world_box(obj) -> tuple[np.ndarray, np.ndarray] | None:
    """World-space (lo, hi) of an (evaluated) object's bounding box; None without geometry."""
    if obj.type not in {"MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES", "POINTCLOUD", "VOLUME"}:
        return None
    corners = np.array([tuple(c) for c in obj.bound_box], np.float64)
    m = np.array(obj.matrix_world, np.float64)
    world = corners @ m[:3, :3].T + m[:3, 3]
    return world.min(axis=0).astype(np.float32), world.max(axis=0).astype(np.float32)


# --- handlers (main thread; cheap: names and boxes, never a snapshot) ---------------------------


def _entries_for(scene) -> list[tuple[Hashable, LiveSession]]:
    name = scene.name_full
    with _lock:
        return [(k, e) for k, e in _live.items() if e.scene is None or e.scene == name]


def _request_refresh(key: Hashable, entry: LiveSession) -> None:
    if entry.refresh is None:
        return
    try:
        entry.refresh()
    except ReferenceError:
        # The refresh callback belongs to a freed Blender object (a closed viewport's engine).
        log.debug("live session %r lost its owner; unregistering it", key)
        unregister_session(key)


@persistent
def on_frame_change_post(scene, depsgraph=None) -> None:
    """Note the animated objects' new boxes and animated lamps; request a refresh."""
    entries = _entries_for(scene)
    if not entries:
        return
    depsgraph = depsgraph if depsgraph is not None else bpy.context.evaluated_depsgraph_get()
    frame = scene.frame_current
    world_animated = scene.world is not None and (
        _has_animation(scene.world) or _has_animation(getattr(scene.world, "node_tree", None)))
    for key, entry in entries:
        if entry.animated is None:
            entry.animated = animated_object_names(scene.objects)
        boxes, lights = {}, world_animated
        for name in entry.animated:
            obj = scene.objects.get(name)
            if obj is None:
                continue
            if obj.type == "LIGHT":
                lights = True
                continue
            box = _world_box(obj.evaluated_get(depsgraph))
            if box is not None:
                boxes[name] = box
        with _lock:
            ev = entry.events
            ev.frame = frame
            for name, box in boxes.items():
                ev.note_moved(name, box)
            ev.lights |= lights
        _request_refresh(key, entry)


@persistent
def on_depsgraph_update_post(scene, depsgraph) -> None:
    """Note edited objects (boxes), lamp/world/material edits and other edits; request a refresh."""
    entries = _entries_for(scene)
    if not entries:
        return
    boxes = {}
    lights = edited = relink = False
    for update in depsgraph.updates:
        data = update.id
        if isinstance(data, bpy.types.Object):
            if data.type == "LIGHT":
                lights = True
            elif update.is_updated_transform or update.is_updated_geometry:
                box = _world_box(data)
                if box is not None:
                    boxes[data.name] = box
        elif isinstance(data, (bpy.types.Light, bpy.types.World, bpy.types.Material, bpy.types.ShaderNodeTree)):
            lights = True
        elif isinstance(data, (bpy.types.Action, bpy.types.Collection, bpy.types.Scene)):
            # Keyframes, objects added or removed, scene settings: what is animated may differ.
            edited = relink = True
    if not (boxes or lights or edited):
        return
    for key, entry in entries:
        with _lock:
            ev = entry.events
            for name, box in boxes.items():
                ev.note_moved(name, box)
            ev.lights |= lights
            ev.edited |= edited
            if relink:
                entry.animated = None
        _request_refresh(key, entry)


@persistent
def on_load_pre(*_args) -> None:
    """Sessions hold the closing file's scene: let their owners free them."""
    reset()


_HANDLERS = (
    ("frame_change_post", on_frame_change_post),
    ("depsgraph_update_post", on_depsgraph_update_post),
    ("load_pre", on_load_pre),
)


def register() -> None:
    for name, handler in _HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if handler not in handlers:
            handlers.append(handler)


def unregister() -> None:
    for name, handler in reversed(_HANDLERS):
        handlers = getattr(bpy.app.handlers, name)
        if handler in handlers:
            handlers.remove(handler)
    reset()
