"""Step 3 of the seed pipeline: the cache cells that the visible surfaces read.

Only cells the gather will touch for some pixel of the (downsampled) G-buffer are updated, so the
ray budget follows the camera.
"""

from __future__ import annotations

import numpy as np

from .grid import CacheGrid
from .rows import finite_rows, row_norms


def visible_cells(grid: CacheGrid, positions: np.ndarray, normals: np.ndarray, normal_bias: float) -> np.ndarray:
    """Sorted unique flat cells around G-buffer points.

    positions, normals : (n, 3) float32 of pixels with geometry (background already removed);
    normal_bias : cells, the same offset the gather applies. Returns (m,) int64.
    """
    if positions.shape[0] == 0:
        return np.zeros(0, np.int64)
    p = np.asarray(positions, np.float32) + np.asarray(normals, np.float32) * np.float32(normal_bias * grid.cell_size)
    # Neighbouring pixels share cells: dedupe the base cell first so the 8-corner expansion is
    # small. Through a 1-D key, and a mask over the keys rather than np.unique (no sort of the
    # up to 2M surface samples of `GISystem.surface_cells`); both give the sorted unique keys.
    dims = np.asarray(grid.dims)
    g = np.floor((p - grid.lo) / np.float32(grid.cell_size) - 0.5).astype(np.int64)
    g = np.clip(g, -1, dims - 1) + 1  # base cells span -1 .. dims-1: shift to 0 .. dims
    sx, sy = dims[0] + 1, dims[1] + 1
    key = _unique_below(g[:, 0] + sx * (g[:, 1] + sy * g[:, 2]), int(sx * sy * (dims[2] + 1)))
    g = np.stack([key % sx, (key // sx) % sy, key // (sx * sy)], axis=1) - 1
    corners = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])
    ijk = np.clip(g[:, None, :] + corners[None], 0, dims - 1).reshape(-1, 3)
    return _unique_below(grid.flatten(ijk), grid.count)


def _unique_below(values: np.ndarray, bound: int) -> np.ndarray:
    """np.unique of non-negative ints below `bound` (int64), by a mask when that is smaller than
    a sort of the values would be."""
    if values.size * 8 < bound:
        return np.unique(values).astype(np.int64)
    mask = np.zeros(bound, bool)
    mask[values] = True
    return np.flatnonzero(mask).astype(np.int64)


def pixels_to_points(position_rgba: np.ndarray, normal_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flatten G-buffer read-backs to the pixels that hold geometry.

    position_rgba : (h, w, 4) with w = 1 on geometry; normal_rgb : (h, w, >=3).
    Returns positions (n, 3), normals (n, 3) float32 and the (n,) flat pixel indices.
    """
    pos = position_rgba.reshape(-1, position_rgba.shape[-1])
    nrm = normal_rgb.reshape(-1, normal_rgb.shape[-1])[:, :3]
    idx = np.flatnonzero((pos[:, 3] > 0.5) & finite_rows(pos[:, :3]))
    n = nrm[idx].astype(np.float32)
    n /= np.maximum(row_norms(n), np.float32(1e-12))[:, None]
    return pos[idx, :3].astype(np.float32), n, idx


#: Cache Cells debug view: the hue of each finer cache level (`levels.py`) from level 1 on
#: (level 0 keeps its pastel hash colours); cells of a level vary in brightness only.
LEVEL_TINTS = ((0.25, 0.5, 1.0), (0.3, 1.0, 0.35))


def cell_debug_colors(cache, points: np.ndarray, normals: np.ndarray, levels=None) -> np.ndarray:
    """(n, 3) float32 debug colours: a stable hash colour per cell, the neighbour with the largest
    gather weight at each point; full brightness where it is converged (>= 1 / (1 - hysteresis)
    samples), dim while converging, dark grey where no valid cell is near, dark red where the
    nearest cell is disabled inside geometry. levels : the system's `CacheLevels` or None; given,
    points whose finest covering level (`CacheLevels.level_at`) is k >= 1 show that level's cells
    in its hue (LEVEL_TINTS[k - 1]), so the levels' boxes and cell sizes can be seen."""
    rgb, _ = _cell_colors(cache, points, normals)
    if levels is None:
        return rgb
    level = levels.level_at(points, normals)
    for k in range(1, levels.count):
        rows = np.flatnonzero(level == k)
        if rows.size:
            _, h = _cell_colors(levels.caches[k], points[rows], normals[rows])
            shade = 0.45 + 0.55 * (h & np.uint64(0xFF)).astype(np.float32) / 255.0
            rgb[rows] = np.asarray(LEVEL_TINTS[(k - 1) % len(LEVEL_TINTS)], np.float32) * shade[:, None]
    return rgb


def _cell_colors(cache, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`cell_debug_colors` of one cache, and the (n,) uint64 hash of each point's cell."""
    from .evaluate import corner_weights  # noqa: PLC0415 (evaluate imports this module's siblings)

    flats, w = corner_weights(cache, points, normals)
    flat = flats[np.arange(flats.shape[0]), w.argmax(axis=1)]
    none = w.sum(axis=1) <= 0
    # Knuth multiplicative hash -> three bytes -> a pastel colour per cell.
    h = (flat.astype(np.uint64) * np.uint64(2654435761)) & np.uint64(0xFFFFFF)
    rgb = np.stack([(h >> np.uint64(s)) & np.uint64(0xFF) for s in (0, 8, 16)], axis=1).astype(np.float32) / 255.0
    rgb = 0.35 + 0.65 * rgb
    converged = cache.samples[flat] >= 1.0 / max(1.0 - cache.settings.hysteresis, 1e-3)
    rgb *= np.where(converged, 1.0, 0.5)[:, None]
    rgb[none] = (0.05, 0.05, 0.05)
    rgb[none & cache.inside[flats[:, 0]]] = (0.4, 0.0, 0.0)
    return rgb.astype(np.float32), h
