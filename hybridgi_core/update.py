"""Steps 4-5 of the seed pipeline: trace probe rays from visible cells, shade the hits, project to
SH and blend into the cache.

Runs on numpy snapshots and embreex only, so it may run in worker threads (embreex releases the
GIL, and so do numpy's large array operations). Chunks of cells are processed in parallel and
blended on the calling thread afterwards, so results do not depend on thread timing.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from . import sh
from .cache import CellSamples, IrradianceCache
from .evaluate import irradiance_sh, nearest_irradiance
from .lights import direct_irradiance
from .sampling import frame_directions, frame_rng, octahedral_texel
from .settings import AO_ONLY, MULTI_BOUNCE
from .shading import SurfaceTable
from .snapshot import Light, World
from .trace import Tracer

STEPS = ("trace", "shade", "shadow", "sh", "blend")
#: Rays per work item: big enough to amortize numpy/embree call overhead, small enough for two threads.
CHUNK_RAYS = 16384


@dataclass
class UpdateStats:
    """What one update did. steps_ms sums each step over worker threads (CPU time per step);
    wall_ms is the elapsed time of the whole update."""

    cells: int = 0
    rays: int = 0
    wall_ms: float = 0.0
    steps_ms: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STEPS, 0.0))

    @property
    def rays_per_s(self) -> float:
        return self.rays / (self.wall_ms * 1e-3) if self.wall_ms > 0 else 0.0


@dataclass
class ShadingScene:
    """What hit shading reads: the traced geometry's surface table, lamps and the world."""

    surfaces: SurfaceTable
    lights: list[Light]
    world: World


class CacheUpdater:
    """Owns the worker pool; `update(cells, frame)` is one EMA step for those cells."""

    def __init__(self, cache: IrradianceCache, tracer: Tracer, scene: ShadingScene, epsilon: float):
        self.cache = cache
        self.tracer = tracer
        self.scene = scene
        self.epsilon = np.float32(epsilon)
        self._pool = ThreadPoolExecutor(max_workers=cache.settings.threads, thread_name_prefix="hybridgi-update")

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    def __enter__(self) -> CacheUpdater:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, cells: np.ndarray, frame: int, alpha: float | None = None) -> UpdateStats:
        """Trace, shade and blend the given flat cells for this frame (deterministic per frame).

        alpha : blend weight overriding the EMA's (see `IrradianceCache.blend`)."""
        t0 = time.perf_counter()
        cache = self.cache
        s = cache.settings
        cells = np.unique(np.asarray(cells, np.int64))
        stats = UpdateStats(cells=int(cells.size), rays=int(cells.size) * s.rays_per_cell)
        if cells.size == 0:
            return stats
        dirs = frame_directions(s.rays_per_cell, s.seed, frame)
        # Hits read the cache as it was before this update, whatever the thread timing.
        table = irradiance_sh(cache, bounced=s.indirect_quality == MULTI_BOUNCE)
        per_chunk = max(1, CHUNK_RAYS // s.rays_per_cell)
        chunks = [cells[i : i + per_chunk] for i in range(0, cells.size, per_chunk)]
        jobs = [
            self._pool.submit(self._sample_chunk, chunk, dirs, table, frame_rng(s.seed, frame * 7919 + i))
            for i, chunk in enumerate(chunks)
        ]
        # Blend only after every chunk is sampled: hits read the cache (further bounces), and a
        # frame must read the same cache whatever the thread timing.
        for samples, times in [job.result() for job in jobs]:
            tb = time.perf_counter()
            cache.blend(samples, frame, alpha)
            times["blend"] = (time.perf_counter() - tb) * 1e3
            for k, v in times.items():
                stats.steps_ms[k] += v
        stats.wall_ms = (time.perf_counter() - t0) * 1e3
        return stats

    def _sample_chunk(self, cells: np.ndarray, dirs: np.ndarray, table: np.ndarray, rng: np.random.Generator):
        """Estimates for one chunk of cells (worker thread: numpy and the tracer only)."""
        cache = self.cache
        s = cache.settings
        times = {}
        m, r = cells.size, dirs.shape[0]
        tic = time.perf_counter()
        origins = np.repeat(cache.centers[cells], r, axis=0)
        ray_dirs = np.tile(dirs, (m, 1))
        tfar = np.float32(s.ray_length) if s.ray_length > 0 else np.float32(np.inf)
        hits = self.tracer.intersect(origins, ray_dirs, tfar)
        times["trace"] = (time.perf_counter() - tic) * 1e3

        tic = time.perf_counter()
        hit = hits.prim >= 0
        idx = np.flatnonzero(hit)
        # Channel-major (m, 7, r): direct RGB, indirect RGB, AO visibility; the SH projection is
        # then one GEMM with no transposed copy.
        values = np.zeros((m, 7, r), np.float32)
        rad_d = np.zeros((m * r, 3), np.float32)
        rad_i = np.zeros((m * r, 3), np.float32)
        rad_d[~hit] = self.scene.world.color
        surf = self.scene.surfaces.surface(hits.prim[idx], hits.u[idx], hits.v[idx], ray_dirs[idx])
        backface = np.zeros(m * r, bool)
        backface[idx] = surf.backface
        shadow_ms = 0.0
        if s.indirect_quality != AO_ONLY and idx.size:
            rad_d[idx] = surf.emission
            ts = time.perf_counter()
            e_lamps = direct_irradiance(
                self.scene.lights, surf.position, surf.normal, self.tracer, rng,
                samples=s.light_samples, epsilon=float(self.epsilon),
            )
            shadow_ms = (time.perf_counter() - ts) * 1e3
            # Further bounces read the cache at the hit: the sky/emission band gives the second
            # bounce even at ONE_BOUNCE quality; MULTI_BOUNCE's table adds the bounced band.
            e_in = e_lamps + nearest_irradiance(cache, table, surf.position, surf.normal)
            rad_i[idx] = surf.albedo * e_in * np.float32(1.0 / np.pi)
        times["shadow"] = shadow_ms
        times["shade"] = (time.perf_counter() - tic) * 1e3 - shadow_ms

        tic = time.perf_counter()
        t = np.where(hit, hits.t, np.float32(np.inf)).reshape(m, r)
        values[:, 0:3] = rad_d.reshape(m, r, 3).transpose(0, 2, 1)
        values[:, 3:6] = rad_i.reshape(m, r, 3).transpose(0, 2, 1)
        values[:, 6] = t > s.ao_distance
        coeffs = sh.project_channels(values, dirs, s.sh_order)  # (m, K, 7)
        depth = np.minimum(t, cache.depth_cap).astype(np.float32)
        texel = octahedral_texel(dirs, s.depth_texels)
        onehot = np.zeros((r, s.depth_texels**2), np.float32)
        onehot[np.arange(r), texel] = 1.0
        depth_sum = np.stack([depth @ onehot, (depth * depth) @ onehot], axis=2)
        samples = CellSamples(
            cells=cells,
            sh_direct=coeffs[..., 0:3],
            sh_indirect=coeffs[..., 3:6],
            ao_sh=coeffs[..., 6],
            depth_sum=depth_sum,
            depth_count=onehot.sum(axis=0),
            backface=backface.reshape(m, r).mean(axis=1).astype(np.float32),
        )
        times["sh"] = (time.perf_counter() - tic) * 1e3
        return samples, times
