"""The 3D irradiance cache: per-cell SH radiance, AO, depth moments, and how samples blend in.

Per cell (N cells, K = 4 or 9 SH coefficients, D = depth_texels):
- sh_direct (N, K, 3): radiance that a surface near the cell receives straight from the sky or an
  emissive surface (Cycles counts both as Direct light)
- sh_indirect (N, K, 3): radiance reflected by surfaces (Cycles' Indirect)
- ao_sh (N, K): visibility within the AO distance, 1 = open
- depth (N, D*D, 2): mean and mean square probe-ray distance per octahedral texel (Chebyshev test)
- backface (N,): share of rays hitting back faces; above `inside_threshold` the cell sits inside
  geometry and is disabled, so it does not darken its neighbours, unless it is `open`
- open (N,): cells the camera saw unblocked, in its own space however the faces around them
  point (`open_space.py`: a room modelled with its normals facing out)
- samples (N,), last_frame (N,): shaded updates blended so far and the frame of the latest update.
  Cells inside geometry are traced (their rays keep the inside test and depth current) but not
  shaded: nothing reads their radiance. A cell that comes out of geometry restarts at 0 samples,
  so it turns valid only once an update has shaded it.
- urgency (N,): 0..1 extra blend weight for cells near something that changed (localized updates)
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .grid import CacheGrid
from .settings import CacheSettings
from .snapshot import SceneSnapshot

log = logging.getLogger(__name__)

#: Depth moments saturate at this many cell sizes: sharper Chebyshev tests (DDGI clamps likewise).
DEPTH_CAP_CELLS = 2.0


@dataclass
class CellSamples:
    """One update's estimates for a set of cells, shaped like the cache arrays indexed by `cells`."""

    cells: np.ndarray  # (m,) int64
    sh_direct: np.ndarray  # (m, K, 3)
    sh_indirect: np.ndarray  # (m, K, 3)
    ao_sh: np.ndarray  # (m, K)
    depth_sum: np.ndarray  # (m, T, 2) sums of d and d^2 over this update's rays per texel
    depth_count: np.ndarray  # (T,) rays per texel when every cell shares the directions, else (m, T)
    backface: np.ndarray  # (m,)
    shaded: np.ndarray | None = None  # (m,) bool: radiance bands estimated (None = all)
    #: (m, K, 3) the direct band without the emitters that probe-ray hits sample themselves
    #: (`solver.GISolver`), or None: hits read `sh_direct`
    sh_direct_hit: np.ndarray | None = None


class IrradianceCache:
    def __init__(self, grid: CacheGrid, settings: CacheSettings):
        self.grid = grid
        self.settings = settings
        settings.check_cell_count(grid.dims)  # LimitError before any array is allocated
        n, k = grid.count, settings.sh_coeffs
        t = settings.depth_texels**2
        self.sh_direct = np.zeros((n, k, 3), np.float32)
        self.sh_indirect = np.zeros((n, k, 3), np.float32)
        #: (n, K, 3) the direct band as probe-ray hits read it where they sample the emitters
        #: themselves (`CellSamples.sh_direct_hit`; the solver's first blend allocates it), or None
        self.sh_direct_hit = None
        self.ao_sh = np.zeros((n, k), np.float32)
        self.depth = np.zeros((n, t, 2), np.float32)
        self.depth_cap = np.float32(DEPTH_CAP_CELLS * grid.cell_size)
        self.depth[..., 0] = self.depth_cap
        self.depth[..., 1] = self.depth_cap**2
        self.backface = np.zeros(n, np.float32)
        self.open = np.zeros(n, bool)
        self.samples = np.zeros(n, np.int32)
        self.last_frame = np.full(n, -(2**31), np.int64)
        self.urgency = np.zeros(n, np.float32)
        self.centers = grid.centers()
        #: (K, 3) radiance SH a surface beyond the grid reads (`outside.py`: the world above its
        #: horizon), or None: such surfaces read the grid's edge cells. Set by the system.
        self.outside: np.ndarray | None = None
        #: Bumped on every blend; GPU uploads compare it to skip unchanged caches.
        self.version = 0

    @classmethod
    def for_scene(cls, scene: SceneSnapshot, settings: CacheSettings) -> IrradianceCache:
        lo, hi = scene.focus_bounds()
        return cls(CacheGrid.from_bounds(lo, hi, settings.resolution), settings)

    @property
    def inside(self) -> np.ndarray:
        """(N,) bool: cells disabled because they sit inside geometry (not `open` to the camera)."""
        return (self.backface > self.settings.inside_threshold) & ~self.open

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: cells the gather may read (sampled at least once and not inside geometry)."""
        return (self.samples > 0) & ~self.inside

    def blend_weights(self, cells: np.ndarray) -> np.ndarray:
        """(m,) float32 weight of a new sample: the EMA's 1 - hysteresis, more while a cell is young
        (1 / (n + 1): a plain mean until the EMA window is reached) or urgent."""
        fresh = 1.0 / (self.samples[cells].astype(np.float32) + 1.0)
        base = np.float32(1.0 - self.settings.hysteresis)
        return np.maximum(np.maximum(fresh, base), self.urgency[cells])

    def blend(self, s: CellSamples, frame: int, alpha: float | None = None) -> None:
        """Fold one update into the cache with the exponential moving average (or with the given
        weight: 1 replaces, as the warm-up's bounce propagation does). Radiance bands of rows
        that were not shaded keep their values."""
        c = s.cells
        a = self.blend_weights(c) if alpha is None else np.full(c.size, alpha, np.float32)
        a1 = a[:, None]
        m = c.size
        shaded = np.ones(m, bool) if s.shaded is None else np.asarray(s.shaded, bool)
        a_rad = (a * shaded)[:, None]
        # Flat (m, -1) rows: broadcasting a per-cell weight over short trailing axes is slow.
        bands = [("sh_direct", s.sh_direct, a_rad), ("sh_indirect", s.sh_indirect, a_rad), ("ao_sh", s.ao_sh, a1)]
        if s.sh_direct_hit is not None:
            if self.sh_direct_hit is None:
                self.sh_direct_hit = self.sh_direct.copy()
            bands.append(("sh_direct_hit", s.sh_direct_hit, a_rad))
        for name, new, w in bands:
            arr = getattr(self, name)
            old = arr[c].reshape(m, -1)
            delta = new.reshape(m, -1) - old
            delta *= w
            old += delta
            arr[c] = old.reshape((m,) + arr.shape[1:])
        was_inside = self.inside[c]
        self.backface[c] += a * (s.backface - self.backface[c])
        # Depth: only texels that received rays this update move, each towards its own mean
        # (whole rows, with a zero weight on empty texels: cheaper than indexing the subset).
        count = np.repeat(s.depth_count, 2, axis=-1)  # matches the (T, 2) moment pairs, flattened
        if (count > 0).any():
            old = self.depth[c].reshape(m, -1)
            delta = s.depth_sum.reshape(m, -1) / np.maximum(count, np.float32(1.0))
            delta -= old
            delta *= a1 * (count > 0)
            old += delta
            self.depth[c] = old.reshape(m, *self.depth.shape[1:])
        self.samples[c] += shaded
        # Out of geometry (it moved): radiance from before is stale; valid again once shaded.
        self.samples[c[was_inside & ~self.inside[c]]] = 0
        self.last_frame[c] = frame
        # Urgency decays as the refreshed cells take samples: the burst lasts a few updates.
        self.urgency[c] *= 0.5
        self.version += 1

    # --- named events (what depsgraph and frame-change handlers call) ---------------------------

    def influence_radius(self) -> float:
        """Metres around a change within which cells refresh: the indirect range.

        The seed limits indirect light to a quadratic fall-off; its range is the ray length when
        one is set, else a few cells (bounce light from a small change fades within it).
        """
        s = self.settings
        return float(s.ray_length) if s.ray_length > 0 else 4.0 * self.grid.cell_size

    def on_geometry_changed(self, boxes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Objects inside these world boxes (old and new positions) moved or deformed.

        Cells within the influence radius get urgency (1 - (d / R)^2): refreshed with lower
        hysteresis, most strongly close to the change. Returns the affected flat cells.
        """
        radius = self.influence_radius()
        touched = []
        for lo, hi in boxes:
            cells, dist = self.grid.cells_near(lo, hi, radius)
            falloff = np.clip(1.0 - (dist / radius) ** 2, 0.0, 1.0).astype(np.float32)
            np.maximum.at(self.urgency, cells, falloff)
            # Depth moments and inside flags near the change are stale: let them re-form quickly
            # (and the camera look again: the change may have closed a space).
            self.open[cells] = False
            touched.append(cells)
        if not touched:
            return np.zeros(0, np.int64)
        return np.unique(np.concatenate(touched))

    def on_lights_changed(self) -> None:
        """Any lamp or the world changed: every cell's radiance is stale, its geometry is not.

        Radiance bands re-converge at a raised blend weight; AO, depth and inside flags keep.
        """
        np.maximum(self.urgency, np.float32(0.5), out=self.urgency)

    def reset(self) -> None:
        """Forget everything (new scene, new grid settings)."""
        self.__init__(self.grid, self.settings)
