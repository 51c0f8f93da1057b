"""A GI state that lives across frames and edits (viewport, animation playback).

`sync(snapshot)` diffs the new snapshot against the last one (`changes.diff_snapshots`) and raises
every cache event itself, doing the least work that keeps the cache right:

| what changed | what happens |
|---|---|
| nothing | nothing |
| lamps, world, materials | shading inputs swapped; `on_lights_changed()` |
| a material's holes for rays (alpha, clear glass, shadow skips) | ray scene rebuilt, cache kept, as for new triangles |
| vertices of dynamic objects | dynamic Embree scene rebuilt; `on_geometry_changed(boxes)` |
| vertices of a static object | it becomes dynamic (one rebuild of the ray scene), then as above |
| objects appeared, vanished, re-topologised | ray scene rebuilt, the cache kept when its settings and grid still fit; `on_geometry_changed(boxes)` where they were and are |
| settings | a fresh system and cache |

Owners (the viewport worker, incremental final renders) add only policy on top of the
`SyncReport`: how urgent a change is for them, whether to warm up again.

Pure numpy: it may run on a worker thread with snapshots made on the main thread.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from .changes import SceneChanges, diff_snapshots
from .errors import EmptySceneError
from .settings import CacheSettings
from .snapshot import SceneSnapshot
from .system import GISystem

log = logging.getLogger(__name__)


@dataclass
class SyncReport:
    """What one `GISession.sync` found and did.

    changes : the named changes from the previous snapshot (everything appeared on a first sync)
    rebuilt : the ray scene was rebuilt; fresh : the cache is new (nothing converged in it)
    touched : (k,) int64 flat cells `on_geometry_changed` raised
    """

    changes: SceneChanges = field(default_factory=SceneChanges)
    rebuilt: bool = False
    fresh: bool = False
    touched: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    ms: float = 0.0

    @property
    def moved(self) -> list[str]:
        """Objects whose vertices moved with their topology kept (rigidly or deformed)."""
        return self.changes.displaced

    @property
    def lights_changed(self) -> bool:
        return self.changes.shading_changed

    @property
    def touched_cells(self) -> int:
        return int(self.touched.size)


class GISession:
    """Owns a `GISystem` and keeps it in step with successive snapshots."""

    def __init__(self, settings: CacheSettings, dynamic_names: frozenset[str] = frozenset()):
        self.settings = settings
        #: Objects traced in the per-frame dynamic scene (animated, or moved once by the user).
        self.dynamic_names = set(dynamic_names)
        self.system: GISystem | None = None
        self.snapshot: SceneSnapshot | None = None

    def close(self) -> None:
        if self.system is not None:
            self.system.close()
            self.system = None

    def set_settings(self, settings: CacheSettings) -> None:
        """New settings take effect at the next sync, with a fresh system and cache."""
        if settings != self.settings:
            self.settings = settings

    def sync(self, snapshot: SceneSnapshot) -> SyncReport:
        """Bring the GI state up to `snapshot`. Raises EmptySceneError when it has no geometry."""
        t0 = time.perf_counter()
        if snapshot.geometry.triangle_count == 0:
            self.close()
            self.snapshot = snapshot
            raise EmptySceneError("the scene has no geometry")
        old = self.snapshot if self.system is not None else None
        changes = diff_snapshots(old, snapshot)
        report = SyncReport(changes=changes)
        if old is None or self.system.settings != self.settings:
            self._rebuild(snapshot, keep_cache=False)
            report.rebuilt = report.fresh = True
        else:
            displaced = set(changes.displaced)
            # New holes for rays (alpha, clear glass) move the rays' hits as new triangles would;
            # triangles that read other materials, UVs or normals need the surface table anew.
            if (changes.topology_changed or changes.cutouts_changed or changes.resurfaced
                    or not displaced <= self.dynamic_names):
                self.dynamic_names |= displaced
                report.fresh = not self._rebuild(snapshot, keep_cache=True)
                report.rebuilt = True
            elif displaced:
                # The diff's boxes (where the displaced objects were and are) are raised below.
                self.system.move_dynamic(snapshot, invalidate=not changes.boxes)
            if not report.fresh:
                if changes.boxes:
                    report.touched = self.system.on_geometry_changed(changes.boxes)
                if changes.shading_changed:
                    if not report.rebuilt:
                        self.system.set_lights(snapshot)
                    self.system.on_lights_changed()
        self.snapshot = snapshot
        report.ms = (time.perf_counter() - t0) * 1e3
        return report

    def _rebuild(self, snapshot: SceneSnapshot, keep_cache: bool) -> bool:
        """A new system for `snapshot`; returns whether it kept the old cache."""
        cache = self.system.cache if keep_cache and self.system is not None else None
        if cache is not None and not self._fits(cache, snapshot):
            cache = None  # the scene outgrew the grid: start over on a grid that covers it
        dynamic = frozenset(i for i, o in enumerate(snapshot.objects) if o.name in self.dynamic_names or o.dynamic)
        if self.system is not None:
            self.system.close()
        self.system = GISystem(snapshot, self.settings, dynamic, cache=cache)
        log.info("GI session rebuilt (%d dynamic objects, cache %s)", len(dynamic), "kept" if cache else "new")
        return cache is not None

    @staticmethod
    def _fits(cache, snapshot: SceneSnapshot) -> bool:
        lo, hi = snapshot.focus_bounds()
        margin = cache.grid.cell_size
        return bool((lo >= cache.grid.lo - margin).all() and (hi <= cache.grid.hi + margin).all())
