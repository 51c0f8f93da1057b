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
space, whatever the faces around it say, and so does a cell next to an open one with nothing
between their centres (`open_to`: one occlusion ray from the camera to each cell flagged inside,
then from each open cell to its flagged face neighbours, until none opens; a solid's inside
stays closed, its surface blocks both). Scenes without such cells (no flagged cell the camera
sees) pay the camera's rays only. The Cornell box with every normal flipped, 640x360
against the unflipped box: Combined 0.0925 with the cells the camera sees opened (those behind
its blocks stayed off), 0.0029 with their neighbours too.
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
    cache.open[seen] = True
    opened = [seen]
    # Then the flagged cells next to an open one (any: a geometry event closes the cells near it,
    # behind an occluder too), and the flagged neighbours of each newly opened one, until none
    # opens. Driven from the flagged side: a room's thousands of open cells cost nothing once
    # open, only the few flagged cells that stay (a wall's inside) are looked at again.
    targets = np.flatnonzero(cache.inside)
    while targets.size:
        seen = _reached(cache, tracer, targets, epsilon)
        if seen.size == 0:
            break
        cache.open[seen] = True
        opened.append(seen)
        nb, ok = _face_neighbours(cache.grid, seen)
        targets = np.unique(nb[ok & cache.inside[nb]])
    opened = np.concatenate(opened)
    if opened.size:
        cache.version += 1
    return opened


#: Face neighbours of a cell, (i, j, k) steps.
_STEPS = np.array([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)], np.int64)


def _face_neighbours(grid, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((n, 6) flat face neighbours of `cells` (n,), clamped into the grid; (n, 6) bool: within it)."""
    ijk = grid.unflatten(cells)[:, None, :] + _STEPS[None, :, :]  # (n, 6, 3)
    dims = np.asarray(grid.dims, np.int64)
    within = np.all((ijk >= 0) & (ijk < dims), axis=-1)
    return grid.flatten(np.clip(ijk, 0, dims - 1)), within


def _reached(cache, tracer, targets: np.ndarray, epsilon: float) -> np.ndarray:
    """The flagged cells `targets` with an open face neighbour whose centre one occlusion ray
    joins to theirs unblocked (tested from one such neighbour each)."""
    nb, ok = _face_neighbours(cache.grid, targets)
    ok &= cache.open[nb]
    has = ok.any(axis=1)
    if not has.any():
        return np.zeros(0, np.int64)
    cells = targets[has]
    src = nb[has][np.arange(cells.size), ok[has].argmax(axis=1)]
    a = np.asarray(cache.centers[src], np.float32)
    to = np.asarray(cache.centers[cells], np.float32) - a
    dist = np.float32(cache.grid.cell_size)
    blocked = tracer.occluded(a, to / dist, np.full(cells.size, dist - np.float32(epsilon), np.float32), trusted=True)
    return cells[~blocked]
