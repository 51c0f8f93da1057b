"""Point clouds as triangles: Cycles renders a PointCloud's points (Geometry Nodes' Mesh to
Points, Distribute Points, imported particle caches) as spheres of each point's radius; the rays
and the G-buffer here see meshes, so each point becomes an icosphere through its radius, its
normals radial (smooth).

A cloud of many points can exceed what is worth tracing: past `TRIANGLE_BUDGET` the spheres get
fewer faces (an icosahedron), then only every n-th point is kept, `thinned` by n, each widened by
sqrt(n) so that the points still cover about as much of what is behind them (the caller warns).
"""

from __future__ import annotations

import numpy as np

from .hair import TRIANGLE_BUDGET, ShapeMesh

#: Blender's radius of a point without a "radius" attribute (Cycles' default too).
DEFAULT_RADIUS = 0.01


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    t = (1.0 + 5.0 ** 0.5) / 2.0
    v = np.array([(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
                  (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)], np.float64)
    f = np.array([(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
                  (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
                  (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)], np.int32)
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def _subdivided(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One loop of midpoint subdivision (each triangle into four), projected onto the sphere."""
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = v[unique].mean(axis=1)
    v2 = np.concatenate([v, mid / np.linalg.norm(mid, axis=1, keepdims=True)])
    m = inverse.reshape(3, -1).T + len(v)  # (F, 3): the midpoints of edges 01, 12, 20
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
    f2 = np.concatenate([np.stack(s, axis=1) for s in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return v2, f2.astype(np.int32)


_ICO = _icosahedron()
#: Unit spheres, finest first: 80 triangles (42 vertices), 20 (12).
SPHERES = (_subdivided(*_ICO), _ICO)


def spheres(points: np.ndarray, radii: np.ndarray, budget: int = TRIANGLE_BUDGET) -> ShapeMesh:
    """Spheres of `radii` (n,) float32 around `points` (n, 3) float32; points with a radius that is
    not finite and above 0, or a position that is not finite, are left out (Cycles draws nothing)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    radii = np.asarray(radii, np.float32).reshape(-1)
    keep = np.flatnonzero(np.isfinite(points).all(axis=1) & np.isfinite(radii) & (radii > 0))
    unit_v, unit_f = SPHERES[0]
    thinned = 1
    if keep.size * unit_f.shape[0] > budget:
        unit_v, unit_f = SPHERES[-1]
        if keep.size * unit_f.shape[0] > budget:
            thinned = -(-keep.size * unit_f.shape[0] // budget)
            keep = keep[::thinned]
    n, nv = keep.size, unit_v.shape[0]
    r = radii[keep] * np.float32(np.sqrt(thinned))
    normals = np.broadcast_to(unit_v.astype(np.float32), (n, nv, 3))
    positions = points[keep][:, None, :] + normals * r[:, None, None]
    triangles = unit_f[None, :, :] + (np.arange(n, dtype=np.int32) * nv)[:, None, None]
    return ShapeMesh(positions=positions.reshape(-1, 3).astype(np.float32),
                   normals=np.ascontiguousarray(normals.reshape(-1, 3)),
                   triangles=triangles.reshape(-1, 3).astype(np.int32),
                   source=np.repeat(keep.astype(np.int32), unit_f.shape[0]), thinned=thinned)
