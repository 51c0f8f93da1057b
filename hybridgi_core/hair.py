"""Curves (hair, fur, grass) as triangles: Cycles renders a Curves object's strands as round tubes
of each point's radius (its default 3D curve shape); the rays and the G-buffer here see meshes,
so each strand becomes a tube of `SIDES` sides through its points (straight between them, where
Cycles follows a Catmull-Rom spline), its normals radial (smooth).

A scene of many strands can exceed what is worth tracing: past `TRIANGLE_BUDGET` the tubes get
fewer sides (3), then only every n-th strand is kept, `thinned` by n, each widened by sqrt(n) so
that the strands still cover about as much of what is behind them (the caller warns).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Sides of a strand's tube, and the fewest it drops to before strands are thinned.
SIDES, MIN_SIDES = 6, 3
#: Triangles all the strands of one Curves object may become.
TRIANGLE_BUDGET = 2_000_000


@dataclass
class ShapeMesh:
    """Triangles made of a shape's elements (strands as tubes here, points as spheres in
    `points.py`). positions, normals : (V, 3) float32 object space; triangles : (T, 3) int32;
    source : (T,) int32 the element (strand, point) each triangle belongs to; thinned : every
    thinned-th element was kept (1: all)."""

    positions: np.ndarray
    normals: np.ndarray
    triangles: np.ndarray
    source: np.ndarray
    thinned: int = 1


def tubes(points: np.ndarray, offsets: np.ndarray, radii: np.ndarray, sides: int = SIDES,
          budget: int = TRIANGLE_BUDGET) -> ShapeMesh:
    """Tubes around strands.

    points : (P, 3) float32 control points of every strand, strand c's from offsets[c] to
        offsets[c + 1] (Blender's `curve_offset_data`); offsets : (C + 1,) int; radii : (P,) float32
    Strands with fewer than two points, and non-finite points, give nothing.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    offsets = np.asarray(offsets, np.int64).reshape(-1)
    radii = np.abs(np.nan_to_num(np.asarray(radii, np.float64).reshape(-1), nan=0.0))
    counts = np.diff(offsets)
    segments = int(np.maximum(counts - 1, 0).sum())
    thinned = 1
    if 2 * sides * segments > budget:
        sides = MIN_SIDES
        if 2 * sides * segments > budget:
            thinned = int(np.ceil(2 * sides * segments / budget))
    keep = np.flatnonzero(counts >= 2)[::thinned]
    widen = np.sqrt(thinned)
    if keep.size == 0:
        return ShapeMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32),
                     np.zeros(0, np.int32), thinned)
    # Point indices of the kept strands, and which strand / position along it each one is.
    n = counts[keep]
    strand = np.repeat(np.arange(keep.size), n)
    first = np.repeat(np.cumsum(n) - n, n)
    along = np.arange(n.sum()) - first
    idx = np.repeat(offsets[keep], n) + along
    p = points[idx]
    r = radii[idx] * widen
    # Tangent at each point: the chord between its neighbours on the strand (one-sided at the ends).
    last = along == np.repeat(n - 1, n)
    prev = np.where(along == 0, np.arange(p.shape[0]), np.arange(p.shape[0]) - 1)
    nxt = np.where(last, np.arange(p.shape[0]), np.arange(p.shape[0]) + 1)
    t = p[nxt] - p[prev]
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-30)
    # One helper axis per strand (its mean direction's least aligned world axis): the rings of a
    # strand share a frame orientation, so its tube does not twist between points.
    mean_dir = np.zeros((keep.size, 3))
    np.add.at(mean_dir, strand, t)
    helper = np.eye(3)[np.argmin(np.abs(mean_dir), axis=1)][strand]
    u = np.cross(t, helper)
    small = np.linalg.norm(u, axis=1) < 1e-6
    u[small] = np.cross(t[small], np.roll(helper[small], 1, axis=1))
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-30)
    v = np.cross(t, u)
    angle = 2.0 * np.pi * np.arange(sides) / sides
    radial = np.cos(angle)[None, :, None] * u[:, None, :] + np.sin(angle)[None, :, None] * v[:, None, :]
    positions = p[:, None, :] + r[:, None, None] * radial  # (Pk, S, 3)
    # Two triangles per side between ring i and ring i + 1 of the same strand.
    starts = np.flatnonzero(~last)
    s = np.arange(sides)
    a = starts[:, None] * sides + s[None, :]
    b = starts[:, None] * sides + (s[None, :] + 1) % sides
    c, d = a + sides, b + sides
    tris = np.stack([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], axis=2).reshape(-1, 3)
    finite = np.isfinite(positions).all(axis=2).reshape(-1)
    ok = finite[tris].all(axis=1)
    curve = np.repeat(keep[strand[starts]], 2 * sides)
    return ShapeMesh(positions.reshape(-1, 3).astype(np.float32), radial.reshape(-1, 3).astype(np.float32),
                 tris[ok].astype(np.int32), curve[ok].astype(np.int32), thinned)
