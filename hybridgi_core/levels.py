"""Camera-centred cache levels (a clipmap): finer cells near the viewer, where detail is seen.

One regular grid over the scene (level 0, `GISystem.cache`) gives a 60 m yard 1.25 m cells, and
raising the resolution everywhere costs the cube of it. Level k > 0 is a grid of half the cell
size of level k - 1 over a box fitted to the G-buffer points nearest the camera
(`fit_level_grids`), filled by the same solver code from its visible cells only.

- Layout: the box holds the visible points up to a quantile of their view depth (LEVEL_QUANTILE,
  stepped down while the cells those points read in the box exceed LEVEL_BUDGET x the cells they
  read in level 0: a level costs a bounded multiple of the frame's own level-0 work), snapped
  outward to the coarser level's cell boundaries with MARGIN_CELLS of margin, shrunk towards the
  points' median while it holds over LEVEL_CELLS x the coarser level's cells (memory). Pure
  arithmetic on the frame's points: deterministic, the same on every machine of a farm, and
  stable under small camera moves (it moves in whole coarse cells).
- Solve: probe rays from the finer level's cells (`GISolver.trace_batch`: lamp light, sky,
  emitters, AO and depth exactly as level 0 stores them); the light of further bounces at their
  hits is read from level 0 (`HitLookup`, the same as pixel rays read it), already converged, so
  one projection is the multi-bounce answer and no fixed point is iterated per level.
- Lookup: a point takes level 0's gathered SH, then lerps towards each finer level's by that
  level's weight `t`: 0 outside its box and within half a cell of a border inside level 0
  (where its trilinear taps clamp), ramping to 1 over BLEND_CELLS of its cells inside. Blending the SH
  (not irradiances) keeps everything downstream linear: the pixel rays' control variate, the
  full-res re-evaluation at each pixel's normal. A point no valid finer cell covers keeps the
  coarser answer. Continuous across the border by construction (tests/test_levels.py).

Final renders (`raster/frame.py`): the pixel rays read the levels' SH (`sh_at`) and, at their
hits, each level's cell where it is valid (`LevelLookup`; finer cells are solved only where the
camera sees surfaces); without pixel rays the GPU gathers each level and `blend` joins them.
Probe hits of level 0 read level 0 only. Measured (bench/fine_detail.py, 320x240 vs Cycles 1024
spp): with pixel rays (the default) the cache is only their control variate and further bounces,
so levels change the error by less than +-0.0003 Combined; without pixel rays (the cache gather)
Combined improves, e.g. car 0.0073 -> 0.0057, contact 0.0121 -> 0.0111. numpy + embreex only.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .cache import IrradianceCache
from .errors import LimitError
from .evaluate import Gathered, HitLookup, corner_visibility, corner_weights, gather, monomials
from .grid import CacheGrid
from .settings import AO_ONLY, MULTI_BOUNCE
from .solver import SolveStats
from .visible import visible_cells

log = logging.getLogger(__name__)

#: Share of the visible points (nearest first, by view depth) a level's box holds at most ...
LEVEL_QUANTILE = 1.0
#: ... times QUANTILE_STEP while the cells they read in it exceed LEVEL_BUDGET x those they read
#: in level 0 (down to MIN_QUANTILE). Half the cell size reads ~4x the cells on the same
#: surfaces, so 4 lets a level cover the whole view when nothing else bounds it. Cache gather at
#: 320x240 vs Cycles, car: budget 1 -> Combined 0.0073, 4 -> 0.0066 (quantile steps of 0.5),
#: 0.0057 (steps of 0.8), unbounded 0.0057.
LEVEL_BUDGET = 4.0
QUANTILE_STEP = 0.8
MIN_QUANTILE = 1.0 / 64
#: Finer cells over which a level's weight ramps from 0 to 1 inside its box (after half a cell).
BLEND_CELLS = 2.0
#: Coarser cells a level's box reaches past its points: more than its blend ramp (half a finer
#: cell plus BLEND_CELLS of them), so the points it was fitted to read it alone.
MARGIN_CELLS = 2
#: Level k's cell is level k - 1's divided by this.
REFINE = 2
#: A level holds at most this many times the cells of the one it refines (memory; only the cells
#: the camera sees are traced).
LEVEL_CELLS = 4


def fit_level(parent: CacheGrid, points: np.ndarray, depth: np.ndarray, quantile: float) -> CacheGrid | None:
    """The grid of half `parent`'s cell size over the points (n, 3) up to `quantile` of their view
    depths (n,) (see the module docstring); None for fewer than 8 points."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    depth = np.asarray(depth, np.float64).reshape(-1)
    if points.shape[0] < 8:
        return None
    near = points[depth <= np.quantile(depth, quantile)]
    c = float(parent.cell_size)
    plo = np.asarray(parent.lo, np.float64)
    dims = np.asarray(parent.dims, np.int64)
    a = np.floor((near.min(axis=0) - plo) / c).astype(np.int64) - MARGIN_CELLS
    b = np.ceil((near.max(axis=0) - plo) / c).astype(np.int64) + MARGIN_CELLS
    a, b = np.clip(a, 0, dims), np.clip(b, 0, dims)
    b = np.maximum(b, a + 1)
    # At most LEVEL_CELLS x the coarser level's cells (memory, GPU textures): the longest span
    # shrinks, one coarse cell at a time, towards the points' median (thin axes keep).
    mid = (np.median(near, axis=0) - plo) / c
    while int(np.prod(b - a)) * REFINE**3 > LEVEL_CELLS * parent.count and (b - a).max() > 1:
        axis = int(np.argmax(b - a))
        if mid[axis] - a[axis] > b[axis] - mid[axis]:
            a[axis] += 1
        else:
            b[axis] -= 1
    return CacheGrid((plo + a * c).astype(np.float32), c / REFINE, tuple(int(x) for x in (b - a) * REFINE))


def fit_level_grids(base: CacheGrid, points: np.ndarray, normals: np.ndarray, depth: np.ndarray, levels: int,
                    normal_bias: float, budget: float = LEVEL_BUDGET) -> list[CacheGrid]:
    """Grids of levels 1 .. levels - 1 (fewer when the points run out) for visible points (n, 3)
    with unit normals (n, 3) at view depths (n,): each holds the points up to a depth quantile,
    LEVEL_QUANTILE first, times QUANTILE_STEP (down to MIN_QUANTILE) while the cells the points read in it
    exceed `budget` x the cells they read in level 0 (what the level costs to trace and solve).
    Deterministic in its inputs."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    normals = np.asarray(normals, np.float32).reshape(-1, 3)
    depth = np.asarray(depth, np.float32).reshape(-1)
    limit = budget * max(visible_cells(base, points, normals, normal_bias).size, 1)
    grids: list[CacheGrid] = []
    parent, sel = base, np.arange(points.shape[0])
    for _ in range(1, levels):
        q = LEVEL_QUANTILE
        while True:
            grid = fit_level(parent, points[sel], depth[sel], q)
            if grid is None:
                return grids
            rows = np.flatnonzero(level_weight(grid, points, base) > 0)
            if visible_cells(grid, points[rows], normals[rows], normal_bias).size <= limit or q <= MIN_QUANTILE:
                break
            q *= QUANTILE_STEP
        grids.append(grid)
        inside = np.all((points[sel] >= grid.lo) & (points[sel] <= grid.hi), axis=1)
        parent, sel = grid, sel[inside]
    return grids


def level_weight(grid: CacheGrid, points: np.ndarray, bounds: CacheGrid | None = None) -> np.ndarray:
    """(n,) float32 in 0..1: how much a finer level's answer replaces the coarser one at points.

    bounds : level 0's grid; faces of `grid` that lie on its border ramp nothing (there is no
    coarser cell beyond them to blend towards, and a room's walls and floor lie there)."""
    p = np.asarray(points, np.float32)
    cell = np.float32(grid.cell_size)
    below, above = p - grid.lo, grid.hi - p
    if bounds is not None:
        tol = np.float32(1e-3) * cell
        below = np.where(np.abs(grid.lo - bounds.lo) <= tol, np.where(below >= -tol, np.inf, below), below)
        above = np.where(np.abs(grid.hi - bounds.hi) <= tol, np.where(above >= -tol, np.inf, above), above)
    d = np.minimum(below, above).min(axis=1)
    return np.clip((d - np.float32(0.5) * cell) / (np.float32(BLEND_CELLS) * cell), 0.0, 1.0).astype(np.float32)


class CacheLevels:
    """Level 0 (the system's cache) and the finer levels' caches; what reads the cache per pixel
    (`pixel_gather`, `GISystem.gather` / `corner_visibility`) goes through `sh_at`."""

    def __init__(self, base: IrradianceCache, fine: list[IrradianceCache]):
        self.caches = [base] + list(fine)

    @property
    def count(self) -> int:
        return len(self.caches)

    def weights(self, points: np.ndarray) -> list[np.ndarray]:
        """Per finer level k = 1.. its (n,) weight at points (geometric: before coverage)."""
        return [level_weight(c.grid, points, self.caches[0].grid) for c in self.caches[1:]]

    def corner_visibility(self, tracer, points: np.ndarray, normals: np.ndarray, epsilon: float) -> np.ndarray:
        """(n, 8 x levels) bool: `evaluate.corner_visibility` of each level, columns 8k .. 8k + 7
        for level k; traced only where that level's weight is above 0 (True elsewhere, unread)."""
        points = np.asarray(points, np.float32).reshape(-1, 3)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        out = np.ones((points.shape[0], 8 * self.count), bool)
        out[:, :8] = corner_visibility(self.caches[0], tracer, points, normals, epsilon)
        for k, (cache, t) in enumerate(zip(self.caches[1:], self.weights(points), strict=True), 1):
            rows = np.flatnonzero(t > 0)
            if rows.size:
                out[rows, 8 * k:8 * k + 8] = corner_visibility(cache, tracer, points[rows], normals[rows], epsilon)
        return out

    def sh_at(self, points: np.ndarray, normals: np.ndarray, corner_visible: np.ndarray | None):
        """`pixel_gather.cache_sh_at` over the levels: (direct (n, K, 3), indirect (n, K, 3), ao (n, K),
        covered (n,)), each finer level lerped in by its weight where it covers the point."""
        from .pixel_gather import cache_sh_at  # noqa: PLC0415 (pixel_gather reads levels through systems)

        points = np.asarray(points, np.float32).reshape(-1, 3)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        vis = (lambda rows, k: None) if corner_visible is None else (
            lambda rows, k: corner_visible[rows, 8 * k:8 * k + 8])
        sh_d, sh_i, sh_a, covered = cache_sh_at(self.caches[0], points, normals, vis(slice(None), 0))
        for k, (cache, t) in enumerate(zip(self.caches[1:], self.weights(points), strict=True), 1):
            rows = np.flatnonzero(t > 0)
            if rows.size == 0:
                continue
            d, i, a, cov = cache_sh_at(cache, points[rows], normals[rows], vis(rows, k))
            # Uncovered here: the coarser answer alone; uncovered there: this level's alone.
            tr = np.where(cov, np.where(covered[rows], t[rows], np.float32(1.0)), np.float32(0.0))
            for arr, new in ((sh_d, d), (sh_i, i), (sh_a, a)):
                w = tr.reshape((-1,) + (1,) * (new.ndim - 1))
                arr[rows] += w * (new - arr[rows])
            covered[rows] |= cov
        return sh_d, sh_i, sh_a, covered

    def level_shares(self, points: np.ndarray, normals: np.ndarray,
                     corner_visible: np.ndarray | None = None) -> list[np.ndarray]:
        """Per finer level k = 1.. the (n,) share its answer takes over the blend of the coarser
        ones: its weight where one of its valid cells covers the point (with the gather's own
        visibility weights), 1 where it covers a point no coarser level does, else 0."""
        points = np.asarray(points, np.float32).reshape(-1, 3)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        covered = self._covered(0, points, normals, corner_visible)
        shares = []
        for k, t in enumerate(self.weights(points), 1):
            share = np.zeros(points.shape[0], np.float32)
            rows = np.flatnonzero(t > 0)
            if rows.size:
                vis = None if corner_visible is None else corner_visible[rows]
                cov = self._covered(k, points[rows], normals[rows], vis)
                share[rows] = np.where(cov, np.where(covered[rows], t[rows], np.float32(1.0)), np.float32(0.0))
                covered[rows] |= cov
            shares.append(share)
        return shares

    def _covered(self, k: int, points, normals, corner_visible) -> np.ndarray:
        vis = None if corner_visible is None else corner_visible[:, 8 * k:8 * k + 8]
        _, w = corner_weights(self.caches[k], points, normals, True, vis)
        return w.sum(axis=1) > 0

    def blend(self, parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], shares: list[np.ndarray]) -> Gathered:
        """Each level's gathered (direct (n, 3), indirect (n, 3), ao (n,)), coarsest first, lerped
        level by level by `level_shares`: what the GPU's levelled gather (one gather per level,
        `raster/frame.py`) and `gather` (its numpy reference) both return."""
        d, i, a = (np.array(x, np.float32) for x in parts[0])
        for (dk, ik, ak), t in zip(parts[1:], shares, strict=True):
            d += t[:, None] * (dk - d)
            i += t[:, None] * (ik - i)
            a += t * (ak - a)
        return Gathered(d, i, a)

    def gather(self, points: np.ndarray, normals: np.ndarray, corner_visible: np.ndarray | None = None) -> Gathered:
        """`evaluate.gather` of each level blended (`blend`): the numpy reference of the GPU's
        levelled gather. corner_visible : (n, 8 x levels) or None (Chebyshev tests)."""
        points = np.asarray(points, np.float32).reshape(-1, 3)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        parts = []
        for k, cache in enumerate(self.caches):
            vis = None if corner_visible is None else corner_visible[:, 8 * k:8 * k + 8]
            g = gather(cache, points, normals, corner_visible=vis)
            parts.append((g.direct, g.indirect, g.ao))
        return self.blend(parts, self.level_shares(points, normals, corner_visible))

    def level_at(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(n,) int: the finest level whose weight is at least 0.5 and that covers each point
        (the Cache Cells debug view colours by it)."""
        level = np.zeros(np.asarray(points).reshape(-1, 3).shape[0], np.int64)
        for k, (cache, t) in enumerate(zip(self.caches[1:], self.weights(points), strict=True), 1):
            rows = np.flatnonzero(t >= 0.5)
            if rows.size:
                _, w = corner_weights(cache, np.asarray(points)[rows], np.asarray(normals)[rows])
                level[rows[w.sum(axis=1) > 0]] = k
        return level


class LevelLookup:
    """`evaluate.HitLookup` over the levels for pixel-ray hits: each finer level's single-cell
    irradiance lerped in by its weight where the hit's cell there is valid (finer levels hold
    only the cells the camera sees; elsewhere the coarser level answers)."""

    def __init__(self, levels: CacheLevels, bounced: bool):
        self.levels = levels
        self.lookups = [HitLookup(c, bounced=bounced) for c in levels.caches]

    def irradiance(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(3, n) float32 irradiance >= 0 at points (n, 3) with unit normals (n, 3)."""
        e = self.lookups[0].irradiance(points, normals)
        for lookup, t in zip(self.lookups[1:], self.levels.weights(points), strict=True):
            rows = np.flatnonzero(t > 0)
            if rows.size == 0:
                continue
            p, nrm = points[rows], normals[rows]
            flat = lookup.cells(p, nrm)
            tr = np.where(lookup.valid[flat], t[rows], np.float32(0.0))
            fine = lookup.evaluate(flat, monomials(nrm, lookup.terms))
            e[:, rows] += tr * (fine - e[:, rows])
        return e


def hit_lookup(system, bounced: bool):
    """What pixel-ray hits read: the system's levels (`LevelLookup`), else level 0's HitLookup."""
    levels = getattr(system, "levels", None)
    if levels is None:
        return HitLookup(system.cache, bounced=bounced)
    return LevelLookup(levels, bounced)


def build_levels(system, points: np.ndarray, normals: np.ndarray, depth: np.ndarray, batches: int,
                 stats: SolveStats | None = None) -> CacheLevels | None:
    """Fit, trace and solve the finer levels of `system` (a GISystem whose level 0 is converged)
    for the frame's visible points (n, 3), normals and view depths (n,). None: no finer level."""
    from .solver import GISolver  # noqa: PLC0415

    s = system.settings
    stats = stats if stats is not None else SolveStats()
    grids = fit_level_grids(system.cache.grid, points, normals, depth, s.cache_levels, s.normal_bias)
    if not grids:
        return None
    base = system.cache
    bounced = s.indirect_quality == MULTI_BOUNCE
    # The finer levels' hits sample the emitters as level 0's did (`GISolver.hit_emitters`), and
    # then read level 0 without them: read with them too, a furnace's walls lit them twice (1.5 x).
    sampled = base.sh_direct_hit is not None and system.solver.hit_emitters() is not None
    direct = base.sh_direct_hit if sampled else base.sh_direct
    lookup = (HitLookup(base, bounced=bounced, coeffs=direct + base.sh_indirect if bounced else direct)
              if s.indirect_quality != AO_ONLY else None)
    fine = []
    for grid in grids:
        try:
            cache = IrradianceCache(grid, s)
        except LimitError as err:  # over the cache memory or texture limit: the coarser levels serve
            log.warning("cache level %d not built: %s", len(fine) + 1, err)
            break
        t = level_weight(grid, points, base.grid)
        rows = np.flatnonzero(t > 0)
        cells = visible_cells(grid, points[rows], normals[rows], s.normal_bias)
        if cells.size == 0:
            break
        solver = GISolver(cache, system.tracer, system.updater.scene, system.tracer.epsilon, system.updater.pool)
        solver.viewpoint = system.viewpoint  # its cells the camera sees are open too (`open_space.py`)
        solver.sample_emitters = sampled
        solver.begin(cells)
        for b in range(max(1, batches)):
            stats.merge(solver.trace_batch(b))
        if lookup is not None:
            tic = time.perf_counter()
            chunks = solver.chunks
            jobs = [system.updater.pool.submit(_project_from, c, cache.centers, lookup) for c in chunks]
            got_cells, mean = solver._mean_over_batches([j.result() for j in jobs], chunks)
            cache.sh_indirect[got_cells] = mean
            cache.version += 1
            stats.add("levels_bounce", (time.perf_counter() - tic) * 1e3)
        tic = time.perf_counter()
        stats.shadow_points += solver.filter_cells()
        stats.add("levels_filter", (time.perf_counter() - tic) * 1e3)
        fine.append(cache)
        log.info("cache level %d: %s cells of %.3f m from %s, %d solved", len(fine), grid.dims, grid.cell_size,
                 np.round(grid.lo, 2).tolist(), cells.size)
    return CacheLevels(base, fine) if fine else None


def _project_from(chunk, centers: np.ndarray, lookup: HitLookup) -> np.ndarray:
    """Worker: (m, K, 3) indirect-band SH of one stored chunk: brdf x (lamp light + level 0's
    irradiance at the hits: sky, emitters and every further bounce)."""
    e = lookup.irradiance(chunk.positions(centers), chunk.normal)
    e += chunk.e_lamp
    e *= chunk.brdf
    values = np.zeros((3, chunk.rays), np.float32)
    values[:, chunk.hit] = e
    return chunk.project(values)
