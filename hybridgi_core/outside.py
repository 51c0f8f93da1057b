"""What a surface outside the cache's grid reads: the sky above its horizon.

The grid covers the scene's objects (`SceneSnapshot.focus_bounds`); rays also reach surfaces
beyond it (the ground outside a room's window, a large floor past the grid's margin). A hit's
further bounces read the cache at the hit (`evaluate.HitLookup`), and one beyond the grid read
the nearest cell at the grid's edge: inside a room with thick walls, a cell in the wall or in
the room, whose light is not the open ground's. Such a hit now reads one cell of its own, lit by
the world above the horizon and nothing else: a ground outside sees the sky and little of the
scene, and below the horizon it would see ground, not sky.
"""

from __future__ import annotations

import numpy as np

from . import sh
from .sampling import spherical_fibonacci

#: Directions the world's light above the horizon is projected with (deterministic).
PROJECTION_DIRECTIONS = 4096


def sky_above_horizon(world, terms: int) -> np.ndarray:
    """(terms, 3) float32 radiance SH (the cache's bands' convention) of the world's light over
    the upper hemisphere (z >= 0), zero below it."""
    dirs = spherical_fibonacci(PROJECTION_DIRECTIONS).astype(np.float32)
    radiance = world.radiance(dirs) * (dirs[:, 2:3] >= 0)
    basis = sh.basis(dirs, 2 if terms == 9 else 1)
    return (basis.T @ radiance * np.float32(4.0 * np.pi / dirs.shape[0])).astype(np.float32)


def beyond(grid_coords: np.ndarray, dims) -> np.ndarray:
    """(n,) bool: points at cell coordinates grid_coords (n, 3) (cell units from the grid's lower
    corner) more than half a cell outside the grid of `dims` cells."""
    top = np.asarray(dims, np.float32) + np.float32(0.5)
    return ((grid_coords < np.float32(-0.5)) | (grid_coords > top)).any(axis=1)
