"""A GI state that lives across frames and edits (viewport, animation playback).

`sync(snapshot)` compares the new snapshot with the last one and turns the difference into the
cache's named events, doing the least work that keeps the cache right:

| what changed | what happens |
|---|---|
| nothing | nothing |
| lamps, world, materials | shading inputs swapped; `cache.on_lights_changed()` |
| vertices of dynamic objects | dynamic Embree scene rebuilt; `cache.on_geometry_changed(boxes)` |
| vertices of a static object | it becomes dynamic (one rebuild of the ray scene), then as above |
| objects added/removed, topology, settings | ray scene rebuilt; the cache is kept when its settings are |

Pure numpy: it may run on a worker thread with snapshots made on the main thread.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import EmptySceneError
from .settings import CacheSettings
from .snapshot import SceneSnapshot
from .system import GISystem

log = logging.getLogger(__name__)


@dataclass
class SyncReport:
    rebuilt: bool = False
    moved: list[str] = field(default_factory=list)
    lights_changed: bool = False
    touched_cells: int = 0
    ms: float = 0.0


def _light_key(scene: SceneSnapshot) -> tuple:
    lights = tuple(
        (lt.kind, lt.color.tobytes(), float(lt.power), lt.matrix.tobytes(), lt.radius, lt.spot_size, lt.spot_blend,
         lt.angle, lt.shape, lt.size, lt.size_y)
        for lt in scene.lights
    )
    mats = tuple(
        (m.base_color.tobytes(), m.emission.tobytes(), None if m.texture is None else (m.texture.shape, float(m.texture.sum())))
        for m in scene.materials
    )
    return lights, mats, scene.world.color.tobytes(), float(scene.world.ao_distance)


def _topology_key(scene: SceneSnapshot) -> tuple:
    g = scene.geometry
    return (
        tuple(o.name for o in scene.objects),
        g.positions.shape,
        g.triangles.shape,
        hash(g.triangles.tobytes()),
        hash(g.object_index.tobytes()),
        hash(g.material_index.tobytes()),
    )


class GISession:
    """Owns a `GISystem` and keeps it in step with successive snapshots."""

    def __init__(self, settings: CacheSettings, dynamic_names: frozenset[str] = frozenset()):
        self.settings = settings
        #: Objects traced in the per-frame dynamic scene (animated, or moved once by the user).
        self.dynamic_names = set(dynamic_names)
        self.system: GISystem | None = None
        self.snapshot: SceneSnapshot | None = None
        self._topology = None
        self._lights = None

    def close(self) -> None:
        if self.system is not None:
            self.system.close()
            self.system = None

    def set_settings(self, settings: CacheSettings) -> None:
        """New settings take effect at the next sync (with a fresh cache when they differ)."""
        if settings != self.settings:
            self.settings = settings
            self._topology = None

    def sync(self, snapshot: SceneSnapshot) -> SyncReport:
        """Bring the GI state up to `snapshot`. Raises EmptySceneError when it has no geometry."""
        t0 = time.perf_counter()
        report = SyncReport()
        if snapshot.geometry.triangle_count == 0:
            self.close()
            self.snapshot = snapshot
            self._topology = None
            raise EmptySceneError("the scene has no geometry")
        topology = _topology_key(snapshot)
        lights = _light_key(snapshot)
        if self.system is None or topology != self._topology:
            self._rebuild(snapshot, keep_cache=self.system is not None and self.system.settings == self.settings)
            report.rebuilt = True
        else:
            moved = self._moved_objects(snapshot)
            if moved:
                names = {snapshot.objects[i].name for i in moved}
                report.moved = sorted(names)
                old = self.snapshot
                if not names <= self.dynamic_names:
                    self.dynamic_names |= names
                    self._rebuild(snapshot, keep_cache=True)
                    report.rebuilt = True
                else:
                    self.system.move_dynamic(snapshot)
                boxes = [self._object_box(s, i) for s in (old, snapshot) for i in moved]
                report.touched_cells = int(self.system.cache.on_geometry_changed(boxes).size)
            if lights != self._lights:
                self.system.set_lights(snapshot)
                self.system.cache.on_lights_changed()
                report.lights_changed = True
        self.snapshot = snapshot
        self._topology = topology
        self._lights = lights
        report.ms = (time.perf_counter() - t0) * 1e3
        return report

    def _rebuild(self, snapshot: SceneSnapshot, keep_cache: bool) -> None:
        cache = self.system.cache if keep_cache and self.system is not None else None
        if cache is not None and not self._fits(cache, snapshot):
            cache = None  # the scene outgrew the grid: start over on a grid that covers it
        dynamic = frozenset(i for i, o in enumerate(snapshot.objects) if o.name in self.dynamic_names or o.dynamic)
        if self.system is not None:
            self.system.close()
        self.system = GISystem(snapshot, self.settings, dynamic, cache=cache)
        log.info("GI session rebuilt (%d dynamic objects, cache %s)", len(dynamic), "kept" if cache else "new")

    @staticmethod
    def _fits(cache, snapshot: SceneSnapshot) -> bool:
        lo, hi = snapshot.focus_bounds()
        margin = cache.grid.cell_size
        return bool((lo >= cache.grid.lo - margin).all() and (hi <= cache.grid.hi + margin).all())

    def _moved_objects(self, snapshot: SceneSnapshot) -> list[int]:
        old = self.snapshot.geometry.positions
        new = snapshot.geometry.positions
        if np.array_equal(old, new):
            return []
        changed_vertices = np.flatnonzero((old != new).any(axis=1))
        tri_changed = np.isin(snapshot.geometry.triangles, changed_vertices).any(axis=1)
        return sorted(int(i) for i in np.unique(snapshot.geometry.object_index[tri_changed]))

    @staticmethod
    def _object_box(snapshot: SceneSnapshot, index: int) -> tuple[np.ndarray, np.ndarray]:
        g = snapshot.geometry
        verts = g.positions[g.triangles[g.object_index == index].ravel()]
        return verts.min(axis=0), verts.max(axis=0)
