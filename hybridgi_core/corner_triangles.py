"""Blender's corner triangles (`Mesh.loop_triangles`) of meshes made of triangles and quads,
computed from the faces' sizes and corner positions instead of read from Blender.

Why: `loop_triangles.foreach_get` calls a getter per triangle (~25 ns a corner) and makes Blender
compute the triangles first: the atrium's 320k triangles cost 24 ms to read (35 ms the first
time) of its 135 ms sync; the dragon's 200k, 16 ms. The faces' sizes (`MeshPolygon.loop_total`,
~30 ns a face) are all it takes for a mesh of triangles and quads. (They are read even at three
corners a face on average: a script can make a face of two corners, which Blender triangulates
as nothing, beside a quad.)

The same triangles as Blender's `corner_tris_calc` (Blender 4.0 on: face i's corners are
offsets[i] .. offsets[i + 1] - 1, the offsets the sizes' running sum): a triangle (0 1 2); a quad
(0 1 2) (0 2 3), or (0 1 3) (1 2 3) where `is_quad_flip_v3_first_third_fast` finds its 0-2
diagonal outside a concave quad, the same float32 arithmetic in the same order. N-gons (Blender's
polygon fill) are left to Blender: `from_sizes` returns None.

numpy only (bpy-free); `addon/sync.py` reads the sizes and the positions.
"""

from __future__ import annotations

import numpy as np

from .rows import cross_rows

#: Fewest faces for which the sync makes a mesh's triangles here: below, numpy's per-call costs
#: (~50 us a mesh) exceed Blender's read (1000 separate 6-quad cubes: 185 -> 230 ms read here).
MIN_FACES = 256


def of_triangles(faces: int) -> tuple[np.ndarray, np.ndarray]:
    """(triangles (F, 3) int32 corner indices, triangle_faces (F,) int32) of a mesh of `faces`
    triangles: face i is the triangle of corners 3i, 3i + 1, 3i + 2."""
    return np.arange(3 * faces, dtype=np.int32).reshape(-1, 3), np.arange(faces, dtype=np.int32)


def from_sizes(sizes: np.ndarray, corner_positions: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(triangles (T, 3) int32 corner indices, triangle_faces (T,) int32) of a mesh whose faces
    have `sizes` (F,) corners (3 or 4), in Blender's order; None if a face has more (or fewer).

    corner_positions : (L, 3) float32, the position of each corner's vertex."""
    sizes = np.asarray(sizes)
    if sizes.size == 0:
        return None
    smallest, largest = int(sizes.min()), int(sizes.max())
    if smallest < 3 or largest > 4:  # an n-gon, or a face Blender's validation would remove
        return None
    if largest == 3:
        return of_triangles(sizes.size)
    starts = np.zeros(sizes.size, np.int64)
    np.cumsum(sizes[:-1], out=starts[1:])
    per_face = sizes.astype(np.int64) - 2  # 1 triangle a triangle, 2 a quad
    first = np.zeros(sizes.size, np.int64)
    np.cumsum(per_face[:-1], out=first[1:])
    total = int(first[-1] + per_face[-1])
    triangles = np.empty((total, 3), np.int32)
    faces = np.repeat(np.arange(sizes.size, dtype=np.int32), per_face)
    # Every face's first triangle (0 1 2); a quad's second (0 2 3).
    triangles[first] = starts[:, None] + np.arange(3)
    quads = np.flatnonzero(sizes == 4)
    if quads.size:
        s, second = starts[quads], first[quads] + 1
        triangles[second] = s[:, None] + np.array([0, 2, 3])
        flip = quad_flips(corner_positions, s)
        if flip.any():  # (0 1 3) (1 2 3)
            f = quads[flip]
            triangles[first[f], 2] = starts[f] + 3
            triangles[first[f] + 1, 0] = starts[f] + 1
    return triangles, faces


def quad_flips(corner_positions: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(Q,) bool: Blender's `is_quad_flip_v3_first_third_fast` of the quads whose corners start at
    `starts` (Q,): whether the triangles (v1 v2 v3) and (v1 v4 v3) face the same way, i.e. the
    diagonal v1-v3 lies outside the quad. float32, Blender's operations in Blender's order."""
    p = np.asarray(corner_positions, np.float32)
    v1, v2, v3, v4 = (p[starts + k] for k in range(4))
    d12, d13, d14 = v2 - v1, v3 - v1, v4 - v1
    a = cross_rows(d12, d13)
    b = cross_rows(d14, d13)
    dot = a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]
    dot += a[:, 2] * b[:, 2]
    return dot > np.float32(0.0)

