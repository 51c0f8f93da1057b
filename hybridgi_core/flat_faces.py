"""Flat-shaded faces that are not planar: each of their triangles shaded by its own plane, as
Cycles shades them.

Why: Blender gives a flat face one normal at all its corners, the face's (Newell's over its
corners); Cycles knows no faces, and shades a flat triangle by its own geometric normal. Where a
flat quad is folded (a displaced or hand-edited grid, a terrain of flat facets), its two
triangles face apart and the face's normal is neither's: a 400 m flat-shaded terrain of random
heights read its far slopes' Normal pass 45 degrees off Cycles', their light 7% dim.

So the triangles of flat faces whose own plane leaves the face's normal by more than
BENT_COS get corners of their own (appended, as the material bakes' atlas triangles do), their
normal the triangle's. Planar faces keep theirs (their triangles' normals are the face's).

numpy only (bpy-free); `addon/sync.py` reads the faces' smooth flags.
"""

from __future__ import annotations

import numpy as np

from .rows import cross_rows

#: Cosine between a flat face's normal and one of its triangles' planes below which the triangle
#: takes its own (about 0.5 degrees: float32 rounding and nearly planar quads stay as they are).
BENT_COS = 0.99996


def bent_flat_triangles(smooth: np.ndarray, positions: np.ndarray, normals: np.ndarray, triangles: np.ndarray,
                        tri_face: np.ndarray) -> np.ndarray:
    """(k,) int64 the triangles (rows of `triangles` (T, 3) corner indices, their faces
    `tri_face` (T,)) of flat faces (`smooth` (F,) bool False) whose plane leaves their corners'
    normal (`normals` (L, 3), the face's) by more than BENT_COS; `positions` (L, 3)."""
    flat = np.flatnonzero(~np.asarray(smooth, bool)[tri_face])
    if flat.size == 0:
        return flat.astype(np.int64)
    t = triangles[flat]
    p0 = positions[t[:, 0]].astype(np.float64)
    own = cross_rows(positions[t[:, 1]] - p0, positions[t[:, 2]] - p0)
    length = np.linalg.norm(own, axis=1)
    face = normals[t[:, 0]].astype(np.float64)
    cos = (own * face).sum(axis=1) / np.maximum(length * np.linalg.norm(face, axis=1), 1e-30)
    return flat[(length > 0) & (cos < BENT_COS)].astype(np.int64)


def own_corners(rows: np.ndarray, triangles: np.ndarray, positions: np.ndarray, normals: np.ndarray,
                uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(triangles, positions, normals, uvs, source): the triangles `rows` given corners of their
    own, appended after the L corners, their normal their own plane's (unit, wound as the
    triangle); source (L + 3 len(rows),) the corner each corner was copied from (itself for the
    first L)."""
    corners = triangles[rows].ravel()
    start = positions.shape[0]
    p = positions[corners].reshape(-1, 3, 3).astype(np.float64)
    own = cross_rows(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    own /= np.maximum(np.linalg.norm(own, axis=1), 1e-30)[:, None]
    out = triangles.copy()
    out[rows] = start + np.arange(corners.size, dtype=triangles.dtype).reshape(-1, 3)
    source = np.concatenate([np.arange(start, dtype=np.int64), corners.astype(np.int64)])
    return (out, np.concatenate([positions, positions[corners]]),
            np.concatenate([normals, np.repeat(own, 3, axis=0).astype(normals.dtype)]),
            np.concatenate([uvs, uvs[corners]]), source)
