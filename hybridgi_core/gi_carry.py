"""A still view's pixel-ray GI carried over a lamp edit until the pixel rays are traced again.

Why: the viewport's pixel rays (`pixel_gather`) give a still view its converged GI, but a pass
costs ~0.6 s on 2 busy cores; after a lamp edit the view showed the re-lit cache's gather
meanwhile, whose coarse cells miss the near field the rays saw and whose blotches show
(Cornell 640x360 vs Cycles: the gather's image 0.038, the pixel rays' 0.021). The re-lit cache
is solved much sooner (~0.25 s). Where the rays' light differs from the cache's (contacts,
corners: what its cells are too coarse for) a lamp edit mostly scales that difference, by as
much as it scales the cache's light around it: so the old image is scaled, per colour channel,
by the ratio of the local means of the new and old cache light around each pixel,

    new = ratio * old + extra,   ratio = clip((mean_new + floor) / (mean_old + floor), 0, RATIO_MAX),

`extra` what a bounded ratio leaves of the new mean (a lamp moved next to a surface the old light
barely reached). Local means over surfaces facing the same way, not each pixel's cache: the
re-lit cache's own noise would print itself on the image (per-pixel ratios: 0.036). The floor
(FLOOR x the image's mean cache light) keeps dark regions' ratios tame. A change of power or
colour carries over exactly (a lamp edit of Cornell's: 0.024 at 0.5 s, the gather's 0.038);
a move approximately (0.026). The AO stays (a lamp edit moves no geometry); the next pixel
pass replaces the carried image.
"""

from __future__ import annotations

import numpy as np

#: Largest factor the old image is scaled by (a lamp moved next to a surface the old light barely
#: reached: `extra` brings the rest of the new cache light there, without the old image's detail).
RATIO_MAX = 8.0
#: The ratio's floor, as a share of the image's mean cache light.
FLOOR = 0.02
#: The local means of `smoothed_change`: sums over blocks of BLOCK x BLOCK GI pixels, a box of
#: (2 RADIUS + 1)^2 blocks over them (Cornell 640x360, a lamp moved: boxes of 3x3 and 5x5 blocks
#: of 4 read the same, 0.0265 / 0.0264 vs Cycles; per-pixel ratios 0.0359: the cache's blotches).
BLOCK = 4
RADIUS = 2


def nearest_lo_point(full_points: np.ndarray, full_pix: np.ndarray, full_width: int, lo_points: np.ndarray,
                     lo_pix: np.ndarray, lo_shape: tuple[int, int]) -> np.ndarray:
    """(m,) index into the GI points of each full-res pixel's GI point: among the GI pixel of
    its block and that pixel's four neighbours, the one whose surface point is nearest (a
    silhouette's block may hold the other surface); -1 where none of them has geometry."""
    h, w = lo_shape
    m = full_points.shape[0]
    factor = max(1, int(round(full_width / max(w, 1))))
    index = np.full(h * w, -1, np.int64)
    index[lo_pix] = np.arange(lo_pix.shape[0])
    bx = np.minimum(full_pix % full_width // factor, w - 1)
    by = np.minimum(full_pix // full_width // factor, h - 1)
    best = np.full(m, np.inf, np.float32)
    choice = np.full(m, -1, np.int64)
    for dx, dy in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
        x, y = bx + dx, by + dy
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        i = np.where(inside, np.take(index, np.clip(y, 0, h - 1) * w + np.clip(x, 0, w - 1)), -1)
        gap = np.take(lo_points, np.maximum(i, 0), axis=0) - full_points
        d = np.where(i >= 0, np.einsum("ij,ij->i", gap, gap), np.inf)
        closer = d < best
        best = np.where(closer, d, best)
        choice = np.where(closer, i, choice)
    return choice


def smoothed_change(cache_old: np.ndarray, cache_new: np.ndarray, lo_pix: np.ndarray, lo_normals: np.ndarray,
                    lo_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """((n, 6) ratio, (n, 6) extra) at the GI points: the ratio of the local means of the cache's
    new and old light (direct rgb, indirect rgb) among GI pixels facing the same way (six normal
    classes: a wall's change is not its floor's), bounded by RATIO_MAX, and what the bounded
    ratio leaves of the new mean. Why local means: the re-lit cache's own noise (its cells'
    blotches, not those of the old cache) would otherwise print itself on the image. The means:
    sums over BLOCK x BLOCK pixel blocks, a box of (2 RADIUS + 1)^2 blocks over them, read
    bilinearly at each point (a few ms; a per-pixel box over the GI image took ~0.2 s)."""
    h, w = lo_shape
    n = lo_pix.shape[0]
    ratio = np.ones((n, 6), np.float32)
    extra = np.zeros((n, 6), np.float32)
    if not n:
        return ratio, extra
    c_old, c_new = cache_old[:, 0:6], cache_new[:, 0:6]
    floor = np.float32(FLOOR * max(float(c_old.mean()), 1e-12))
    axis = np.argmax(np.abs(lo_normals), axis=1)
    face = 2 * axis + (np.take_along_axis(lo_normals, axis[:, None], axis=1)[:, 0] < 0)
    x, y = lo_pix % w, lo_pix // w
    bh, bw = -(-h // BLOCK), -(-w // BLOCK)
    cell = (face * bh + y // BLOCK) * bw + x // BLOCK
    values = np.concatenate([c_old, c_new, np.ones((n, 1), np.float32)], axis=1)
    sums = np.stack([np.bincount(cell, weights=values[:, k], minlength=6 * bh * bw) for k in range(13)], axis=1)
    grid = _box(_box(sums.reshape(6, bh, bw, 13), 1), 2).astype(np.float32).reshape(-1, 13)
    # Bilinear over the block centres, of the sums (so the counts weigh as the values do).
    fx, fy = (x + 0.5) / BLOCK - 0.5, (y + 0.5) / BLOCK - 0.5
    x0, y0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
    tx, ty = (fx - x0).astype(np.float32), (fy - y0).astype(np.float32)
    acc = np.zeros((n, 13), np.float32)
    for dx, dy, wt in ((0, 0, (1 - tx) * (1 - ty)), (1, 0, tx * (1 - ty)), (0, 1, (1 - tx) * ty), (1, 1, tx * ty)):
        flat = (face * bh + np.clip(y0 + dy, 0, bh - 1)) * bw + np.clip(x0 + dx, 0, bw - 1)
        acc += wt[:, None] * np.take(grid, flat, axis=0)
    count = np.maximum(acc[:, 12:13], np.float32(1e-9))
    old, new = acc[:, 0:6] / count, acc[:, 6:12] / count
    r = np.clip((new + floor) / (old + floor), 0.0, RATIO_MAX)
    return r.astype(np.float32), np.maximum(new - r * old, 0.0).astype(np.float32)


def _box(grid: np.ndarray, axis: int) -> np.ndarray:
    """Sums over 2 RADIUS + 1 entries along `axis` (the part inside the grid at its edges)."""
    size = grid.shape[axis]
    c = np.cumsum(grid, axis=axis)
    c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
    idx = np.arange(size)
    return np.take(c, np.minimum(idx + RADIUS + 1, size), axis=axis) - np.take(c, np.maximum(idx - RADIUS, 0), axis=axis)


def carried(indirect: np.ndarray, direct: np.ndarray, ratio: np.ndarray, extra: np.ndarray,
            nearest: np.ndarray, full_pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(indirect, direct) textures (H, W, 4) carried over an edit of the light (module docstring).

    indirect, direct : the rays' textures before it (as `pixel_gather.textures` writes them);
    ratio, extra : (n, 6) at the GI points (`smoothed_change`); nearest : (m,) each full-res
    pixel's GI point (`nearest_lo_point`), full_pix : (m,) their flat pixels."""
    old_d = direct.reshape(-1, 4)
    old_i = indirect.reshape(-1, 4)
    new_d, new_i = old_d.copy(), old_i.copy()
    keep = nearest >= 0
    q, i = full_pix[keep], nearest[keep]
    for lo, hi, old, new in ((0, 3, old_d, new_d), (3, 6, old_i, new_i)):
        new[q, 0:3] = ratio[i, lo:hi] * old[q, 0:3] + extra[i, lo:hi]
    return new_i.reshape(indirect.shape), new_d.reshape(direct.shape)
