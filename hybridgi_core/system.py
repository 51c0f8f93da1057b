"""One scene's GI state: ray mesh, tracer, irradiance cache and its updater.

This is what the render engine, the viewport and the benchmark drive: build it from a snapshot,
feed it visible cells each frame, read irradiance back. Everything here is numpy + embreex.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .bump import has_normal_maps, smooth_normals
from .cache import IrradianceCache
from .cutout import Cutouts, glass_transmission
from .evaluate import Gathered, corner_visibility, gather
from .glossy import GlossyMaterials, glossy_direct
from .levels import CacheLevels, build_levels
from .lights import GLOSSY_LAMP_BUDGET, RATIO_MIN_SAMPLES, _pick_lamps, direct_irradiance
from .lod import decimate
from .open_space import open_to
from .outside import sky_above_horizon
from .rows import column_bounds
from .sampling import frame_rng
from .settings import MULTI_BOUNCE, CacheSettings
from .shading import SurfaceTable
from .snapshot import SceneSnapshot, concat_geometry
from .solver import WARMUP_FRAME_BASE, GISolver, SolveStats
from .trace.embree import EmbreeTracer
from .update import CacheUpdater, ShadingScene, UpdateStats
from .visible import visible_cells

log = logging.getLogger(__name__)

#: Points sampled on the ray mesh to find the cells any surface reads (warm-up set).
SURFACE_SAMPLES = 2_000_000
#: Surface samples per cell area (`_cells_on`). 8 found 0.3-0.7% more cells than 2 (cells barely
#: read: the same 640x360 Cornell, car and atrium images) at 4x the cost: Cornell 0.25 -> 0.05 s.
SURFACE_DENSITY = 2.0
#: Warm-up batches use frame numbers from WARMUP_FRAME_BASE on (defined in solver.py, re-exported
#: here), so warm-up rays never repeat a frame's rays.
__all__ = ["GISystem", "MAX_WARMUP_ITERATIONS", "SURFACE_SAMPLES", "UPDATES_PER_BATCH", "WARMUP_FRAME_BASE"]
#: Warm-up updates per traced batch of directions: a warm-up of N updates traces
#: max(1, round(N / UPDATES_PER_BATCH)) batches of rays_per_cell directions per cell and spends
#: the rest of its steps on fixed-point iterations over the stored hits (no rays).
UPDATES_PER_BATCH = 8
#: Most fixed-point iterations of one warm-up (they stop earlier once converged).
MAX_WARMUP_ITERATIONS = 16
#: Shadow rays per block of `GISystem.direct` (receivers x samples); larger calls are split over
#: the worker pool. 32k blocks of 16k-ray chunks kept both threads waiting on the GIL (see
#: `lights.CHUNK_RAYS`); 64k: Cornell 640x360's "direct" step 500-527 -> 435-459 ms (3 interleaved
#: runs each, idle host).
DIRECT_BLOCK_RAYS = 1 << 16
#: Frame offset between the lamps' sample streams of the picked glossy light.
GLOSSY_LAMP_STRIDE = 1 << 12
#: G-buffer points per block of `GISystem.corner_visibility` (8 occlusion rays each).
VISIBILITY_BLOCK = 8192


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
        self.cache = cache if cache is not None else IrradianceCache.for_scene(scene, settings)
        self.cache.outside = sky_above_horizon(scene.world, settings.sh_coeffs)
        # The surface table (numpy) builds on a thread of its own while Embree builds the BVH
        # here: neither reads the other, and each leaves a core idle much of its time (the
        # atrium's 320k triangles: ~70 ms each, ~80 ms together). (The surface cells on a second
        # side thread saved nothing more: the three contend for the two cores.)
        with ThreadPoolExecutor(1, thread_name_prefix="hybridgi-build") as side:
            table = side.submit(SurfaceTable, self.ray_geometry, scene.materials, reflect=settings.bounce_light,
                                filter_glossy=settings.filter_glossy)
            try:
                self.tracer = EmbreeTracer(self.ray_geometry, self.dynamic_objects, threads=1)
            finally:
                self.surfaces = table.result()
        self._surface_cells: np.ndarray | None = None  # `surface_cells`, made on use
        self._set_cutouts(scene)
        self.updater = CacheUpdater(self.cache, self.tracer, ShadingScene(self.surfaces, scene.lights, scene.world), self.tracer.epsilon)
        #: Stored probe hits and the fixed-point solver of final renders (and of re-lighting).
        self.solver = GISolver(self.cache, self.tracer, self.updater.scene, self.tracer.epsilon, self.updater.pool)
        #: Finer camera-centred levels over level 0 (`levels.CacheLevels`), built per frame by
        #: `build_levels`; None: level 0 alone (every reader then takes the single-grid path).
        self.levels: CacheLevels | None = None
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

    def _set_cutouts(self, scene: SceneSnapshot) -> None:
        """Hand the tracer the holes, glass and shadow skips of the ray geometry's materials and
        objects (`cutout.Cutouts`; glass passes as Cycles' Filter Glossy lets it)."""
        self.tracer.set_cutouts(Cutouts(self.ray_geometry, scene.materials, scene.objects,
                                        glass=glass_transmission(self.settings.filter_glossy)))

    def _with_dynamic(self, scene: SceneSnapshot):
        if not self.dynamic_objects:
            return self._static_rays
        return concat_geometry([self._static_rays, scene.geometry.subset(self._dynamic_mask(scene))])

    def move_dynamic(self, scene: SceneSnapshot, invalidate: bool = True) -> None:
        """Take the dynamic objects' new vertex positions from `scene` (same topology).

        Rebuilds only the small dynamic Embree scene and those triangles' surface records.
        invalidate : mark the stored rays that meet the moved triangles' old and new boxes stale;
        False when the caller raises `on_geometry_changed` with boxes covering them anyway (a
        session's sync: each mark is a pass over every stored ray).
        """
        old = self.ray_geometry
        self.scene = scene
        self.ray_geometry = self._with_dynamic(scene)
        self.tracer.update_dynamic(self.ray_geometry)
        self._set_cutouts(scene)
        rows = np.arange(self._static_rays.triangle_count, self.ray_geometry.triangle_count)
        self.surfaces.update_rows(self.ray_geometry, rows)
        if invalidate and self.solver.has_hits:
            self.solver.invalidate_boxes(_moved_boxes(old, self.ray_geometry, rows))
        if self._surface_cells is not None and rows.size:
            # Surfaces that moved read new cells: further bounces need those converged too
            # (`resolve` traces them).
            self._surface_cells = np.union1d(self._surface_cells, self._cells_on(rows))

    def set_lights(self, scene: SceneSnapshot) -> None:
        """New lamps, world or materials (same geometry): the shading inputs change, rays do not.
        A snapshot that shares the materials list of the current one (a lamp or world edit: the
        viewport's `SetShading` keeps it) keeps the surface table and cutouts (re-building them
        was 58 of a lamp edit's 60 ms on the atrium's 320k triangles)."""
        same_materials = scene.materials is self.scene.materials
        self.scene = scene
        self.cache.outside = sky_above_horizon(scene.world, self.settings.sh_coeffs)
        self.updater.scene = ShadingScene(self.surfaces, scene.lights, scene.world)
        if not same_materials:
            self.surfaces.set_materials(scene.materials)
            self._set_cutouts(scene)
        self.solver.scene = self.updater.scene
        self.solver.lights_changed()

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
            self._surface_cells = self._cells_on(None)
        return self._surface_cells

    def _cells_on(self, rows: np.ndarray | None) -> np.ndarray:
        """Cells the surfaces of triangles `rows` of the ray geometry read (sampled points; None:
        every triangle). Corners gathered per column with np.take and the points made for the
        sampled triangles only: the whole mesh's (T, 3, 3) corners by fancy indexing were most of
        the time here (the atrium's warm-up 289 -> 267 ms, mean of 4)."""
        g = self.ray_geometry
        tris = g.triangles if rows is None else np.take(g.triangles, rows, axis=0)
        count = tris.shape[0]
        c0, c1, c2 = (np.take(g.positions, tris[:, k], axis=0) for k in range(3))
        e1, e2 = c1 - c0, c2 - c0
        # The edges' cross product gives both the areas and (at the sampled triangles) the face
        # normals: `Geometry.face_normals` over all of them cost as much again (atrium: ~60 ms).
        cross = np.cross(e1, e2)
        area = np.sqrt(np.einsum("ij,ij->i", cross, cross))
        if count == 0 or area.sum() <= 0:
            return np.zeros(0, np.int64)
        rng = np.random.default_rng(12345)
        # Enough points that every cell-sized patch of surface gets some, whatever the triangle
        # count (34 large Cornell triangles need as many as 300k small ones). A point reads the
        # 8 cells around it, so a cell is read by ~8 cell areas of surface: SURFACE_DENSITY
        # points per cell area leave a cell missed with odds ~exp(-8 SURFACE_DENSITY).
        cell_area = self.cache.grid.cell_size**2
        n = int(np.clip(SURFACE_DENSITY * area.sum() / cell_area, 1000, SURFACE_SAMPLES))
        tri = rng.choice(count, size=n, p=area / area.sum())
        a, b = rng.random((2, n, 1), dtype=np.float32)
        flip = (a + b) > 1
        a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
        pts = np.take(c0, tri, axis=0) + a * np.take(e1, tri, axis=0) + b * np.take(e2, tri, axis=0)
        fn = np.take(cross, tri, axis=0) / np.take(area, tri)[:, None]  # drawn by area: > 0
        # Both sides: open meshes are seen from both.
        return np.union1d(self.visible_cells(pts, fn), self.visible_cells(pts, -fn))

    def update(self, cells: np.ndarray, frame: int, alpha: float | None = None) -> UpdateStats:
        """Steps 4-5 for these cells."""
        stats = self.updater.update(cells, frame, alpha)
        open_to(self.cache, self.tracer, self.viewpoint, float(self.tracer.epsilon))
        return stats

    @property
    def viewpoint(self):
        """(3,) the camera's position (or None): the cells it sees are never inside geometry,
        however the faces around them point (`open_space.py`); the solver's too."""
        return self.solver.viewpoint

    @viewpoint.setter
    def viewpoint(self, position) -> None:
        self.solver.viewpoint = None if position is None else np.asarray(position, np.float32).reshape(3).copy()

    def warm_up(self, iterations: int, cells: np.ndarray | None = None, start: int = 0, total: int | None = None) -> list[SolveStats]:
        """Converge the cache before a final render, deterministically: trace once, re-shade many.

        A warm-up of `total` updates traces B = max(1, round(total / UPDATES_PER_BATCH)) batches of
        directions (the steps 0..B-1), storing every probe hit with its lamp light
        (`solver.StoredHits`), then solves the multi-bounce cache as a fixed point over the stored
        hits: each later step runs its share of MAX_WARMUP_ITERATIONS iterations (each one more
        bounce, no ray), none once converged; the last adds the geometric tail of the bounces still missing and filters each cell with
        its visible neighbours (`GISolver.filter_cells`: every cell has its own ray rotation, so
        neighbours' noise is independent). The same steps always use
        the same rays, so a static scene renders identically on every frame and on any machine of
        a render farm. `start` and `total` let a caller run the steps one at a time (progress,
        cancelling), with the same `cells` each time. Returns one SolveStats per step.
        """
        cells = self.surface_cells() if cells is None else cells
        total = iterations if total is None else total
        batches = max(1, min(total, round(total / UPDATES_PER_BATCH)))
        # The iterations (cheap) spread over the steps left, up to MAX_WARMUP_ITERATIONS in all:
        # a short warm-up converges as far as a long one.
        per_step = -(-MAX_WARMUP_ITERATIONS // max(1, total - batches))
        runs = []
        for i in range(start, start + iterations):
            if i == 0:
                self.solver.begin(cells)
            st = self.solver.trace_batch(i) if i < batches else SolveStats()
            if i >= batches or total == batches and i == batches - 1:
                for _ in range(per_step):
                    if self.solver.converged:
                        break
                    st.merge(self.solver.relax())
            if i == total - 1:
                self.solver.extrapolate()
                tic = time.perf_counter()
                st.shadow_points += self.solver.filter_cells()
                st.add("filter", (time.perf_counter() - tic) * 1e3)
                self._mark_warm(total)
            runs.append(st)
        return runs

    def warm_up_retraced(self, iterations: int, cells: np.ndarray | None = None) -> list[UpdateStats]:
        """The EMA warm-up that `warm_up` replaced, kept as the reference it is measured and
        tested against: every update retraces all rays; the first half replaces the cells'
        values (update k holds k bounces), the second half averages."""
        cells = self.surface_cells() if cells is None else cells
        propagate = iterations // 2 if self.settings.indirect_quality == MULTI_BOUNCE else 0
        runs = []
        for i in range(iterations):
            if i == propagate and propagate > 0:
                self.cache.samples[cells] = 1
            runs.append(self.update(cells, WARMUP_FRAME_BASE + i, alpha=1.0 if i < propagate else None))
        return runs

    def _mark_warm(self, total: int) -> None:
        """Sample counts of a finished warm-up: those of the EMA warm-up of `total` updates (its
        averaging half plus one), so EMA updates after it blend in as they did after the old one."""
        cells = self.solver.cells
        count = 1 + total - total // 2 if self.settings.indirect_quality == MULTI_BOUNCE else total
        self.cache.samples[cells] = np.where(self.cache.samples[cells] > 0, count, 0)

    def solve(self, cells: np.ndarray | None = None, batches: int = 2, max_iterations: int = 16,
              extrapolate: bool = True) -> SolveStats:
        """Trace `batches` direction sets from `cells` (default: the surface cells), store the
        hits and solve the fixed point: what `warm_up` does, in one call."""
        self.solver.begin(self.surface_cells() if cells is None else cells)
        stats = SolveStats()
        for b in range(batches):
            stats.merge(self.solver.trace_batch(b))
        stats.merge(self.solver.solve(max_iterations, extrapolate))
        stats.shadow_points += self.solver.filter_cells()
        return stats

    # --- cache events: what GISession.sync raises --------------------------------------------------

    def invalidate_boxes(self, boxes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Geometry changed inside these world boxes [(lo (3,), hi (3,)), ...], old and new places.

        Marks stale every stored probe ray whose segment (cell centre to its hit, or to the ray
        length when it missed) meets a box, and the lamp light of stored hits whose shadow rays
        may cross a box. Nothing is traced until `resolve()`, which traces exactly those rays
        again (same directions). Returns the flat cells (int64) with a stale ray. The EMA path
        is untouched: `on_geometry_changed` does both.
        """
        return self.solver.invalidate_boxes(boxes)

    def on_geometry_changed(self, boxes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Geometry changed inside these world (lo, hi) boxes (where it was and where it is):
        objects moved, deformed, appeared, vanished or changed topology (raised by
        GISession.sync from the snapshot diff). The cells within the indirect range re-converge
        (`cache.on_geometry_changed`: urgency with the quadratic fall-off, for EMA updates), and
        the stored rays that reach a box turn stale (`invalidate_boxes`; `resolve()` traces them
        again). Returns the touched flat cells (int64) of the fall-off."""
        touched = self.cache.on_geometry_changed(boxes)
        self.invalidate_boxes(boxes)
        # The event closed the cells near it: those still in the camera's space open again now,
        # not at the next traced batch (a change that leaves every stored ray as it was has none).
        open_to(self.cache, self.tracer, self.viewpoint, float(self.tracer.epsilon))
        return touched

    def on_lights_changed(self, resolve: bool = False) -> SolveStats:
        """Lamps, the world or materials changed (call after `set_lights`, which already marks
        every stored hit stale): every cell re-converges (`cache.on_lights_changed`, for EMA
        updates). With stored hits and `resolve`, the cache re-converges from them right away:
        shadow rays at the stored hits, no probe ray, then the fixed point (else at the next
        `resolve()`). GISession.sync calls it without `resolve`, keeping a sync cheap."""
        self.cache.on_lights_changed()
        self.solver.lights_changed()
        return self.resolve() if resolve else SolveStats()

    def resolve(self, max_iterations: int = 16) -> SolveStats:
        """Bring a solved cache up to date after events: trace the stale rays again (and the
        batches of cells new surfaces read), re-shade stale hits, solve again, filter the indirect
        band. No-op (empty stats) without stored hits."""
        if not self.solver.has_hits:
            return SolveStats()
        if self._surface_cells is not None:
            self.solver.extend(self._surface_cells)
        stats = self.solver.resolve(max_iterations)
        stats.shadow_points += self.solver.filter_cells(bands=("sh_indirect",))
        return stats

    def build_levels(self, points: np.ndarray, normals: np.ndarray, depth: np.ndarray, batches: int) -> SolveStats:
        """Fit and solve the finer cache levels for a frame's visible points (n, 3), normals and
        view depths (n,) (`levels.build_levels`; level 0 converged first). With cache_levels = 1
        (the default) there are none and nothing is traced."""
        stats = SolveStats()
        self.levels = None
        if self.settings.cache_levels > 1 and np.asarray(points).size:
            self.levels = build_levels(self, points, normals, depth, batches, stats)
        return stats

    def corner_visibility(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(n, 8) bool exact visibility of the neighbouring cells (occlusion rays) for the gather;
        (n, 8 x levels) with finer levels (`CacheLevels.corner_visibility`).

        Blocks of VISIBILITY_BLOCK points run on the worker pool (the tracer is single-threaded);
        each point's rays are its own, so the answer does not depend on the split."""
        eps = float(self.tracer.epsilon)
        if self.levels is None:
            def of(cache, tracer, p, nrm, e):
                return corner_visibility(cache, tracer, p, nrm, e)
        else:
            def of(cache, tracer, p, nrm, e):
                return self.levels.corner_visibility(tracer, p, nrm, e)
        n = int(np.asarray(points).reshape(-1, 3).shape[0])
        if n <= VISIBILITY_BLOCK:
            return of(self.cache, self.tracer, points, normals, eps)
        points = np.asarray(points, np.float32).reshape(-1, 3)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        jobs = [self.updater.pool.submit(of, self.cache, self.tracer, points[a : a + VISIBILITY_BLOCK],
                                         normals[a : a + VISIBILITY_BLOCK], eps)
                for a in range(0, n, VISIBILITY_BLOCK)]
        return np.concatenate([j.result() for j in jobs])

    def gather(self, points: np.ndarray, normals: np.ndarray, exact: bool = True) -> Gathered:
        """Step 6 on the CPU (the numpy reference of the GPU gather); exact = occlusion rays."""
        vis = self.corner_visibility(points, normals) if exact else None
        if self.levels is not None:
            return self.levels.gather(points, normals, corner_visible=vis)
        return gather(self.cache, points, normals, corner_visible=vis)

    def direct(self, points: np.ndarray, normals: np.ndarray, frame: int, samples: int | None = None,
               partial: np.ndarray | None = None, unshadowed: np.ndarray | None = None,
               exact: np.ndarray | None = None, per_lamp: np.ndarray | None = None,
               lights: list[int] | None = None, smooth: np.ndarray | None = None,
               ratio_samples: int = RATIO_MIN_SAMPLES) -> np.ndarray:
        """Lamp irradiance (n, 3) W/m^2 with shadow rays at points: the deferred pass's direct light.

        Up to DIRECT_BLOCK_RAYS shadow rays run in one call on this thread; more (the full-res
        image at 16 samples: 2M rays) are cut into blocks of that many rays shared by the worker
        pool, block i drawing its samples from child i of the frame's generator: deterministic
        and independent of the thread count (the tracer itself is single-threaded). partial : an
        optional (n,) bool output, True where a penumbra crosses, or (n, lamps) per lamp
        (`lights.direct_irradiance`). unshadowed : an optional (n, 3) output, the same samples'
        light without shadows. exact : an optional (n, lamps) float64 in/out, the area lamps'
        exact unshadowed irradiance. per_lamp : an optional (n, lamps, 3) output, each lamp's
        share. lights : indices of the scene's lamps to shade (None: all); the lamp columns of
        partial, exact and per_lamp follow it. smooth : the (n, 3) smooth surface normals under
        points where a normal map may bend `normals` (the G-buffer's `surface` target); None:
        found by one ray each in scenes with normal maps (`bump.smooth_normals`). ratio_samples :
        `lights.direct_irradiance`'s (1: one sample gives a `one_sample_exact` lamp's exact light
        times its visibility)."""
        rng = frame_rng(self.settings.seed + 1, frame)
        samples = samples or self.settings.light_samples
        eps = float(self.tracer.epsilon)
        lamps = self.scene.lights if lights is None else [self.scene.lights[i] for i in lights]
        n = int(np.asarray(points).reshape(-1, 3).shape[0])
        per_block = max(1, DIRECT_BLOCK_RAYS // samples)
        # Normals a normal map bent are lit as Cycles lights them (`bump.py`): the smooth surface
        # normal under each point comes from the ray mesh.
        if not (n and lamps and has_normal_maps(self.scene)):
            smooth = None
        elif smooth is None:
            smooth = smooth_normals(self.surfaces, self.tracer, points, normals, eps)
        else:
            smooth = np.asarray(smooth, np.float32).reshape(-1, 3)
        outputs = {"partial": partial, "unshadowed": unshadowed, "exact": exact, "per_lamp": per_lamp,
                   "smooth": smooth}
        if n <= per_block or not lamps:
            return direct_irradiance(lamps, points, normals, self.tracer, rng, samples=samples, epsilon=eps,
                                     ratio_samples=ratio_samples, **outputs)
        points = np.asarray(points, np.float32).reshape(-1, 3)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        starts = range(0, n, per_block)
        return np.concatenate(self._blocks([
            (direct_irradiance, (lamps, points[a : a + per_block], normals[a : a + per_block], self.tracer, child,
                                 samples, eps),
             {"ratio_samples": ratio_samples,
              **{k: None if v is None else v[a : a + per_block] for k, v in outputs.items()}})
            for a, child in zip(starts, rng.spawn(len(starts)), strict=True)]))

    def emitter_light(self, points: np.ndarray, normals: np.ndarray, frame: int, samples: int,
                      partial: np.ndarray | None = None, unshadowed: np.ndarray | None = None,
                      cones: np.ndarray | None = None) -> np.ndarray | None:
        """(n, 3) irradiance of the emissive triangles at receivers (`emitters.MeshLights`,
        `samples` points and shadow rays each), in blocks on the worker pool as `direct`'s; None
        when nothing emits. Its own stream of the frame (seed + 3). partial, unshadowed : optional
        outputs (`MeshLights.irradiance`), so that `penumbra.adaptive_direct` can take this as
        its `direct` where the emitters are few triangles (`MeshLights.ratio`); unshadowed and
        cones, sampled by power, as `MeshLights.irradiance` fills them."""
        emitters = self.surfaces.emitters
        if emitters is None:
            return None
        points = np.asarray(points, np.float32).reshape(-1, 3)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        n = points.shape[0]
        rng = frame_rng(self.settings.seed + 3, frame)
        per_block = max(1, DIRECT_BLOCK_RAYS // max(samples, 1))
        eps = float(self.tracer.epsilon)
        if n <= per_block:
            return emitters.irradiance(points, normals, self.tracer, rng, samples, eps, partial, unshadowed, cones)
        starts = range(0, n, per_block)
        return np.concatenate(self._blocks([
            (emitters.irradiance, (points[a : a + per_block], normals[a : a + per_block], self.tracer, child, samples,
                                   eps, None if partial is None else partial[a : a + per_block],
                                   None if unshadowed is None else unshadowed[a : a + per_block],
                                   None if cones is None else cones[a : a + per_block]), {})
            for a, child in zip(starts, rng.spawn(len(starts)), strict=True)]))

    def _blocks(self, calls: list) -> list:
        """Results of calls [(fn, args, kwargs)] in order: on the worker pool, or one after another
        when the caller is itself one of its workers (the same blocks and generators either way,
        so the result does not depend on who asks)."""
        if self.updater.on_pool_thread():
            return [fn(*args, **kwargs) for fn, args, kwargs in calls]
        jobs = [self.updater.pool.submit(fn, *args, **kwargs) for fn, args, kwargs in calls]
        return [j.result() for j in jobs]

    @property
    def glossy_materials(self) -> GlossyMaterials:
        """The scene's materials' glossy lobes (`glossy.GlossyMaterials`), rebuilt when they change."""
        materials = self.scene.materials
        if getattr(self, "_glossy_key", None) is not materials:
            self._glossy_materials, self._glossy_key = GlossyMaterials.from_materials(materials), materials
        return self._glossy_materials

    def _glossy_picked(self, points, normals, to_eye, rows, frame: int, samples: int, lights: list,
                       variance: np.ndarray | None, allowed: np.ndarray | None = None,
                       widen: np.ndarray | None = None) -> np.ndarray:
        """`glossy` of many lamps: GLOSSY_LAMP_BUDGET draws of them per receiver (`_pick_lamps`),
        each drawn lamp's light (its own sample stream) times its weight; the variance output
        scales by the squared weights (the draws' own spread is not counted)."""
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        nrm = np.asarray(normals, np.float32).reshape(-1, 3)
        eye = np.asarray(to_eye, np.float32).reshape(-1, 3)
        rows = np.asarray(rows).reshape(-1)
        weights = _pick_lamps(lights, pts, nrm, GLOSSY_LAMP_BUDGET, frame_rng(self.settings.seed + 5, frame), allowed)
        out = np.zeros((pts.shape[0], 3), np.float32)
        if variance is not None:
            variance[:] = 0.0
        for j, light in enumerate(lights):
            sel = np.flatnonzero(weights[:, j] > 0)
            if sel.size == 0:
                continue
            w = weights[sel, j]
            var = None if variance is None else np.zeros(sel.size, np.float32)
            out[sel] += w[:, None] * self.glossy(pts[sel], nrm[sel], eye[sel], rows[sel],
                                                 frame + (j + 1) * GLOSSY_LAMP_STRIDE, samples, [light], var,
                                                 widen=None if widen is None else widen[sel])
            if var is not None:
                variance[sel] += var * w * w
        return out

    def glossy(self, points: np.ndarray, normals: np.ndarray, to_eye: np.ndarray, rows: np.ndarray, frame: int,
               samples: int | None = None, lights: list | None = None,
               variance: np.ndarray | None = None, allowed: np.ndarray | None = None,
               widen: np.ndarray | None = None) -> np.ndarray:
        """Lamp radiance (n, 3) the glossy lobes of materials `rows` reflect towards the eye, with
        shadow rays (`glossy.glossy_direct`; its own samples, seeded apart from `direct`'s), of
        the scene's lamps or of `lights`, a subset of them. variance : an optional (n,) output,
        the estimate's luminance variance (`glossy_direct`'s). allowed : optional (n, L) bool,
        with more than GLOSSY_LAMP_BUDGET lamps, the lamps each receiver's light is of (its
        draws are among them, `_glossy_picked`). widen : optional (n,) alpha^2 the receivers'
        lobes gain (`specular_aa.footprint_alpha2`)."""
        rng = frame_rng(self.settings.seed + 2, frame)
        if widen is not None:
            widen = np.asarray(widen, np.float32).reshape(-1)
        samples = samples or self.settings.light_samples
        eps = float(self.tracer.epsilon)
        n = int(np.asarray(points).reshape(-1, 3).shape[0])
        per_block = max(1, DIRECT_BLOCK_RAYS // samples)
        lights, mats = self.scene.lights if lights is None else lights, self.glossy_materials
        if len(lights) > GLOSSY_LAMP_BUDGET and n:
            return self._glossy_picked(points, normals, to_eye, rows, frame, samples, lights, variance, allowed, widen)
        if allowed is not None:
            raise ValueError("glossy: allowed lamps per receiver need more than GLOSSY_LAMP_BUDGET lamps")
        if n <= per_block or not lights:
            return glossy_direct(lights, points, normals, to_eye, rows, mats, self.tracer, rng, samples, eps,
                                 variance=variance, widen=widen)
        # Blocks on the worker pool, each with its own child generator (as `direct`), each
        # writing its own slice of `variance`.
        per_pixel = [np.asarray(a).reshape(n, -1) for a in (points, normals, to_eye)]
        rows = np.asarray(rows).reshape(-1)
        starts = range(0, n, per_block)
        return np.concatenate(self._blocks([
            (glossy_direct, (lights, *(a[b : b + per_block] for a in per_pixel), rows[b : b + per_block], mats,
                             self.tracer, child, samples, eps),
             {"variance": None if variance is None else variance[b : b + per_block],
              "widen": None if widen is None else widen[b : b + per_block]})
            for b, child in zip(starts, rng.spawn(len(starts)), strict=True)]))


def _moved_boxes(old, new, rows: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """World boxes, old and new, of each object whose triangles `rows` moved between two ray
    geometries of the same topology."""
    if rows.size == 0 or old.triangle_count != new.triangle_count:
        return []
    p_old = old.positions[old.triangles[rows]]
    p_new = new.positions[new.triangles[rows]]
    moved = (p_old != p_new).any(axis=(1, 2))
    boxes = []
    objs = new.object_index[rows]
    for obj in np.unique(objs[moved]):
        sel = objs == obj
        for p in (p_old[sel], p_new[sel]):
            pts = p.reshape(-1, 3)
            boxes.append(column_bounds(pts))
    return boxes
