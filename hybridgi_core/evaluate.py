"""Reference gather (step 6 on the CPU): cache irradiance at surface points, leak-free.

Each point reads the 8 cells around it (trilinear), each weighted by whether the cell can see the
point (measured against Cycles as the largest single gain over plain trilinear interpolation:
Diffuse Indirect error 0.12 -> 0.085 on the Cornell box, 0.13-0.28 -> 0.075 on the atrium):
a soft back-face term, times either

- exact visibility: an occlusion ray from the point to each cell centre (`corner_visibility`,
  Embree; ~115k rays for a 160x90 G-buffer). Used for image pixels: the mask is uploaded to the
  GPU gather as a texture, or
- a Chebyshev test against the cell's depth moments in the direction of the point (DDGI). Cheap
  and approximate (coarse texels mix near hits and misses); used at probe-ray hits.

The GPU gather (`raster/gather.py`) reproduces this function exactly; tests compare the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import sh
from .bump import irradiance_kernel
from .cache import IrradianceCache
from .outside import beyond
from .sampling import octahedral_texel

#: Minimum weights, as in DDGI: keep every valid neighbour slightly in play so the result never
#: collapses to 0 / 0 where all tests are pessimistic.
MIN_CHEBYSHEV = 0.05
MIN_WEIGHT = 1e-4
BACKFACE_FLOOR = 0.2


@dataclass
class Gathered:
    """Irradiance (W/m^2) at points. direct/indirect : (n, 3) float32; ao : (n,) float32 in 0..1."""

    direct: np.ndarray
    indirect: np.ndarray
    ao: np.ndarray


def biased_points(cache: IrradianceCache, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Shading points moved `normal_bias` cells along the normal, as every gather reads them."""
    bias = np.float32(cache.settings.normal_bias * cache.grid.cell_size)
    return np.asarray(points, np.float32) + np.asarray(normals, np.float32) * bias


def corner_visibility(cache: IrradianceCache, tracer, points: np.ndarray, normals: np.ndarray, epsilon: float) -> np.ndarray:
    """(n, 8) bool: whether each of the 8 neighbouring cell centres is visible from the point.

    One occlusion ray per corner from the biased point (pushed `epsilon` further off the surface).
    """
    normals = np.asarray(normals, np.float32)
    biased = biased_points(cache, points, normals)
    p = biased + normals * np.float32(epsilon)
    flats, _ = cache.grid.corner_cells(biased)
    to_cell = np.take(cache.centers, flats, axis=0) - p[:, None, :]
    dist = np.linalg.norm(to_cell, axis=2)
    dirs = to_cell / np.maximum(dist, np.float32(1e-9))[..., None]
    origins = np.repeat(p, 8, axis=0)
    tfar = np.maximum(dist.ravel() - np.float32(epsilon), 0.0).astype(np.float32)
    blocked = tracer.occluded(origins, dirs.reshape(-1, 3).astype(np.float32), tfar)
    return ~np.asarray(blocked, bool).reshape(-1, 8)


def corner_weights(
    cache: IrradianceCache,
    points: np.ndarray,
    normals: np.ndarray,
    visibility: bool = True,
    corner_visible: np.ndarray | None = None,
):
    """Flat cells (n, 8) and normalized weights (n, 8) float32 of the visibility-weighted gather.

    corner_visible : (n, 8) bool from `corner_visibility`; when given it replaces the Chebyshev
    test. Rows whose weights are all zero (no valid cell near) stay zero: no cache light there.
    """
    s = cache.settings
    cell = np.float32(cache.grid.cell_size)
    normals = np.asarray(normals, np.float32)
    p = biased_points(cache, points, normals)
    flats, tri = cache.grid.corner_cells(p)
    w = tri * np.take(cache.valid, flats)
    if visibility:
        to_cell = np.take(cache.centers, flats, axis=0) - p[:, None, :]  # (n, 8, 3): take, ~5x faster than [flats]
        dist = np.linalg.norm(to_cell, axis=2)
        safe = np.maximum(dist, np.float32(1e-6))[..., None]
        dirs = np.where(dist[..., None] > 1e-6, to_cell / safe, normals[:, None, :])
        cos = np.einsum("nci,ni->nc", dirs, normals)
        w *= np.square((cos + 1.0) * 0.5) + np.float32(BACKFACE_FLOOR)
        if corner_visible is not None:
            w = _mask_or_keep(w, corner_visible)
        else:
            # The cell looks back towards the point: its depth moments in direction -dirs.
            texel = octahedral_texel(-dirs.reshape(-1, 3), s.depth_texels).reshape(flats.shape)
            m = cache.depth[flats, texel]  # (n, 8, 2)
            mean, mean2 = m[..., 0], m[..., 1]
            var = np.maximum(mean2 - mean * mean, np.float32(1e-4) * cell * cell)
            excess = np.maximum(dist - mean, 0.0)
            cheb = var / (var + excess * excess)
            cheb = np.where(dist <= mean, np.float32(1.0), cheb**3)
            w *= np.maximum(cheb, np.float32(MIN_CHEBYSHEV))
            # Coarse depth texels miss thin walls; a cell behind the point's own tangent plane
            # cannot see it past a planar surface, so it drops out (exact rays make this moot).
            w = _mask_or_keep(w, cos > 0.0)
        w = np.where(w > 0, np.maximum(w, np.float32(MIN_WEIGHT) * tri), 0.0)
    total = w.sum(axis=1, keepdims=True)
    w = np.divide(w, total, out=np.zeros_like(w), where=total > 0).astype(np.float32)
    return flats, w


def _mask_or_keep(w: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Zero the masked-out neighbours, except in rows where that would leave none: those keep
    their weights rather than go black (a point in a crevice)."""
    masked = w * mask
    return np.where(masked.sum(axis=1, keepdims=True) > 0, masked, w)


def gather(
    cache: IrradianceCache,
    points: np.ndarray,
    normals: np.ndarray,
    visibility: bool = True,
    corner_visible: np.ndarray | None = None,
    surfaces: np.ndarray | None = None,
) -> Gathered:
    """Irradiance from the cache at points with unit normals (n, 3) float32, clamped to >= 0.

    The SH of the 8 cells are blended first and convolved once (linear, so identical to blending
    irradiances, and 8x cheaper). AO is the cosine-weighted visibility: irradiance of the
    visibility SH divided by pi. surfaces : (n, 3) the smooth surface normals under normals a
    normal map bent, or None: the light is then read through the bent lobe
    (`bump.irradiance_kernel`: nothing from below the surface), AO keeps the cosine.
    """
    normals = np.asarray(normals, np.float32)
    flats, w = corner_weights(cache, points, normals, visibility, corner_visible)
    n = flats.shape[0]
    if n == 0:
        z = np.zeros((0, 3), np.float32)
        return Gathered(z, z.copy(), np.zeros(0, np.float32))
    sh_d = np.einsum("nc,nckl->nkl", w, cache.sh_direct[flats])
    sh_i = np.einsum("nc,nckl->nkl", w, cache.sh_indirect[flats])
    sh_a = np.einsum("nc,nck->nk", w, cache.ao_sh[flats])[..., None]
    if surfaces is None:
        direct = np.maximum(sh.irradiance(sh_d, normals), 0.0)
        indirect = np.maximum(sh.irradiance(sh_i, normals), 0.0)
    else:
        kernel = irradiance_kernel(surfaces, normals, 2 if sh_d.shape[1] == 9 else 1)
        direct = np.maximum(np.einsum("nk,nkc->nc", kernel, sh_d), 0.0)
        indirect = np.maximum(np.einsum("nk,nkc->nc", kernel, sh_i), 0.0)
    covered = w.sum(axis=1) > 0
    ao = np.where(covered, np.clip(sh.irradiance(sh_a, normals)[:, 0] / np.pi, 0.0, 1.0), 1.0)
    return Gathered(direct.astype(np.float32), indirect.astype(np.float32), ao.astype(np.float32))


#: How far (cells) a probe hit looks along its normal for the cell it reads: sqrt(3) / 2 puts
#: the centre of the containing cell on the front side of the hit's plane for any normal.
HIT_LOOKUP_BIAS = 0.87


class HitLookup:
    """The cache as probe-ray hits read it during one update: a frozen snapshot, so hits read the
    cache as it was before the update began, whatever the thread timing.

    Further bounces are low frequency and costly in bulk (one per probe ray), so a hit reads the
    single cell in front of it instead of the 8-neighbour visibility-weighted gather. A hit whose
    cell cannot be read (never sampled, or inside geometry) takes the best valid one of the 8
    cells around it, in front of its tangent plane (`_best_front_neighbour`). A hit more than
    half a cell beyond the grid reads a cell of its own, index N (`outside.py`), where the cache
    has an `outside` light.

    Irradiance is a polynomial in the normal (SH up to L2): the table holds it on the monomials
    1, y, z, x, xy, yz, z^2, xz, x^2 - y^2 with every SH and cosine constant folded in, one
    (K*3,) row per cell (`irradiance_poly`): a hit's gather reads one or two cache lines, where
    (K*3, N) structure-of-arrays rows cost a cache miss per term on a grid larger than the
    caches (`evaluate_rows`).
    """

    def __init__(self, cache: IrradianceCache, bounced: bool, coeffs: np.ndarray | None = None, table: bool = True):
        """bounced : the table holds direct + indirect bands (else direct only); coeffs : (N, K, 3)
        radiance SH to use instead of the cache's bands (the solver's iterates); table : False
        builds no irradiance table (`cells` only: the solver keeps its own table of the cells its
        hits read, and the whole grid's cost ~50 ms on the Cornell box)."""
        grid = cache.grid
        self.valid = cache.valid
        self.inside = cache.inside
        k = cache.settings.sh_coeffs
        self.terms = k
        self.table = None
        #: The cache's light beyond the grid (`outside.py`), or None (beyond reads the edge).
        self.outside = cache.outside
        if table:
            if coeffs is None:
                coeffs = cache.sh_direct + cache.sh_indirect if bounced else cache.sh_direct
            # (N, K*3) for `evaluate_rows`; row N: what a surface beyond the grid reads.
            self.table = irradiance_rows(coeffs, self.valid, self.outside)
        self.origin = np.asarray(grid.lo, np.float32)
        self.inv_cell = np.float32(1.0 / grid.cell_size)
        self.bias = np.float32(HIT_LOOKUP_BIAS * grid.cell_size)
        self.top = np.asarray(grid.dims, np.int32) - 1
        self.strides = (1, grid.dims[0], grid.dims[0] * grid.dims[1])
        self.grid = grid
        self._rows_of = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))

    def _per_row(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """origin and top repeated over n rows: numpy broadcasts a (3,) operand over (n, 3) rows
        ~4x slower than it combines two (n, 3) arrays. Grown on demand; a race only repeats work."""
        origin, top = self._rows_of
        if origin.shape[0] < n:
            origin, top = np.tile(self.origin, (n, 1)), np.tile(self.top, (n, 1))
            self._rows_of = (origin, top)
        return origin[:n], top[:n]

    def irradiance(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(3, n) float32 irradiance >= 0 (channel rows) at points (n, 3) with unit normals (n, 3);
        zero normals (missed rays) read a cell but get no special treatment: mask them yourself."""
        return self.evaluate(self.cells(points, normals), monomials(normals, self.terms))

    def cells(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(n,) intp cell each hit reads: the one in front of it, else its best valid neighbour;
        N (the grid's cell count) beyond the grid where the cache has an `outside` light.

        Depends only on the grid and on which cells are valid, so stored probe hits
        (`solver.StoredHits`) keep it across fixed-point iterations."""
        origin, top = self._per_row(points.shape[0])
        g = normals * self.bias
        g += points
        g -= origin
        g *= self.inv_cell
        # Truncation is floor wherever the clamp below keeps the value (negatives all clamp to 0).
        ijk = g.astype(np.int32)
        np.maximum(ijk, 0, out=ijk)
        np.minimum(ijk, top, out=ijk)
        flat = ijk[:, 0].astype(np.intp)
        flat += ijk[:, 1] * self.strides[1]
        flat += ijk[:, 2] * self.strides[2]
        valid = np.take(self.valid, flat)
        if self.outside is not None:
            out = np.flatnonzero(beyond(g, self.top + 1))
            if out.size:
                flat[out] = self.valid.shape[0]  # the outside cell
                valid[out] = True
        bad = np.flatnonzero(~valid)
        if bad.size:  # row gathers through np.take: ~5x faster than fancy indexing (numpy 1.26)
            g_bad = np.take(g, bad, axis=0)
            g_bad -= np.float32(0.5)
            flat[bad] = _best_front_neighbour(self.grid, self.valid, g_bad, np.take(points, bad, axis=0),
                                              np.take(normals, bad, axis=0), np.take(flat, bad))
        return flat

    def evaluate(self, flat: np.ndarray, mono: np.ndarray) -> np.ndarray:
        """(3, n) float32 irradiance >= 0 of cells flat (n,) at normals given as their
        `monomials` (terms, n)."""
        return evaluate_rows(self.table, flat, mono)


def evaluate_rows(rows: np.ndarray, index: np.ndarray, mono: np.ndarray) -> np.ndarray:
    """(3, n) float32 irradiance >= 0 of table `rows` (R, K*3) at entries index (n,), normals
    given as their monomials (K, n). One row gather per entry and one contraction over the terms
    (no transpose of the gathered rows). Against gathering the columns of a (K*3, R) table, each
    term a cache miss of its own: the atrium's pixel-ray shading (its 21.6k-cell grid, 64k hits
    an item) 4% faster on one thread, the gather 2.75 -> 1.85 ms; 110k cells: 5.8 -> 1.8 ms."""
    n, k = index.shape[0], mono.shape[0]
    e = np.empty((3, n), np.float32)  # C order: einsum's own choice of output is slower to write
    np.einsum("nkc,kn->cn", np.take(rows, index, axis=0).reshape(n, k, 3), mono, out=e)
    np.maximum(e, 0.0, out=e)
    return e


def irradiance_rows(coeffs: np.ndarray, valid: np.ndarray | None = None,
                    outside: np.ndarray | None = None) -> np.ndarray:
    """(n, K*3) float32 irradiance polynomial of radiance SH coeffs (n, K, 3) on the `monomials`,
    one contiguous row per cell (`irradiance_poly`), for `evaluate_rows`; with `outside` (K, 3)
    one more row, n, of that light: the outside cell (`outside.py`) the hits beyond the grid read."""
    if outside is not None:
        coeffs = np.concatenate([coeffs, np.asarray(outside, np.float32)[None]])
        valid = None if valid is None else np.append(valid, True)
    return irradiance_poly(coeffs, valid)


def irradiance_poly(coeffs: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(n, K*3) float32 irradiance polynomial of radiance SH coeffs (n, K, 3) on the `monomials`,
    every SH and cosine constant folded in; rows where valid (n,) is False are zero.

    Flat (n, K*3) rows take one multiply by a (K*3,) factor (per-axis broadcasts over (n, K, 3)
    cost 3x more)."""
    n, k = coeffs.shape[0], coeffs.shape[1]
    poly = np.array(coeffs, np.float32).reshape(n, k * 3)
    basis = np.array([sh.C0, sh.C1, sh.C1, sh.C1, sh.C2, sh.C2, 3.0 * sh.C3, sh.C2, sh.C4][:k], np.float32)
    poly *= np.repeat(sh.cosine_scale(1 if k == 4 else 2) * basis, 3)
    if k == 9:
        poly[:, 0:3] -= poly[:, 18:21] * np.float32(1.0 / 3.0)  # C3 (3 z^2 - 1): -1 joins the constant
    if valid is not None:
        poly[~valid] = 0.0
    return poly


def monomials(normals: np.ndarray, terms: int) -> np.ndarray:
    """(terms, n) float32 monomials 1, y, z, x (, xy, yz, z^2, xz, x^2 - y^2) of unit normals
    (n, 3): the irradiance polynomial's variables in `irradiance_poly` order."""
    x, y, z = np.ascontiguousarray(np.asarray(normals, np.float32).T)
    out = np.empty((terms, x.shape[0]), np.float32)
    out[0] = 1.0
    out[1], out[2], out[3] = y, z, x
    if terms == 9:
        np.multiply(x, y, out=out[4])
        np.multiply(y, z, out=out[5])
        np.multiply(z, z, out=out[6])
        np.multiply(x, z, out=out[7])
        np.multiply(x, x, out=out[8])
        out[8] -= y * y
    return out


def _best_front_neighbour(grid, valid, g, points, normals, fallback):
    """(k,) flat cells: of the 8 cells around each point (g : (k, 3) cell coordinates less 0.5),
    the valid one in front of the point's tangent plane with the largest trilinear weight;
    `fallback` where there is none. The same choice as scoring `grid.corner_cells`.

    A running best over the 8 corners on (k,) arrays: (k, 8) score tables and broadcasts over
    short trailing axes measured slower.
    """
    base = np.floor(g)
    f = (g - base).astype(np.float32)
    base = base.astype(np.int32)
    dims = grid.dims
    stride = (1, dims[0], dims[0] * dims[1])
    cell = np.float32(grid.cell_size)
    idx, wgt, front = [], [], []
    for a in range(3):
        i0 = np.clip(base[:, a], 0, dims[a] - 1)
        i1 = np.clip(base[:, a] + 1, 0, dims[a] - 1)
        # Offset of each candidate centre from the point along this axis, times the normal's axis.
        lo = np.float32(grid.lo[a]) + np.float32(0.5) * cell - points[:, a]
        idx.append((i0 * stride[a], i1 * stride[a]))
        wgt.append((1.0 - f[:, a], f[:, a]))
        front.append(((i0 * cell + lo) * normals[:, a], (i1 * cell + lo) * normals[:, a]))
    best = np.zeros(g.shape[0], np.float32)
    out = np.asarray(fallback, np.intp).copy()
    for ox in (0, 1):
        for oy in (0, 1):
            w_xy = wgt[0][ox] * wgt[1][oy]
            i_xy = idx[0][ox] + idx[1][oy]
            f_xy = front[0][ox] + front[1][oy]
            for oz in (0, 1):
                flat = i_xy + idx[2][oz]
                ok = (f_xy + front[2][oz]) > 0
                ok &= valid[flat]
                score = np.where(ok, w_xy * wgt[2][oz], np.float32(0.0))
                better = score > best
                np.copyto(out, flat, where=better)
                np.maximum(best, score, out=best)
    return out
