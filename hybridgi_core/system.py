"""One scene's GI state: ray mesh, tracer, irradiance cache and its updater.

This is what the render engine, the viewport and the benchmark drive: build it from a snapshot,
feed it visible cells each frame, read irradiance back. Everything here is numpy + embreex.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .cache import IrradianceCache
from .evaluate import Gathered, corner_visibility, gather
from .lights import direct_irradiance
from .lod import decimate
from .sampling import frame_rng
from .settings import MULTI_BOUNCE, CacheSettings
from .shading import SurfaceTable
from .snapshot import SceneSnapshot, concat_geometry
from .trace.embree import EmbreeTracer
from .update import CacheUpdater, ShadingScene, UpdateStats
from .visible import visible_cells

log = logging.getLogger(__name__)

#: Points sampled on the ray mesh to find the cells any surface reads (warm-up set).
SURFACE_SAMPLES = 2_000_000
#: Warm-up iterations use frame numbers from here on, so warm-up rays never repeat a frame's rays.
WARMUP_FRAME_BASE = -(2**20)


class GISystem:
    def __init__(
        self,
        scene: SceneSnapshot,
        settings: CacheSettings,
        dynamic_objects: frozenset[int] = frozenset(),
        cache: IrradianceCache | None = None,
    ):
        """cache : an existing cache to keep (same settings), e.g. across a rebuild of the ray
        scene in the viewport; None builds a fresh one over the scene's bounds."""
        t0 = time.perf_counter()
        self.scene = scene
        self.settings = settings
        self.dynamic_objects = frozenset(dynamic_objects)
        self._static_rays = self._static_ray_geometry(scene)
        self.ray_geometry = self._with_dynamic(scene)
        self.tracer = EmbreeTracer(self.ray_geometry, self.dynamic_objects, threads=1)
        self.surfaces = SurfaceTable(self.ray_geometry, scene.materials)
        self.cache = cache if cache is not None else IrradianceCache.for_scene(scene, settings)
        self.updater = CacheUpdater(self.cache, self.tracer, ShadingScene(self.surfaces, scene.lights, scene.world), self.tracer.epsilon)
        self._surface_cells: np.ndarray | None = None
        self.build_ms = (time.perf_counter() - t0) * 1e3
        log.info(
            "GI system: %d triangles (%d traced), grid %s (%d cells), built in %.0f ms",
            scene.geometry.triangle_count, self.ray_geometry.triangle_count,
            self.cache.grid.dims, self.cache.grid.count, self.build_ms,
        )

    def _dynamic_mask(self, scene: SceneSnapshot) -> np.ndarray:
        return np.isin(scene.geometry.object_index, np.fromiter(self.dynamic_objects, np.int64, len(self.dynamic_objects)))

    def _static_ray_geometry(self, scene: SceneSnapshot):
        """The static triangles, decimated by the LOD ratio (moving objects stay full resolution:
        their topology must not change between frames)."""
        static = scene.geometry.subset(~self._dynamic_mask(scene)) if self.dynamic_objects else scene.geometry
        return decimate(static, self.settings.lod_ratio) if self.settings.lod_ratio < 1.0 else static

    def _with_dynamic(self, scene: SceneSnapshot):
        if not self.dynamic_objects:
            return self._static_rays
        return concat_geometry([self._static_rays, scene.geometry.subset(self._dynamic_mask(scene))])

    def move_dynamic(self, scene: SceneSnapshot) -> None:
        """Take the dynamic objects' new vertex positions from `scene` (same topology).

        Rebuilds only the small dynamic Embree scene and those triangles' surface records.
        """
        self.scene = scene
        self.ray_geometry = self._with_dynamic(scene)
        self.tracer.update_dynamic(self.ray_geometry)
        rows = np.arange(self._static_rays.triangle_count, self.ray_geometry.triangle_count)
        self.surfaces.update_rows(self.ray_geometry, rows)

    def set_lights(self, scene: SceneSnapshot) -> None:
        """New lamps, world or materials (same geometry): the shading inputs change, rays do not."""
        self.scene = scene
        self.updater.scene = ShadingScene(self.surfaces, scene.lights, scene.world)
        self.surfaces.set_materials(scene.materials)

    # --- cache events (raised by GISession.sync from the snapshot diff) --------------------------

    def on_geometry_changed(self, boxes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Geometry changed inside these world (lo, hi) boxes (where it was and where it is):
        the cells within the indirect range re-converge. Returns the touched flat cells (int64)."""
        return self.cache.on_geometry_changed(boxes)

    def on_lights_changed(self) -> None:
        """Lamps, the world or materials changed (call after `set_lights`): every cell re-converges."""
        self.cache.on_lights_changed()

    def close(self) -> None:
        self.updater.close()
        self.tracer.close()

    def __enter__(self) -> GISystem:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- steps -----------------------------------------------------------------------------------

    def visible_cells(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Step 3: cells read by these G-buffer points (n, 3)."""
        return visible_cells(self.cache.grid, points, normals, self.settings.normal_bias)

    def surface_cells(self) -> np.ndarray:
        """Cells any surface of the scene reads: what further bounces need converged."""
        if self._surface_cells is None:
            g = self.ray_geometry
            p = g.positions[g.triangles]
            area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
            rng = np.random.default_rng(12345)
            # Enough points that every cell-sized patch of surface gets several, whatever the
            # triangle count (34 large Cornell triangles need as many as 300k small ones).
            cell_area = self.cache.grid.cell_size**2
            n = int(np.clip(8.0 * area.sum() / cell_area, 1000, SURFACE_SAMPLES))
            tri = rng.choice(g.triangle_count, size=n, p=area / area.sum())
            a, b = rng.random((2, n, 1), dtype=np.float32)
            flip = (a + b) > 1
            a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
            pts = p[tri, 0] + a * (p[tri, 1] - p[tri, 0]) + b * (p[tri, 2] - p[tri, 0])
            fn = g.face_normals()[tri]
            # Both sides: open meshes are seen from both.
            cells = np.union1d(self.visible_cells(pts, fn), self.visible_cells(pts, -fn))
            self._surface_cells = cells
        return self._surface_cells

    def update(self, cells: np.ndarray, frame: int, alpha: float | None = None) -> UpdateStats:
        """Steps 4-5 for these cells."""
        return self.updater.update(cells, frame, alpha)

    def warm_up(self, iterations: int, cells: np.ndarray | None = None, start: int = 0, total: int | None = None) -> list[UpdateStats]:
        """Converge the cache before a final render, deterministically.

        The first half of the `total` iterations propagates bounces: each replaces the cells'
        values, so iteration k holds k bounces (a running mean would keep the early, darker
        estimates: measured 30% low on the Cornell box). The second half averages for noise.
        Iteration i always uses the same rays whatever frame is being rendered, so a static scene
        renders identically on every frame and on any machine of a render farm. `start` and
        `total` let a caller run the iterations one at a time (progress, cancelling).
        """
        cells = self.surface_cells() if cells is None else cells
        total = iterations if total is None else total
        propagate = total // 2 if self.settings.indirect_quality == MULTI_BOUNCE else 0
        runs = []
        for i in range(start, start + iterations):
            if i == propagate and propagate > 0:
                # The averaging phase is a plain mean that starts from the propagated value (one
                # sample's worth; 0 would mark the cells invalid for this update's hit lookups).
                self.cache.samples[cells] = 1
            runs.append(self.update(cells, WARMUP_FRAME_BASE + i, alpha=1.0 if i < propagate else None))
        return runs

    def corner_visibility(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(n, 8) bool exact visibility of the neighbouring cells (occlusion rays) for the gather."""
        return corner_visibility(self.cache, self.tracer, points, normals, float(self.tracer.epsilon))

    def gather(self, points: np.ndarray, normals: np.ndarray, exact: bool = True) -> Gathered:
        """Step 6 on the CPU (the numpy reference of the GPU gather); exact = occlusion rays."""
        vis = self.corner_visibility(points, normals) if exact else None
        return gather(self.cache, points, normals, corner_visible=vis)

    def direct(self, points: np.ndarray, normals: np.ndarray, frame: int, samples: int | None = None) -> np.ndarray:
        """Lamp irradiance (n, 3) W/m^2 with shadow rays at points: the deferred pass's direct light."""
        rng = frame_rng(self.settings.seed + 1, frame)
        return direct_irradiance(
            self.scene.lights, points, normals, self.tracer, rng,
            samples=samples or self.settings.light_samples, epsilon=float(self.tracer.epsilon),
        )
