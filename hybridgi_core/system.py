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
from .settings import CacheSettings
from .shading import SurfaceTable
from .snapshot import SceneSnapshot
from .trace.embree import EmbreeTracer
from .update import CacheUpdater, ShadingScene, UpdateStats
from .visible import visible_cells

log = logging.getLogger(__name__)

#: Points sampled on the ray mesh to find the cells any surface reads (warm-up set).
SURFACE_SAMPLES = 200_000
#: Warm-up iterations use frame numbers from here on, so warm-up rays never repeat a frame's rays.
WARMUP_FRAME_BASE = -(2**20)


class GISystem:
    def __init__(self, scene: SceneSnapshot, settings: CacheSettings, dynamic_objects: frozenset[int] = frozenset()):
        t0 = time.perf_counter()
        self.scene = scene
        self.settings = settings
        self.dynamic_objects = frozenset(dynamic_objects)
        self.ray_geometry = decimate(scene.geometry, settings.lod_ratio) if settings.lod_ratio < 1.0 else scene.geometry
        self.tracer = EmbreeTracer(self.ray_geometry, self.dynamic_objects, threads=1)
        self.surfaces = SurfaceTable(self.ray_geometry, scene.materials)
        self.cache = IrradianceCache.for_scene(scene, settings)
        self.updater = CacheUpdater(self.cache, self.tracer, ShadingScene(self.surfaces, scene.lights, scene.world), self.tracer.epsilon)
        self._surface_cells: np.ndarray | None = None
        self.build_ms = (time.perf_counter() - t0) * 1e3
        log.info(
            "GI system: %d triangles (%d traced), grid %s (%d cells), built in %.0f ms",
            scene.geometry.triangle_count, self.ray_geometry.triangle_count,
            self.cache.grid.dims, self.cache.grid.count, self.build_ms,
        )

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
            n = min(SURFACE_SAMPLES, max(8 * g.triangle_count, 1000))
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

    def update(self, cells: np.ndarray, frame: int) -> UpdateStats:
        """Steps 4-5 for these cells."""
        return self.updater.update(cells, frame)

    def warm_up(self, iterations: int, cells: np.ndarray | None = None, start: int = 0) -> list[UpdateStats]:
        """Converge the cache before a final render, deterministically.

        Iteration i always uses the same rays whatever frame is being rendered, so a static scene
        renders identically on every frame and on any machine of a render farm. `start` lets a
        caller run the iterations one at a time (progress, cancelling).
        """
        cells = self.surface_cells() if cells is None else cells
        return [self.update(cells, WARMUP_FRAME_BASE + i) for i in range(start, start + iterations)]

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
