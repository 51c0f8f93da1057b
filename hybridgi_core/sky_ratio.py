"""The sky's light at pixels as its exact unshadowed irradiance less the part the pixel's own rays
found blocked, where the sky is mostly open.

Why: a pixel ray that escapes brings the sky's radiance in its direction (`World.radiance`: the
environment map, its sun split off as a lamp). With cosine-distributed rays the estimate of the
sky's irradiance carries the map's variation over the hemisphere as noise, which the cache's L2
SH control variate removes only in part (an HDRI's bright horizon, clouds, the sky's gradient):
on an HDRI-lit yard and room (320x240 vs Cycles 1024 spp) Diffuse Direct was the largest error,
0.015, and fell only with many more rays (48 -> 384: 0.0149 -> 0.0080). Here the sky's
irradiance is U(n) - pi/N sum_i L(w_i) (1 - v_i): its unshadowed integral U(n) = integral L(w)
max(0, n . w) dw, exact (`SkyIrradiance`, a table over normals from the same map the rays read),
less the Monte Carlo estimate of what the rays found blocked. Unbiased, and exact where no ray
is blocked, which is where the sky's variation was most of the noise. Where most of the sky is
blocked the blocked part carries that variation instead, so the estimate is blended with the
control-variate one by how open the cache finds the sky (`open_share`; a weight the rays do not
set, so the blend stays unbiased). A ratio estimator (U x the unblocked share of the rays' sky)
was tried first: under a roof it read 17% high with 16 rays (its denominator, the rays' own sky,
is correlated with what they find open).

Only for skies that vary with direction (a map): under a uniform sky the plain estimate is exact
in the open already.

numpy only (no bpy).
"""

from __future__ import annotations

import numpy as np

from .environment import LUMA, equirect_directions

#: `open_share`: the cache's direct light over the unshadowed sky's at which the open-sky estimate
#: takes over entirely, and below which it has no weight.
#: (HDRI room / yard, 320x240, Combined vs Cycles 1024 spp, before: 0.0162 / 0.0180; 0.9 and 0.5:
#: 0.0183 / 0.0109; 0.98 and 0.8: 0.0159 / 0.0117; these: 0.0158 / 0.0112.)
OPEN_FULL = 0.95
OPEN_NONE = 0.7
#: Rec. 709 luminance weights, as the float32 arrays they weigh.
_LUMA = LUMA.astype(np.float32)
#: Normals of the irradiance table: rows (elevation) x twice as many columns (azimuth). The
#: irradiance is the map convolved with a clamped cosine: smooth, bilinear in between is ample.
TABLE_ROWS = 32


class SkyIrradiance:
    """U(n), the unshadowed irradiance a surface of normal n receives from a `SkyMap`, tabulated
    once per map over normals in the map's texture space: TABLE_ROWS latitudes from pole to pole
    (both included: a ground's normal is a pole) x 2 TABLE_ROWS longitudes, read bilinearly."""

    def __init__(self, sky_map):
        self.to_texture = sky_map.to_texture
        pixels = np.asarray(sky_map.pixels, np.float64)
        h, w = pixels.shape[:2]
        dirs, solid = equirect_directions(h, w)  # texel directions (texture space), per-row solid angle
        weighted = (pixels * solid[:, None, None]).reshape(-1, 3)
        d = dirs.reshape(-1, 3)
        lat = np.linspace(-0.5 * np.pi, 0.5 * np.pi, TABLE_ROWS)
        lon = np.pi - 2.0 * np.pi * np.arange(2 * TABLE_ROWS) / (2 * TABLE_ROWS)  # u = column / width
        n = np.stack(np.broadcast_arrays(np.cos(lat)[:, None] * np.cos(lon)[None, :],
                                         np.cos(lat)[:, None] * np.sin(lon)[None, :], np.sin(lat)[:, None]),
                     axis=-1).reshape(-1, 3)
        table = np.zeros((n.shape[0], 3))
        for start in range(0, n.shape[0], 256):  # (256, texels) cosines at a time
            cos = np.maximum(n[start:start + 256] @ d.T, 0.0)
            table[start:start + 256] = cos @ weighted
        self.table = table.reshape(TABLE_ROWS, 2 * TABLE_ROWS, 3).astype(np.float32)

    def irradiance(self, normals: np.ndarray) -> np.ndarray:
        """(n, 3) float32 U at unit world normals (n, 3)."""
        d = np.asarray(normals, np.float32).reshape(-1, 3)
        if self.to_texture is not None:
            d = d @ self.to_texture.T
        rows, cols = self.table.shape[:2]
        x, y, z = d[:, 0], d[:, 1], d[:, 2]
        norm = np.maximum(np.sqrt(x * x + y * y + z * z), np.float32(1e-30))
        u = (np.float32(np.pi) - np.arctan2(y, x)) * np.float32(0.5 / np.pi)
        lat = np.arcsin(np.clip(z / norm, -1.0, 1.0))
        fx = u * np.float32(cols)
        fy = (lat * np.float32(1.0 / np.pi) + np.float32(0.5)) * np.float32(rows - 1)
        x0 = np.floor(fx)
        y0 = np.minimum(np.floor(fy), np.float32(rows - 2))
        tx, ty = (fx - x0)[:, None], (fy - y0)[:, None]
        c0 = x0.astype(np.int64) % cols
        c1 = (c0 + 1) % cols
        r0 = y0.astype(np.int64)
        t = self.table
        top = t[r0, c0] * (1 - tx) + t[r0, c1] * tx
        bottom = t[r0 + 1, c0] * (1 - tx) + t[r0 + 1, c1] * tx
        return (top * (1 - ty) + bottom * ty).astype(np.float32)


def sky_irradiance(world) -> SkyIrradiance | None:
    """The world's `SkyIrradiance` (made once and kept on it), or None without a sky map."""
    sky_map = getattr(world, "sky_map", None)
    if sky_map is None:
        return None
    table = getattr(sky_map, "_irradiance", None)
    if table is None:
        table = SkyIrradiance(sky_map)
        sky_map._irradiance = table
    return table


def open_sky_estimate(unshadowed: np.ndarray, sky: np.ndarray, escaped: np.ndarray, rays: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """((m, 3) U - pi/N sum_i L(w_i) (1 - v_i), (m, rays) float32 each ray's luminance term of
    the sum, in radiance: -L(w_i) (1 - v_i)) for m pixels of N = `rays` cosine rays each: the
    sky's irradiance as its exact unshadowed integral less the part the rays found blocked.
    Unbiased, and exact where no ray was blocked.

    unshadowed : (m, 3) U at the pixels' normals; sky : (m * rays, 3) the sky's radiance in every
    ray's direction, blocked or not; escaped : (m * rays,) bool the rays that reached it."""
    m = unshadowed.shape[0]
    blocked = np.where(np.asarray(escaped).reshape(-1, 1), np.float32(0.0), np.asarray(sky, np.float32))
    blocked = blocked.reshape(m, rays, 3)
    estimate = unshadowed - blocked.mean(axis=1) * np.float32(np.pi)
    return estimate.astype(np.float32), -(blocked @ _LUMA)


def open_share(cache_light: np.ndarray, unshadowed: np.ndarray) -> np.ndarray:
    """(m,) float32 the weight of `open_sky_estimate` against the cache's control-variate estimate
    at m pixels: 1 where the cache's direct light (m, 3) is at least OPEN_FULL of the unshadowed
    sky's (m, 3), 0 below OPEN_NONE, linear between. It depends on the cache, not on the pixel's
    own rays, so the blend of two unbiased estimates stays unbiased: the open estimate is exact in
    the open and noisy where most of the sky is blocked (its blocked part carries the sky's whole
    variation there), where the cache's estimate is the quieter."""
    share = (np.asarray(cache_light, np.float32) @ _LUMA) / np.maximum(np.asarray(unshadowed, np.float32) @ _LUMA,
                                                                         np.float32(1e-30))
    return np.clip((share - np.float32(OPEN_NONE)) / np.float32(OPEN_FULL - OPEN_NONE), 0.0, 1.0).astype(np.float32)
