"""Unshadowed irradiance of a polygonal lamp, in closed form (Lambert 1760).

Why: an area lamp's direct light is estimated with a few shadow rays per pixel. Even where
nothing shadows the lamp, each sample's cosine differs, so the estimate is noisy everywhere the
lamp's solid angle is large (a Cornell box's walls next to its ceiling lamp). Heitz et al.
("Combining Analytic Direct Illumination and Stochastic Shadows", I3D 2018) split the two: the
unshadowed irradiance U is exact, and the rays estimate only the visibility ratio
V = sum(f_i v_i) / sum(f_i) of the same samples f_i. U x V is noise-free where nothing
shadows (V = 1 exactly) and noisy only in penumbrae; it is consistent (a ratio estimator: its
bias vanishes as the samples grow and is zero wherever the visibility is constant over the lamp).

Lambert's formula: the cosine-weighted solid angle of a polygon with vertices v_1..v_k (relative
to the receiver, the polygon clipped to the receiver's upper hemisphere) is

    integral cos dw = 1/2 |sum_i angle(v_i, v_i+1) n . unit(v_i x v_i+1)|

Round lamps (disc, ellipse) are regular polygons of ROUND_SIDES sides whose area equals the
ellipse's (the cosine integral then differs by < 0.1% at any distance).

numpy only, float64: the terms are small differences of angles.
"""

from __future__ import annotations

import numpy as np

#: Sides of the polygon standing in for a disc or ellipse lamp.
ROUND_SIDES = 16
#: Share of receivers seeing the whole polygon above which `cosine_solid_angle` sums every row
#: unclipped (cheaper than gathering those rows) before it redoes the rest.
WHOLE_ROWS_SHARE = 0.6


def lamp_polygon(centre, half_u, half_v, round_shape: bool) -> np.ndarray:
    """(k, 3) float64 vertices of a lamp (centre, half extents along its two axes), in order
    around its boundary. Round lamps: ROUND_SIDES vertices on an ellipse scaled so that the
    polygon's area is the ellipse's."""
    c, hu, hv = (np.asarray(a, np.float64) for a in (centre, half_u, half_v))
    if not round_shape:
        return np.stack([c - hu - hv, c + hu - hv, c + hu + hv, c - hu + hv])
    k = ROUND_SIDES
    scale = np.sqrt(np.pi / (0.5 * k * np.sin(2.0 * np.pi / k)))
    t = 2.0 * np.pi * np.arange(k) / k
    return c + scale * (np.cos(t)[:, None] * hu + np.sin(t)[:, None] * hv)


def cosine_solid_angle(polygon: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(n,) float64: the integral of max(0, n . w) over the directions w in which each receiver
    (points (n, 3), unit normals (n, 3)) sees the convex polygon (k, 3); 0 where it lies wholly
    below the receiver's horizon. Irradiance = radiance x this."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    if p.shape[0] == 0:
        return np.zeros(0)
    # Component planes (n, k): whole-array arithmetic, no einsum or cross-product loops.
    v = [polygon[None, :, c] - p[:, c, None] for c in range(3)]  # receiver -> vertex
    return form_factor(v, [nrm[:, c, None] for c in range(3)])


def form_factor(v: list[np.ndarray], nc: list[np.ndarray] | None = None) -> np.ndarray:
    """(n,) float64: the integral of max(0, n . w) over the directions w of a convex polygon,
    per row, given as three (n, k) planes of its vertices relative to the receiver; nc: the
    normal's three components, (n, 1) each. 0 where the polygon lies wholly below the horizon."""
    h = v[0] * nc[0] + v[1] * nc[1] + v[2] * nc[2]  # heights above the tangent plane
    return _by_rows(v, h, lambda planes, rows, valid: _lambert(planes, [c[rows] for c in nc], valid), ())


def vector_form_factor(v: list[np.ndarray]) -> np.ndarray:
    """(n, 3) float64: the vector form factor of a convex polygon (three (n, k) vertex planes)
    clipped to the horizon z >= 0 (`ltc`'s cosine space): its z is the polygon's integral of
    max(0, w_z) (`form_factor` of normal +z), its direction the mean direction (by solid angle)
    of the polygon's visible part (the way the light arrives, for the Fresnel of the glossy lobes)."""
    return _by_rows(v, v[2], lambda planes, rows, valid: _lambert_vector(planes, valid), (3,))


def _by_rows(v: list[np.ndarray], h: np.ndarray, lambert, tail: tuple) -> np.ndarray:
    """`lambert(planes, rows, valid)` per row of the polygons' planes v above the heights h (n, k):
    rows wholly above their horizon unclipped, rows partly above clipped, the rest 0."""
    n = v[0].shape[0]
    out = np.zeros((n, *tail))
    if n == 0:
        return out
    above = h > 0
    # Vertex columns, not reductions over rows of k (numpy's are ~5x slower for small k).
    whole, some = above[:, 0].copy(), above[:, 0].copy()
    for j in range(1, above.shape[1]):
        whole &= above[:, j]
        some |= above[:, j]
    share = np.count_nonzero(whole) / n
    every = slice(None)
    if share == 1.0:
        return lambert(v, every, None)
    if share >= WHOLE_ROWS_SHARE:
        # Most rows see the whole polygon: the unclipped sum over every row costs less than
        # gathering those rows; the others are overwritten below (0 or clipped).
        out = lambert(v, every, None)
        out[~whole] = 0.0
    elif share > 0.0:
        out[whole] = lambert([c[whole] for c in v], whole, None)
    part = np.flatnonzero(some & ~whole)
    if part.size:
        clipped, valid = _clip_to_horizon([c[part] for c in v], h[part])
        out[part] = lambert(clipped, part, valid)
    return out


def _clip_to_horizon(v: list[np.ndarray], h: np.ndarray):
    """Sutherland-Hodgman against the plane h = 0 (keep h >= 0): three (m, 2k) vertex component
    planes and a (m, 2k) mask of the vertices that exist, in boundary order (a convex polygon
    gains at most one vertex per edge)."""
    m, k = h.shape
    nxt = np.roll(np.arange(k), -1)
    hb = h[:, nxt]
    keep = h >= 0
    crosses = keep != (hb >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crosses, h / (h - hb), 0.0)
    out = []
    for c in v:
        both = np.empty((m, k, 2))
        both[:, :, 0] = c
        both[:, :, 1] = c + t * (c[:, nxt] - c)
        out.append(both.reshape(m, 2 * k))
    return out, np.stack([keep, crosses], axis=2).reshape(m, 2 * k)


def clip_below(v: list[np.ndarray], h: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """(planes, count): convex polygons (three (m, k) vertex component planes) clipped to the
    side h >= 0 of a plane through the receiver (heights h (m, k) of their vertices), as three
    (m, k + 1) planes whose first `count` (m,) vertices are the clipped polygon's and whose other
    slots repeat its last vertex (edges of length 0 add nothing to Lambert's sums), so another
    plane can clip them again (`ltc.polygon_integral`: the surface's horizon, then the cosine's).
    A row with no vertex above the plane has count 0. k + 1 slots, not the clip's 2k: a convex
    polygon cut by one plane gains one vertex at most (its vertices above the plane are one run),
    and the slots past it would be zero-length edges that every later sum still computes (a
    lamp's four vertices over bunny_npm's 38k cut receivers: 8 -> 5 columns, the glossy lamp
    light 159 -> 147 ms, the same values). A sliver within rounding of the plane that reads more
    runs keeps its first k + 1 vertices (it spans no solid angle)."""
    clipped, valid = _clip_to_horizon(v, h)
    order = np.argsort(~valid, axis=1, kind="stable")  # valid vertices first, order kept
    count = np.minimum(valid.sum(axis=1), h.shape[1] + 1)
    j = np.arange(h.shape[1] + 1)[None, :]
    slot = np.take_along_axis(order, np.where(j < count[:, None], j, np.maximum(count - 1, 0)[:, None]), axis=1)
    return [np.take_along_axis(c, slot, axis=1) for c in clipped], count


def _lambert(v: list[np.ndarray], nc: list[np.ndarray], valid: np.ndarray | None) -> np.ndarray:
    """Lambert's sum over each row's vertices (component planes (m, k); valid (m, k) or None for
    all), taken in order and closed cyclically."""
    cross, scale = _edges(v, valid)
    term = scale * (cross[0] * nc[0] + cross[1] * nc[1] + cross[2] * nc[2])
    total = term[:, 0].copy()  # summed column by column, in numpy's order for k < 8
    for j in range(1, term.shape[1]):
        total += term[:, j]
    return 0.5 * np.abs(total)


def _lambert_vector(v: list[np.ndarray], valid: np.ndarray | None) -> np.ndarray:
    """(m, 3) Lambert's vector sum over each row's vertices (as `_lambert`, before the normal),
    oriented to +z (a polygon's winding does not matter)."""
    cross, scale = _edges(v, valid)
    out = np.stack([0.5 * (c * scale).sum(axis=1) for c in cross], axis=1)
    out[out[:, 2] < 0] *= -1.0
    return out


def _edges(v: list[np.ndarray], valid: np.ndarray | None) -> tuple[list[np.ndarray], np.ndarray]:
    """(cross, scale): each edge's unit vertices' cross product (three (m, k) planes) and its
    angle over that cross product's length ((m, k), 0 for the slots `valid` leaves empty), the
    terms of Lambert's sums. Each row's valid vertices are taken first, in their order, and
    closed cyclically over them (`_clip_to_horizon`'s rows); valid None: all of them."""
    m, k = v[0].shape
    if valid is None:
        take, live = _next_vertex, None
    else:
        order = np.argsort(~valid, axis=1, kind="stable")  # valid vertices first, order kept
        v = [np.take_along_axis(c, order, axis=1) for c in v]
        count = valid.sum(axis=1)
        j = np.arange(k)[None, :]
        nxt = np.where(j + 1 < count[:, None], j + 1, 0)
        take = lambda c: np.take_along_axis(c, nxt, axis=1)  # noqa: E731
        live = j < count[:, None]
    inv = 1.0 / np.maximum(np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), 1e-300)
    a = [c * inv for c in v]
    b = [take(c) for c in a]
    cross = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    sin = np.sqrt(cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2])
    scale = np.arctan2(sin, a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) / np.maximum(sin, 1e-300)
    if live is not None:
        scale = np.where(live, scale, 0.0)
    return cross, scale


def _next_vertex(c: np.ndarray) -> np.ndarray:
    """(m, k) the next vertex's component of each vertex (cyclic): slices, not a column gather."""
    out = np.empty_like(c)
    out[:, :-1] = c[:, 1:]
    out[:, -1] = c[:, 0]
    return out
