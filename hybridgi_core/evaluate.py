"""Reference gather (step 6 on the CPU): cache irradiance at surface points, leak-free.

Each point reads the 8 cells around it (trilinear), each weighted by whether the cell can see the
point (GI_FACTS.md measured this as the largest single gain over plain trilinear interpolation):
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
from .cache import IrradianceCache
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
    p = biased_points(cache, points, normals) + normals * np.float32(epsilon)
    flats, _ = cache.grid.corner_cells(biased_points(cache, points, normals))
    to_cell = cache.centers[flats] - p[:, None, :]
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
    w = tri * cache.valid[flats]
    if visibility:
        to_cell = cache.centers[flats] - p[:, None, :]  # (n, 8, 3)
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
) -> Gathered:
    """Irradiance from the cache at points with unit normals (n, 3) float32, clamped to >= 0.

    The SH of the 8 cells are blended first and convolved once (linear, so identical to blending
    irradiances, and 8x cheaper). AO is the cosine-weighted visibility: irradiance of the
    visibility SH divided by pi.
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
    direct = np.maximum(sh.irradiance(sh_d, normals), 0.0)
    indirect = np.maximum(sh.irradiance(sh_i, normals), 0.0)
    covered = w.sum(axis=1) > 0
    ao = np.where(covered, np.clip(sh.irradiance(sh_a, normals)[:, 0] / np.pi, 0.0, 1.0), 1.0)
    return Gathered(direct.astype(np.float32), indirect.astype(np.float32), ao.astype(np.float32))


#: How far (cells) a probe hit looks along its normal for the cell it reads: sqrt(3) / 2 puts
#: the centre of the containing cell on the front side of the hit's plane for any normal.
HIT_LOOKUP_BIAS = 0.87


def irradiance_sh(cache: IrradianceCache, bounced: bool) -> np.ndarray:
    """(N, K, 3) float32 per-cell *irradiance* SH (cosine-convolved): direct band, plus the bounced
    band when `bounced`. Invalid cells are zero. Evaluating it is one dot product per point."""
    coeffs = cache.sh_direct + cache.sh_indirect if bounced else cache.sh_direct.copy()
    coeffs *= sh.cosine_scale(cache.settings.sh_order)[None, :, None]
    coeffs[~cache.valid] = 0.0
    return coeffs


def nearest_irradiance(cache: IrradianceCache, table: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(n, 3) float32 irradiance >= 0 at probe-ray hits from the single cell in front of each hit.

    Further bounces are low frequency and costly in bulk (one per probe ray), so they read one
    cell instead of the 8-neighbour visibility-weighted gather. table : `irradiance_sh(...)`.
    """
    normals = np.asarray(normals, np.float32)
    points = np.asarray(points, np.float32)
    p = points + normals * np.float32(HIT_LOOKUP_BIAS * cache.grid.cell_size)
    ijk = np.floor((p - cache.grid.lo) / np.float32(cache.grid.cell_size)).astype(np.int64)
    ijk = np.clip(ijk, 0, np.asarray(cache.grid.dims) - 1)
    flat = cache.grid.flatten(ijk)
    # Near an object's edge the cell in front of a hit can be one disabled inside the object:
    # those hits take the best valid neighbour in front of their tangent plane instead.
    bad = np.flatnonzero(~cache.valid[flat])
    if bad.size:
        corners, tri = cache.grid.corner_cells(p[bad])
        in_front = np.einsum("nci,ni->nc", cache.centers[corners] - points[bad, None, :], normals[bad]) > 0
        score = tri * cache.valid[corners] * in_front
        best = score.argmax(axis=1)
        ok = score[np.arange(bad.size), best] > 0
        flat[bad[ok]] = corners[ok, best[ok]]
    coeffs = np.take(table, flat, axis=0)  # (n, K, 3); invalid cells hold zeros
    y = sh.basis(normals, cache.settings.sh_order)
    return np.maximum(np.einsum("nk,nkc->nc", y, coeffs), 0.0).astype(np.float32)
