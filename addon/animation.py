"""Frame changes and edits -> the events an incremental final-render job takes between frames.

An incremental job (`pipeline.IncrementalJob`) keeps a `GISession` across the frames of one
render. It registers here under a key; two handlers then note, cheaply, what Blender says changed
(`updates.py` reads it):

| handler | what it notes |
|---|---|
| `frame_change_post` | the animated objects' world boxes (moved or deformed), animated lamps/world |
| `depsgraph_update_post` | edited objects' world boxes, lamp/world/material edits, other edits |

No handler builds a snapshot: the job takes the events (`take_events`) when it renders its next
frame; `GISession.sync` computes the exact diff and raises the cache's events itself, and the job
adds the swept boxes (every place an object passed through between two frames) of what the diff
confirms moved.

Main thread for the handlers; the registry itself is guarded by a lock.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field

import bpy
import numpy as np
from bpy.app.handlers import persistent

from . import updates

log = logging.getLogger(__name__)


@dataclass
class CacheEvents:
    """What changed since the owner last took its events.

    frame : the latest frame the scene changed to (None: no frame change)
    moved : names of objects that moved or deformed
    swept : per moved object, the world (lo, hi) float32 (3,) box around every place the
        handlers saw it since the events were last taken (bounded however long nobody takes them)
    lights : a lamp, the world or a material changed
    edited : some other edit (objects added or removed, keyframes, settings)
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

    def note_moved(self, name: str, box: tuple[np.ndarray, np.ndarray]) -> None:
        self.moved.add(name)
        old = self.swept.get(name)
        self.swept[name] = box if old is None else (np.minimum(old[0], box[0]), np.maximum(old[1], box[1]))


@dataclass
class LiveSession:
    session: object  # hybridgi_core.session.GISession
    scene: str | None  # name_full of the scene whose handlers feed it; None: every scene
    on_drop: Callable[[], None] | None
    events: CacheEvents = field(default_factory=CacheEvents)
    #: Animated object names of `scene`, cached between frames; None = recompute on next use.
    animated: frozenset[str] | None = None


_lock = threading.Lock()
_live: dict[Hashable, LiveSession] = {}


# --- registry ----------------------------------------------------------------------------------


def register_session(key: Hashable, session, scene: str | None = None,
                     on_drop: Callable[[], None] | None = None) -> None:
    """Feed `session` the events of `scene` (a scene's name_full; None for all) from now on.

    on_drop : called when the registry lets go of the session (`unregister_session`, a file load,
        the add-on's unregister): the owner closes what it owns there. Re-registering a key
        replaces the old entry without calling its on_drop.
    """
    with _lock:
        _live[key] = LiveSession(session, scene, on_drop)


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


def reset() -> None:
    """Drop every live session (calling each on_drop): the file they belong to is going away."""
    for key in list(_live):
        unregister_session(key)


def render_job_key(scene_name: str, view_layer: str) -> tuple[str, str, str]:
    """Registry key of the incremental final-render job of a scene's view layer (see pipeline.py):
    each view layer renders its own objects, so each keeps its own cache between frames."""
    return ("render", scene_name, view_layer)


# --- handlers (main thread; cheap: names and boxes, never a snapshot) ---------------------------


def _entries_for(scene) -> list[LiveSession]:
    name = scene.name_full
    with _lock:
        return [e for e in _live.values() if e.scene is None or e.scene == name]


@persistent
def on_frame_change_post(scene, depsgraph=None) -> None:
    """Note the animated objects' new boxes and animated lamps."""
    entries = _entries_for(scene)
    if not entries:
        return
    depsgraph = depsgraph if depsgraph is not None else bpy.context.evaluated_depsgraph_get()
    frame = scene.frame_current
    for entry in entries:
        if entry.animated is None:
            entry.animated = updates.animated_object_names(scene.objects)
        boxes, lights = updates.animated_boxes(scene, depsgraph, entry.animated)
        with _lock:
            ev = entry.events
            ev.frame = frame
            for name, box in boxes.items():
                ev.note_moved(name, box)
            ev.lights |= lights


@persistent
def on_depsgraph_update_post(scene, depsgraph) -> None:
    """Note edited objects (boxes), lamp/world/material edits and other edits."""
    entries = _entries_for(scene)
    if not entries:
        return
    c = updates.classify_updates(depsgraph)
    if not (c.boxes or c.shading or c.relink):
        return
    for entry in entries:
        with _lock:
            ev = entry.events
            for name, box in c.boxes.items():
                ev.note_moved(name, box)
            ev.lights |= c.shading
            ev.edited |= c.relink
            if c.relink:
                entry.animated = None


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
