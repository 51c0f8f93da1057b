"""Steps 4-5 of the seed pipeline: trace probe rays from visible cells, shade the hits, project to
SH and blend into the cache.

Runs on numpy snapshots and embreex only, so it may run in worker threads (embreex releases the
GIL, and so do numpy's large array operations). Chunks of cells are processed in parallel and
blended on the calling thread afterwards, so results do not depend on thread timing.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field

import numpy as np

from . import sh
from .blas_threads import single_threaded_blas
from .cache import CellSamples, IrradianceCache
from .evaluate import HitLookup
from .lights import HIT_LAMP_BUDGET, direct_irradiance
from .sampling import frame_directions, frame_rng, octahedral_texel
from .settings import AO_ONLY, MULTI_BOUNCE
from .shading import SurfaceTable
from .snapshot import Light, World
from .trace import Tracer

STEPS = ("trace", "shade", "shadow", "sh", "blend")
#: Most rays per work item. Big items amortize the per-call overhead of numpy and embree and
#: contend less for the GIL; too big and the shading temporaries fall out of cache (measured on
#: the 307k-ray atrium update, 2 cores: 24k rays 64 ms, 48k 60 ms, 96k 56 ms, 150k 70 ms).
#: `update` splits into equal items, a multiple of the thread count.
CHUNK_RAYS = 98304
#: Fewest rays per chunk worth splitting an update further for load balance.
MIN_CHUNK_RAYS = 16384
#: Below this share of hits a chunk's hits are compacted before shading; above it every ray is
#: shaded in place (misses read a zero surface record), which skips the gathers and scatters.
COMPACT_BELOW = 0.75


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


#: Thread-name prefix of the worker pools (`CacheUpdater.on_pool_thread`).
POOL_PREFIX = "hybridgi-update"


class CacheUpdater:
    """Owns the worker pool; `update(cells, frame)` is one EMA step for those cells."""

    def __init__(self, cache: IrradianceCache, tracer: Tracer, scene: ShadingScene, epsilon: float):
        self.cache = cache
        self.tracer = tracer
        self.scene = scene
        self.epsilon = np.float32(epsilon)
        single_threaded_blas()  # the pool is the parallelism (`blas_threads`)
        self._pool = ThreadPoolExecutor(max_workers=cache.settings.threads, thread_name_prefix=POOL_PREFIX)

    @property
    def pool(self) -> ThreadPoolExecutor:
        """The worker pool (the solver shares it)."""
        return self._pool

    @staticmethod
    def on_pool_thread() -> bool:
        """Whether the caller runs on a worker of such a pool: work it would split over the pool
        must run inline there (a worker waiting on jobs queued behind itself deadlocks)."""
        return threading.current_thread().name.startswith(POOL_PREFIX)

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
        # Hits read the cache as it was before this update, whatever the thread timing: the
        # lookup is a snapshot, so chunks blend as they finish.
        lookup = HitLookup(cache, bounced=s.indirect_quality == MULTI_BOUNCE)
        # Equal chunks, a multiple of the threads and at least two per thread when the update is
        # big enough, each at most CHUNK_RAYS rays (one cell at least): a thread that drew cheap
        # cells takes another, and the last chunk's blend, which runs alone, stays small.
        threads = max(1, s.threads)
        n_chunks = -(-stats.rays // CHUNK_RAYS)
        if stats.rays >= 2 * threads * MIN_CHUNK_RAYS:
            n_chunks = max(n_chunks, 2 * threads)
        n_chunks = min(cells.size, -(-n_chunks // threads) * threads)
        jobs = [
            self._pool.submit(self._sample_chunk, chunk, dirs, lookup, frame_rng(s.seed, frame * 7919 + i))
            for i, chunk in enumerate(np.array_split(cells, n_chunks))
        ]
        # Chunks hold disjoint cells and a blend reads only its own cells: the order is free.
        for job in as_completed(jobs):
            samples, times = job.result()
            tb = time.perf_counter()
            cache.blend(samples, frame, alpha)
            times["blend"] = (time.perf_counter() - tb) * 1e3
            for k, v in times.items():
                stats.steps_ms[k] += v
        stats.wall_ms = (time.perf_counter() - t0) * 1e3
        return stats

    def _sample_chunk(self, cells: np.ndarray, dirs: np.ndarray, lookup: HitLookup, rng: np.random.Generator):
        """Estimates for one chunk of cells (worker thread: numpy and the tracer only).

        lookup : the cache as hits read it, taken before the update began."""
        cache = self.cache
        s = cache.settings
        times = {}
        # Cells inside geometry are traced (inside test, depth) but not shaded: nothing reads
        # their radiance. Outside cells go first, so the shaded rays are a prefix of the batch.
        inside = lookup.inside[cells]
        cells = np.concatenate([cells[~inside], cells[inside]])
        m, r = cells.size, dirs.shape[0]
        n = m * r
        m_s = int(m - np.count_nonzero(inside))  # shaded cells
        n_s = m_s * r
        tic = time.perf_counter()
        origins = np.repeat(cache.centers[cells], r, axis=0)
        ray_dirs = np.tile(dirs, (m, 1))
        tfar = np.float32(s.ray_length) if s.ray_length > 0 else np.float32(np.inf)
        hits = self.tracer.intersect(origins, ray_dirs, tfar, trusted=True)  # cell centres, unit directions
        times["trace"] = (time.perf_counter() - tic) * 1e3

        tic = time.perf_counter()
        hit = hits.prim[:n_s] >= 0
        # Channel-major rows per ray: direct RGB, indirect RGB, AO visibility; (7, n) reshapes to
        # the SH projection's (m, 7, r) blocks with one transposed copy.
        values = np.empty((7, n), np.float32)
        world = self.scene.world
        if world.sky_sh is None:
            values[0:3] = world.color[:, None]
        else:
            values[0:3] = world.radiance(ray_dirs).T  # a sky that varies with direction
        values[3:6] = 0.0
        np.greater(hits.t, s.ao_distance, out=values[6])  # misses have t = inf
        n_hit = int(np.count_nonzero(hit))
        # Mostly hits (interiors): shade every ray, misses read a zero record and add nothing.
        # Mostly misses (open scenes): compact the hits first.
        idx = None if n_hit >= COMPACT_BELOW * n_s else np.flatnonzero(hit)
        pick = (lambda a: a[:n_s]) if idx is None else (lambda a: a[idx])
        t_hit = np.where(hit, hits.t[:n_s], np.float32(0.0)) if idx is None else hits.t[idx]
        prim, hd = pick(hits.prim), pick(ray_dirs)
        surf = self.scene.surfaces.probe_hits(prim, pick(hits.u), pick(hits.v), hd)
        shadow_ms = 0.0
        if s.indirect_quality != AO_ONLY and n_hit:
            position = hd * t_hit[:, None]
            position += pick(origins)
            ts = time.perf_counter()
            # The cache is low frequency: one shadow ray along a sun's axis per hit is enough
            # (image pixels keep the sun's soft disc).
            e_in = direct_irradiance(
                self.scene.lights, position, surf.normal, self.tracer, rng,
                samples=s.light_samples, epsilon=float(self.epsilon), sun_disc=False, solid_angle=False,
                lamp_budget=HIT_LAMP_BUDGET,
            ).T
            shadow_ms = (time.perf_counter() - ts) * 1e3
            # Further bounces read the cache at the hit: the sky/emission band gives the second
            # bounce even at ONE_BOUNCE quality; MULTI_BOUNCE's table adds the bounced band.
            e_in += lookup.irradiance(position, surf.normal)
            e_in *= surf.brdf.T
            if idx is None:
                # Hits add their emission (a strided read: skipped where nothing emits); misses
                # read a zero record and get the sky back below.
                values[0:3, :n_s] = surf.emission.T if self.scene.surfaces.emissive else np.float32(0.0)
                if n_hit < n_s and world.any:
                    miss = np.flatnonzero(~hit)
                    values[0:3, miss] = world.radiance(ray_dirs[miss]).T
                values[3:6, :n_s] = e_in
            else:
                values[0:3, idx] = surf.emission.T
                values[3:6, idx] = e_in
        elif n_hit:
            values[0:3, :n_s][:, hit] = 0.0
        times["shadow"] = shadow_ms
        times["shade"] = (time.perf_counter() - tic) * 1e3 - shadow_ms

        tic = time.perf_counter()
        coeffs = sh.project_channels(values.reshape(7, m, r).transpose(1, 0, 2), dirs, s.sh_order)  # (m, K, 7)
        # Depth moments per (cell, octahedral texel): every cell shares the texels of the frame's
        # directions, so the sums are (2m, r) @ one-hot (r, T); bincount cost 3x more (it widens
        # its weights to float64).
        n_tex = s.depth_texels**2
        texel = octahedral_texel(dirs, s.depth_texels)
        one_hot = np.zeros((r, n_tex), np.float32)
        one_hot[np.arange(r), texel] = 1.0
        depth = np.empty((2, n), np.float32)
        np.minimum(hits.t, cache.depth_cap, out=depth[0])
        np.multiply(depth[0], depth[0], out=depth[1])
        sums = sh.matmul_on_this_thread(depth.reshape(2 * m, r), one_hot).reshape(2, m, n_tex)
        depth_sum = np.stack([sums[0], sums[1]], axis=-1)  # (m, T, 2)
        # Back faces of every ray, the unshaded ones included: they keep the inside test current.
        back = np.einsum("ij,ij->i", self.scene.surfaces.face_normals(hits.prim[n_s:]), ray_dirs[n_s:]) > 0
        if idx is None:
            back = np.concatenate([surf.backface, back])
        else:
            back = np.concatenate([np.bincount(idx, weights=surf.backface, minlength=n_s) > 0, back])
        backface = back.reshape(m, r).sum(axis=1, dtype=np.float32) * np.float32(1.0 / r)
        samples = CellSamples(
            cells=cells,
            sh_direct=coeffs[..., 0:3],
            sh_indirect=coeffs[..., 3:6],
            ao_sh=coeffs[..., 6],
            depth_sum=depth_sum,
            depth_count=one_hot.sum(axis=0),
            backface=backface,
            shaded=np.arange(m) < m_s,
        )
        times["sh"] = (time.perf_counter() - tic) * 1e3
        return samples, times
