"""Lamp light at probe hits, hashed in world space: shadow rays paid once per surface patch.

Each traced batch of probe directions lands new hits on the same surfaces, and the lamp light a
surface receives does not depend on which cell's ray found it. `LampLightTable` keeps the mean
lamp irradiance of the first batch's hits (traced with shadow rays) per bin: a voxel of
BIN_CELLS cache cells, split by the hit normal's octahedral texel (NORMAL_TEXELS^2 of them, so the
floor and a wall meeting in a voxel, or the two sides of a thin sheet, never share a bin). Hits of
later batches read their bin; only hits in bins the first batch never reached trace shadow rays.

The cache is low frequency (its cells are BIN_CELLS^-1 bins across), so blurring lamp light over
a bin changes no cell; it also averages the first batch's soft-shadow noise (one shadow ray per
hit) over every hit in the bin. numpy only.
"""

from __future__ import annotations

import numpy as np

from .sampling import octahedral_texel

#: Bin edge in cache cells.
BIN_CELLS = 0.25
#: Octahedral normal texels per side (the bin's normal split).
NORMAL_TEXELS = 4
_AXIS_BITS = 20  # voxel coordinates per axis: up to 2^20 bins across the grid


class LampLightTable:
    """Mean lamp irradiance (W/m^2, RGB) per (voxel, normal texel) bin of surface hits."""

    def __init__(self, lo: np.ndarray, cell_size: float):
        self.lo = np.asarray(lo, np.float32)
        self.inv_bin = np.float32(1.0 / (BIN_CELLS * cell_size))
        self.keys = np.zeros(0, np.int64)
        self.mean = np.zeros((3, 0), np.float32)

    def key(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(n,) int64 bin of hits at points (n, 3) with unit normals (n, 3)."""
        v = ((np.asarray(points, np.float32) - self.lo) * self.inv_bin).astype(np.int64)
        np.clip(v, 0, (1 << _AXIS_BITS) - 1, out=v)
        k = octahedral_texel(normals, NORMAL_TEXELS).astype(np.int64)
        k |= v[:, 0] << 8
        k |= v[:, 1] << (8 + _AXIS_BITS)
        k |= v[:, 2] << (8 + 2 * _AXIS_BITS)
        return k

    def build(self, keys: np.ndarray, irradiance: np.ndarray) -> None:
        """Replace the table by the means of irradiance (3, n) over each key (n,)."""
        self.keys, inverse = np.unique(keys, return_inverse=True)
        count = np.bincount(inverse, minlength=self.keys.size).astype(np.float32)
        self.mean = np.stack(
            [np.bincount(inverse, weights=irradiance[c], minlength=self.keys.size) for c in range(3)]
        ).astype(np.float32)
        self.mean /= np.maximum(count, np.float32(1.0))

    @property
    def empty(self) -> bool:
        return self.keys.size == 0

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """found (n,) bool and irradiance (3, n) float32 (0 where not found) of bins keys (n,)."""
        if self.empty:
            return np.zeros(keys.shape[0], bool), np.zeros((3, keys.shape[0]), np.float32)
        pos = np.searchsorted(self.keys, keys)
        np.minimum(pos, self.keys.size - 1, out=pos)
        found = self.keys[pos] == keys
        e = np.take(self.mean, pos, axis=1)
        e[:, ~found] = 0.0
        return found, e
