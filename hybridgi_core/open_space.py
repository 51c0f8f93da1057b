"""Cells the camera shares its space with are never "inside geometry".

A cell whose probe rays mostly meet back faces counts as inside a solid (`IrradianceCache.inside`)
and is switched off, so that the dark inside of a wall or a column does not darken the surfaces
around it. But the same rays say the same about the inside of a room modelled with its normals
facing out (a scaled default cube, single-sided walls, an imported model with flipped normals),
where the camera stands: Cycles shades both sides of a surface and lights such a room as any
other, while every cell in it was switched off, and its surfaces borrowed light from cells
outside, through the walls (a room of single-sided walls with a window, 320x180 against Cycles:
Diffuse Indirect 65% low; a camera inside a closed 1 m cube: grey instead of black).

The camera cannot be inside a solid: a cell whose centre it sees unblocked lies in its open
space, whatever the faces around it say (`open_to`): one occlusion ray from the camera to each
such cell, at most once per cell while the geometry around it holds.
"""

from __future__ import annotations

import numpy as np


def open_to(cache, tracer, viewpoint, epsilon: float) -> np.ndarray:
    """Mark the cells flagged inside geometry whose centre `viewpoint` (3,) sees unblocked as open
    (`cache.open`); returns them (flat indices). Cells already open or not inside cost nothing;
    none without a viewpoint."""
    if viewpoint is None:
        return np.zeros(0, np.int64)
    cand = np.flatnonzero(cache.inside)
    if cand.size == 0:
        return cand
    eye = np.asarray(viewpoint, np.float32).reshape(3)
    to = np.asarray(cache.centers[cand], np.float32) - eye
    dist = np.sqrt(np.einsum("ij,ij->i", to, to))
    keep = dist > np.float32(epsilon)
    cand, to, dist = cand[keep], to[keep], dist[keep]
    if cand.size == 0:
        return cand
    dirs = to / dist[:, None]
    blocked = tracer.occluded(np.tile(eye, (cand.size, 1)), dirs, dist - np.float32(epsilon), trusted=True)
    seen = cand[~blocked]
    if seen.size:
        cache.open[seen] = True
        cache.version += 1
    return seen
